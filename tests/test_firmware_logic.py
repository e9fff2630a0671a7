"""The firmware's pure logic modules (firmware/device) under CPython, as the zone simulator imports them, and
the same checks on the MicroPython VM with the ESP8266's heap."""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from wsnav import firmware
from wsnav.firmware.testing import HOST_STUBS, build_for_host, micropython_cmd, micropython_env
from wsnav.schemas import topics
from wsnav.schemas.credentials import NodeConfig
from wsnav.schemas.messages import NodeInfo, NodeStatus, ZoneState, ZoneStateValue, parse_payload
from wsnav.schemas.site_file import pin_problem

# Loaded as the zone simulator loads them (pyright cannot follow a module loaded at run time).
_device: dict[str, Any] = firmware.load_device_modules(
    "logic_checks", "diagnostics", "node_logic", "nodeconfig", "payloads", extra_dirs=[HOST_STUBS]
)
logic_checks: Any = _device["logic_checks"]
diagnostics: Any = _device["diagnostics"]
node_logic: Any = _device["node_logic"]
nodeconfig: Any = _device["nodeconfig"]
payloads: Any = _device["payloads"]


@pytest.mark.parametrize("check", logic_checks.CHECKS, ids=lambda c: c.__name__)
def test_logic_on_cpython(check: Callable[[], None]) -> None:
    check()


