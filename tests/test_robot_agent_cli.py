"""`wsnav robot` as a user runs it: a subprocess against the real broker, the simulated TurtleBot3 in real time;
bad arguments, files and an unreachable broker as one line."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import SCHOOL
from tests.robot_agent_rig import connect
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.broker.mosquitto.process import free_port
from wsnav.schemas import topics
from wsnav.schemas.messages import ZoneState

WSNAV = [sys.executable, "-m", "wsnav.cli"]


def wsnav(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*WSNAV, *args], capture_output=True, text=True, timeout=timeout)


def robot_args(broker: BrokerThread, *extra: str) -> list[str]:
    creds = broker.credentials_dir / "robot1.json"
    address = f"{broker.host}:{broker.port}"
    return ["robot", "--site", str(SCHOOL), "--broker", address, "--credentials", str(creds), "--sim", *extra]


def test_robot_drives_to_a_near_goal_in_real_time_and_exits_0_on_arrival() -> None:
    with BrokerThread(SCHOOL) as broker:
        result = wsnav(*robot_args(broker, "--start", "A", "--goal", "13.0,7.2,0", "--exit-on-arrival"))
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert "robot robot1 on school (config full)" in lines[0]
    assert " navigating " in lines[1] and "plan=1.00m" in lines[1]
    assert " arrived " in lines[-1]
    x = float(lines[-1].split("pose=[")[1].split(",")[0])
    assert abs(x - 13.0) < 0.15


def test_a_goal_in_a_blocked_zone_exits_1_with_the_reason() -> None:
    with BrokerThread(SCHOOL) as broker:
        node = connect(broker, "n1")
        state = ZoneState(zone="z1", node="n1", state="blocked", seq=7)
        node.publish(topics.zone_state("school", "z1", "n1"), state.to_payload(), qos=1, retain=True)
        node.close()  # a clean disconnect delivers what was queued; the broker keeps the retained word
        result = wsnav(*robot_args(broker, "--start", "A", "--goal", "18,7.2", "--exit-on-arrival"))
    assert result.returncode == 1, result.stderr
    assert " cancelled " in result.stdout.splitlines()[-1]
    assert "z1" in result.stdout.splitlines()[-1]


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ({"--start": "nowhere"}, "--start 'nowhere': not a point of site 'school'"),
        ({"--goal": "0,0"}, "--goal [0, 0] lies inside"),
        ({"--config": "missing.yaml"}, "missing.yaml: no such agent config"),
        ({"--credentials": "missing.json"}, "missing.json: cannot read: No such file or directory"),
        ({"--sim": None}, "pass --sim (a simulated TurtleBot3) or --ros"),
        ({"--broker": "nohost"}, "argument --broker: expected HOST:PORT"),
        ({"--broker": "UNREACHABLE"}, "cannot connect to MQTT broker 127.0.0.1:"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(
    tmp_path: Path, change: dict[str, str | None], expected: str
) -> None:
    creds = tmp_path / "robot1.json"
    creds.write_text(
        json.dumps({"username": "robot1", "password": "x" * 20, "role": "robot", "site": "school"})
    )
    args = {"--site": str(SCHOOL), "--broker": "127.0.0.1:1", "--credentials": str(creds), "--start": "A"}
    args["--config"] = "full"
    sim = True
    for key, value in change.items():
        if value is None:
            sim = False
        elif value == "UNREACHABLE":
            args[key] = f"127.0.0.1:{free_port()}"
        else:
            args[key] = str(tmp_path / value) if value.endswith((".yaml", ".json")) else value
    argv = ["robot", *[p for kv in args.items() for p in kv], "--connect-timeout", "2"]
    if sim:
        argv.append("--sim")
    result = wsnav(*argv)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert expected in result.stderr


def test_a_bad_config_file_names_the_key(tmp_path: Path) -> None:
    bad = tmp_path / "agent.yaml"
    bad.write_text("zone_layer: true\nreplan_rate_hz: -1\n")
    from wsnav.robot_agent.agent_config import AgentConfigError, load_agent_config

    with pytest.raises(AgentConfigError, match=r"agent\.yaml: replan_rate_hz: Input should be greater"):
        load_agent_config(bad)
    bad.write_text("zone_layer: true\nunknown_knob: 3\n")
    with pytest.raises(AgentConfigError, match=r"unknown_knob: Extra inputs are not permitted"):
        load_agent_config(bad)


def test_the_shipped_configs_are_the_stock_turtlebot3_and_the_full_system() -> None:
    from wsnav.robot_agent.agent_config import load_agent_config

    default, full = load_agent_config("default"), load_agent_config("full")
    assert (default.zone_layer, default.replan_rate_hz, default.global_costmap_rate_hz) == (False, 5.0, 10.0)
    assert default.local_costmap_size_m == 3.0
    assert (full.zone_layer, full.replan_rate_hz) == (True, 0.0)
    assert full.local_costmap_size_m < default.local_costmap_size_m
    assert full.global_costmap_rate_hz < default.global_costmap_rate_hz


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 0)])
def test_ctrl_c_and_sigterm_stop_the_robot_cleanly(sig: signal.Signals, code: int) -> None:
    with BrokerThread(SCHOOL) as broker:
        proc = subprocess.Popen(
            [*WSNAV, *robot_args(broker, "--start", "A", "--goal", "B")],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            # A shell's background job inherits SIGINT ignored; a user's terminal delivers it.
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        assert proc.stdout is not None
        proc.stdout.readline()  # the banner: connected
        assert " navigating " in proc.stdout.readline()
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == code
    assert err == ""
    assert "Traceback" not in out