def test_logic_on_micropython(tmp_path: Path) -> None:
    device, stubs = build_for_host(tmp_path)
    proc = subprocess.run(
        micropython_cmd("logic_checks"),
        env=micropython_env(device, stubs),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.stdout.strip() == f"ok {len(logic_checks.CHECKS)}", proc.stdout + proc.stderr


STATES: list[ZoneStateValue] = ["blocked", "clear", "caution"]


def test_payloads_match_the_schema_models_byte_for_byte() -> None:
    rng = random.Random(7)
    alphabet = "abcXYZ019_-"
    for _ in range(500):
        site, zone, node = ("".join(rng.choices(alphabet, k=rng.randint(1, 32))) for _ in range(3))
        state: ZoneStateValue = rng.choice(STATES)
        seq = rng.randint(0, payloads.SEQ_MAX)
        assert (
            payloads.zone_state_payload(zone, node, state, seq)
            == ZoneState(zone=zone, node=node, state=state, seq=seq).to_payload()
        )
        assert payloads.zone_state_topic(site, zone, node) == topics.zone_state(site, zone, node)
        assert payloads.node_status_topic(site, node) == topics.node_status(site, node)
        for status in ("online", "offline"):
            assert (
                payloads.node_status_payload(node, status)
                == NodeStatus(node=node, status=status).to_payload()
            )


def test_diagnostics_match_the_schema_model_byte_for_byte() -> None:
    """Whatever the node measures and whatever its last error said (quotes, backslashes, non-ASCII, too long),
    diagnostics.info writes exactly what NodeInfo accepts and serialises, and at most ~200 bytes of it (the
    largest free block of the board's heap after connecting is a few hundred)."""
    rng = random.Random(11)
    errors = [None, "wifi lost", OSError(113), 'say "hi"\\ now', "dns \u00e9chec \u2603", "x" * 200]
    names = ["power_on", "watchdog", "exception", "soft_wdt", "soft_reset", "deep_sleep", "reset_pin"]
    for _ in range(300):
        node = "".join(rng.choices("abcXYZ019_-", k=rng.randint(1, 32)))
        logic = node_logic.NodeLogic("s", "z1", node, 0, 0, 1000)
        error = rng.choice(errors)
        cause, connects = rng.randint(-1, 9), rng.randint(0, 5)
        uptime_s, rssi, heap = (
            rng.randint(0, 2**30),
            rng.choice([None, 31, -40, -90]),
            rng.choice([None, 9000]),
        )
        trial = rng.random() < 0.5
        topic, text, retain, qos = diagnostics.info(logic, uptime_s, connects, cause, rssi, heap, error)
        if trial:  # what app.Node._send_info appends during an update's trial: NodeInfo's last field
            text = text[:-1] + ',"trial":true}'
        payload = text.encode()  # what the board's MQTT client sends (a str's UTF-8 bytes)
        info = parse_payload(NodeInfo, payload)
        assert info.to_payload() == payload and (topic, retain, qos) == (topics.node_info("s", node), True, 0)
        assert len(payload) <= 200 + len(node) + (13 if trial else 0), payload  # 13: ,"trial":true
        assert info.reset == (names[cause] if 0 <= cause < 7 else "unknown")
        assert info.rssi == (None if rssi == 31 else rssi) and info.heap_free == heap
        assert info.uptime_s == uptime_s and info.reconnects == max(connects - 1, 0)
        assert (info.error is None) == (error is None) and (info.error is None or len(info.error) <= 32)
        assert info.trial is (True if trial else None)


def test_nodes_that_reconnect_together_do_not_heartbeat_in_step() -> None:
    """After a broker restart every board reconnects within the same second; each one's first heartbeat comes
    between half a period and a period later at its own offset, so the broker does not get them all at once,
    and the period after that is the configured one."""
    rng = random.Random(5)
    heartbeat_ms = 10000
    nodes = [
        node_logic.NodeLogic("s", "z1", f"n{i}", 0, 0, heartbeat_ms, rng.getrandbits(20)) for i in range(200)
    ]
    for n in nodes:
        n.on_connect(0)
    first: list[int] = []
    for n in nodes:
        t = 0
        while n.step(False, t) is None:
            t += 50  # the board's loop period
        first.append(t)
        assert n.step(False, t + heartbeat_ms - 50) is None and n.step(False, t + heartbeat_ms) is not None
    assert all(heartbeat_ms // 2 <= t <= heartbeat_ms for t in first), first
    busiest = max(sum(1 for t in first if w <= t < w + 100) for w in range(0, heartbeat_ms, 50))
    assert busiest <= len(nodes) // 10, busiest  # in step, all 200 would fall in one 100 ms window


def test_the_only_modules_simulators_may_import_are_pure() -> None:
    """No board module sneaks into PURE_MODULES: each imports on CPython without machine/network."""
    firmware.load_device_modules(*firmware.PURE_MODULES)
    for name in ("machine", "network"):
        assert name not in sys.modules


def test_board_module_names_stay_out_of_the_top_level_where_a_pypi_package_has_them(tmp_path: Path) -> None:
    """A PyPI package named like a board module (`backoff` exists) must neither break the simulator nor be
    replaced by our module: the board's names live under wsnav.firmware.device only."""
    (tmp_path / "backoff.py").write_text("ON_PYPI = True\n")
    code = (
        "import backoff; from wsnav.zone_sim import firmware_modules as fm; import sys; "
        "assert backoff.ON_PYPI and sys.modules['backoff'] is backoff; "
        "assert fm.Backoff.__module__ == 'wsnav.firmware.device.backoff'; "
        "assert not {'payloads', 'node_logic', 'debounce', 'sensing'} & set(sys.modules); print('ok')"
    )
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert proc.stdout.strip() == "ok", proc.stderr


def base_config(**changes: Any) -> dict[str, Any]:
    data: dict[str, Any] = {
        "username": "n1",
        "password": "x" * 24,
        "role": "node",
        "site": "school",
        "broker": {"host": "10.0.0.2", "port": 1883},
        "node": "n1",
        "zone": "z1",
        "sensor": {"type": "pir", "pin": 5},
        "heartbeat_s": 5.0,
        "on_delay_ms": 500,
        "off_delay_ms": 3000,
    }
    data.update(changes)
    return data


@pytest.mark.parametrize(
    "sensor",
    [
        {"type": "pir", "pin": 5},
        {"type": "ir_beam", "pin": 4, "invert": True},
        {"type": "hcsr04", "trigger_pin": 12, "echo_pin": 14, "threshold_m": 0.8, "samples": 7},
        {"type": "hcsr04", "trigger_pin": 12, "echo_pin": 14, "threshold_m": 0.8, "caution_m": 1.5},
    ],
)
def test_config_accepts_what_the_schema_accepts(sensor: dict[str, Any], tmp_path: Path) -> None:
    model = NodeConfig.model_validate(base_config(sensor=sensor))
    path = tmp_path / "config.json"
    path.write_text(model.model_dump_json())
    cfg = nodeconfig.load(str(path))
    assert (cfg["site"], cfg["node"], cfg["zone"]) == ("school", "n1", "z1")
    assert cfg["heartbeat_ms"] == 5000 and cfg["keepalive_s"] == 30 and cfg["broker_port"] == 1883
    assert cfg["sensor_type"] == sensor["type"]
    if sensor["type"] == "hcsr04":
        assert (cfg["trigger_pin"], cfg["echo_pin"], cfg["threshold_mm"]) == (12, 14, 800)
        assert cfg["samples"] == sensor.get("samples", 5)
        assert cfg["caution_mm"] == (1500 if "caution_m" in sensor else 0)
    else:
        assert (cfg["pin"], cfg["invert"]) == (sensor["pin"], sensor.get("invert", False))


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"node": "n/1"}, "node is not a valid id"),
        ({"broker": {"host": "", "port": 1883}}, "broker.host is empty"),
        ({"heartbeat_s": True}, "heartbeat_s must be a number"),
        ({"on_delay_ms": 1.5}, "on_delay_ms must be an integer"),
        ({"sensor": {"type": "pir"}}, "missing key sensor.pin"),
        ({"sensor": {"type": "pir", "pin": 17}}, "sensor.pin must be a GPIO the sensor can use"),
        ({"sensor": {"type": "ir_beam", "pin": 1}}, "sensor.pin must be a GPIO the sensor can use"),
        ({"sensor": {"type": "sonar", "pin": 1}}, "sensor.type must be pir, ir_beam or hcsr04"),
        ({"keepalive_s": 2}, "keepalive_s must be in [5, 3600]"),
        (
            {
                "sensor": {
                    "type": "hcsr04",
                    "trigger_pin": 12,
                    "echo_pin": 14,
                    "threshold_m": 1,
                    "caution_m": 0.5,
                }
            },
            "sensor.caution_m must be beyond threshold_m",
        ),
        (
            {"sensor": {"type": "hcsr04", "trigger_pin": 12, "echo_pin": 14, "caution_m": "far"}},
            "sensor.caution_m must be a number",
        ),
    ],
)
def test_config_errors_name_the_key(changes: dict[str, Any], message: str, tmp_path: Path) -> None:
    path = tmp_path / "config.json"
    path.write_text(json.dumps(base_config(**changes)))
    with pytest.raises(nodeconfig.ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        nodeconfig.load(str(path))


SENSOR_LINES: list[tuple[str, str, bool, bool]] = [
    # (sensor type, key, an input, pulled up)
    ("pir", "pin", True, False),
    ("ir_beam", "pin", True, True),
    ("hcsr04", "trigger_pin", False, False),
    ("hcsr04", "echo_pin", True, False),
]


def sensor_on(kind: str, key: str, pin: int) -> dict[str, Any]:
    if kind == "hcsr04":
        sensor: dict[str, Any] = {"type": kind, "trigger_pin": 12, "echo_pin": 14}
        if key == "echo_pin" and pin == 12:
            sensor["trigger_pin"] = 13
        if key == "trigger_pin" and pin == 14:
            sensor["echo_pin"] = 13
    else:
        sensor = {"type": kind}
    sensor[key] = pin
    return sensor


@pytest.mark.parametrize(("kind", "key", "is_input", "pull_up"), SENSOR_LINES)
def test_the_board_and_the_site_check_refuse_the_same_pins(
    kind: str, key: str, is_input: bool, pull_up: bool
) -> None:
    """GPIO1/3 (serial console) and 6-11 (SPI flash) never; 0, 2, 15 (boot mode) not as inputs; 16 not for an IR
    receiver (no pull-up). The schema (site check, credentials, deploy) names the problem; the board's own
    parser refuses the same pins with one message."""
    refused = []
    for pin in range(17):
        why = pin_problem(pin, is_input, pull_up)
        try:
            NodeConfig.model_validate(base_config(sensor=sensor_on(kind, key, pin)))
            schema_ok = True
        except ValueError as exc:
            schema_ok = False
            assert f"sensor.{key}" in str(exc) or key in str(exc)
        try:
            nodeconfig.parse(base_config(sensor=sensor_on(kind, key, pin)))
            board_ok = True
        except nodeconfig.ConfigError as exc:
            board_ok = False
            assert f"sensor.{key} must be a GPIO the sensor can use" in str(exc)
        assert schema_ok == board_ok == (why is None), (pin, why)
        if why is not None:
            refused.append(pin)
    expected = {1, 3, 6, 7, 8, 9, 10, 11} | ({0, 2, 15} if is_input else set()) | ({16} if pull_up else set())
    assert set(refused) == expected


def test_an_ultrasonic_sensor_needs_two_pins() -> None:
    sensor = {"type": "hcsr04", "trigger_pin": 12, "echo_pin": 12}
    with pytest.raises(ValueError, match="must differ from trigger_pin"):
        NodeConfig.model_validate(base_config(sensor=sensor))
    with pytest.raises(nodeconfig.ConfigError, match=r"sensor\.echo_pin must be a GPIO the sensor can use"):
        nodeconfig.parse(base_config(sensor=sensor))


def test_site_file_rejects_a_caution_band_inside_the_blocking_distance() -> None:
    sensor = {"type": "hcsr04", "trigger_pin": 12, "echo_pin": 14, "threshold_m": 1.0, "caution_m": 1.0}
    with pytest.raises(ValueError, match=r"caution_m \(1.0\) must be farther than threshold_m \(1.0\)"):
        NodeConfig.model_validate(base_config(sensor=sensor))


def test_config_file_problems(tmp_path: Path) -> None:
    with pytest.raises(nodeconfig.ConfigError, match="cannot read"):
        nodeconfig.load(str(tmp_path / "missing.json"))
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    with pytest.raises(nodeconfig.ConfigError, match="not valid JSON"):
        nodeconfig.load(str(bad))
