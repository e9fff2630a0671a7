"""Over-the-air app update (`wsnav firmware ota`): how long the whole app takes over a broker loaded with zone
traffic, and the heap of update mode.

Time: a node on the MicroPython unix port (firmware/unix_board.py: boot.py and main.py in a folder, resets as a
board's) updated by firmware.ota.OtaServer through the project's broker (`wsnav broker run`), from the command to
the node's `info` with the new version (reboot, transfer, swap, trial boot, connect), and the transfer alone (first
request to last byte served). Load: every other node of the site publishing its zone state (retained, QoS 1) once
a second with its own credentials. Baseline in the same run: the same update on the idle broker; runs alternate
idle and loaded, updating the node back and forth between two builds of the same firmware.
Heap (32-bit: MicroPython's WebAssembly port with a 38 KiB heap, bench/wasm_port/setup_heap.mjs): the node after
setup for this tree and the baseline revision, update mode after setup and at the transfer's peak.
Writes its section of BENCHMARKS.md unless --no-write.
`--quick`: one idle and one loaded update, no heap rows, the firmware built with a trial of seconds
(testing.SHORT_TRIAL: each update waits out an 8 s healthy period, not 30 s); the loaded transfer over the idle
one at most 5.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import tempfile
import threading
import time
from collections.abc import Mapping
from pathlib import Path

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from bench.benchmarks_md import commit, machine_note, write_section
from bench.firmware_heap import WASM_PORT, build_revision, node_config, wasm_port_ready, wasm_setup
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser
from wsnav.broker.credentials import new_password
from wsnav.console.operator_commands import node_command
from wsnav.firmware.build import build
from wsnav.firmware.deploy import firmware_files
from wsnav.firmware.ota import OtaServer, Update, make_update
from wsnav.firmware.testing import (
    SHORT_TRIAL,
    SiteBroker,
    build_for_host,
    versioned_sources,
    write_credentials,
)
from wsnav.firmware.unix_board import UnixBoard
from wsnav.runtime.mqtt_bus import MqttBus
from wsnav.schemas import topics
from wsnav.schemas.credentials import Credentials, NodeConfig, load_credentials
from wsnav.schemas.messages import ZoneState
from wsnav.schemas.site import load_site

SECTION = "## Firmware: over-the-air update"
COMMAND = "./.venv/bin/python -m bench.firmware_ota"
SITE = Path(__file__).resolve().parent.parent / "sites" / "school"
NODE = "n1"
VERSIONS = ("bench-a", "bench-b")


class ZoneLoad:
    """Every node of the site but `NODE` publishing its zone state at 1 Hz, each with its own login."""

    def __init__(self, broker: SiteBroker, creds: Path) -> None:
        self.clients: list[tuple[mqtt.Client, str, bytes]] = []
        self._stop = threading.Event()
        self.sent = 0
        for node in load_site(SITE).spec.nodes:
            if node.id == NODE:
                continue
            c = load_credentials(creds / f"{node.id}.json")
            client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"{node.id}-load")
            client.username_pw_set(c.username, c.password)
            client.connect(broker.host, broker.port)
            client.loop_start()
            payload = ZoneState(zone=node.zone, node=node.id, state="clear", seq=1).to_payload()
            self.clients.append((client, topics.zone_state(SITE.name, node.zone, node.id), payload))
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(1.0):
            for client, topic, payload in self.clients:
                client.publish(topic, payload, qos=1, retain=True)
                self.sent += 1

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)
        for client, _t, _p in self.clients:
            client.loop_stop()
            client.disconnect()


def one_update(bus: MqttBus, update: Update, key: str, timeout_s: float = 300.0) -> tuple[float, float]:
    """(command to confirmed info, first request to last byte) in seconds, for one update of NODE, signed with
    NODE's update `key` as `wsnav firmware ota` signs it."""
    server = OtaServer(bus, SITE.name, update, [NODE], say=lambda _line: None)
    server.subscribe()  # again each run: the bus keeps one subscription per filter
    time.sleep(0.5)  # in place before the node can ask
    pub = node_command(load_site(SITE), NODE, "update", manifest=update.signature(key))
    t0 = time.monotonic()
    if not bus.publish_confirmed(pub.topic, pub.payload):
        raise SystemExit("firmware_ota: the broker did not confirm the update command")
    failures = server.run(timeout_s)
    total = time.monotonic() - t0
    if failures:
        raise SystemExit(f"firmware_ota: {failures[0]}")
    prog = server.progress[NODE]
    assert prog.first_at is not None and prog.last_at is not None
    return total, prog.last_at - prog.first_at


CONFIG_SCRIPT = """
import sys
import nodeconfig
CFG = nodeconfig.load("/config.json")
del nodeconfig
del sys.modules["nodeconfig"]
gc.collect()
import otaboot
import updater
link = updater.Fetcher(CFG)
import wifi
w = wifi.Wifi(CFG["wifi_ssid"], CFG["wifi_password"])
import json
with open("/config.json") as f:
    KEY = json.load(f)["update_key"].encode()
gc.collect()
def get(index, size, digest, out, key=None):
    with open("/data.bin", "rb") as f:
        out.write(f.read())
link.get = get
_save = otaboot.save
def save(st):
    gc.collect()
    print("bench config_used", gc.mem_alloc())
    _save(st)
otaboot.save = save
import otaconfig
otaconfig.fetch(link, {"stage": "config", "manifest": "0" * 64, "boots": 0}, KEY)
"""
"""Update mode opening a configuration (device/otaconfig.py, loaded by the updater as for a `config` command), as
the update script of setup_heap.mjs sets update mode up; the chunk comes from /data.bin instead of the broker
(`get` stands for the updater's fetch, whose own peak is the update rows'). Measured when otaconfig saves its
state (`otaboot.save`): the sealed chunk, the settings and the merged config.json are still held then. That is
inside one call, where the WebAssembly port frees nothing (bench/wasm_port/setup_heap.mjs), so the figure counts
the garbage of the whole setup too: a bound below what the board has free there."""


def config_heap(
    node: str, device: Path, config: Path, settings: Mapping[str, object], tmp: Path, numbered: bool = True
) -> int:
    """Free heap (32-bit, 38 KiB) in update mode at the end of opening `settings` sealed for the node, with their
    number (`seq`) unless not `numbered` (a firmware from before numbers, which refuses one)."""
    from wsnav.schemas.credentials import config_seq, seal_config

    key = NodeConfig.model_validate_json(config.read_text()).update_key
    assert key is not None
    data = {**settings, "seq": config_seq(time.time())} if numbered else settings
    (tmp / "sealed.bin").write_bytes(seal_config(key, json.dumps(data).encode(), bytes(16)))
    (tmp / "config_heap.py").write_text(CONFIG_SCRIPT)
    cmd = [node, str(WASM_PORT / "setup_heap.mjs"), str(device), str(config), str(tmp / "config_heap.py")]
    proc = subprocess.run(
        [*cmd, str(tmp / "sealed.bin")], capture_output=True, text=True, timeout=300, check=False
    )
    lines = proc.stdout.splitlines()
    peak = [int(line.split()[1]) for line in lines if line.startswith("config_used ")]
    final = [line.split() for line in lines if line.startswith("heap ")]
    if not peak or not final:
        raise SystemExit(f"setup_heap.mjs (configuration): {(proc.stdout + proc.stderr).strip()[-300:]}")
    words = final[0]
    return dict(zip(words[1::2], map(int, words[2::2]), strict=True))["total"] - peak[0]


def takes_numbers(revision: str) -> bool:
    """Whether `revision`'s otaconfig wants a configuration's number (`seq`): from 2026-11-28 on it refuses one
    without; before, it refuses one with."""
    source = subprocess.run(
        ["git", "show", f"{revision}:firmware/device/otaconfig.py"],
        capture_output=True,
        text=True,
        check=False,
    )
    return '"seq"' in source.stdout


def heap_rows(tmp: Path, creds: Path, update: Update, baseline: str) -> list[tuple[str, int]]:
    node = wasm_port_ready()
    build(tmp / "heap-build")
    pir = node_config(creds, tmp / "pir.json", "127.0.0.1", 1)
    sonar_sensor = {"type": "hcsr04", "trigger_pin": 12, "echo_pin": 14, "threshold_m": 1.0, "samples": 15}
    sonar = node_config(creds, tmp / "sonar.json", "127.0.0.1", 1, sonar_sensor)
    base, _stubs = build_revision(baseline, tmp / "baseline")
    manifest = tmp / "manifest.json"
    manifest.write_bytes(update.payloads[0])
    proc = subprocess.run(
        [node, str(WASM_PORT / "setup_heap.mjs"), str(tmp / "heap-build"), str(pir), str(manifest)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    words = proc.stdout.split()
    if words[:1] != ["heap"]:
        raise SystemExit(f"setup_heap.mjs (update mode): {(proc.stdout + proc.stderr).strip()[-300:]}")
    up = dict(zip(words[1::2], map(int, words[2::2]), strict=True))
    wifi: dict[str, object] = {"wifi": {"ssid": "school-iot-2", "password": "a-new-wifi-key-0123456789"}}
    password = {"password": new_password()}
    every = {**wifi, "broker": {"host": "192.168.10.20", "port": 1883}, **password}
    opened = "update mode opening a configuration"
    return [
        ("PIR node after setup", wasm_setup(node, tmp / "heap-build", pir)["free"]),
        (f"PIR node after setup, {baseline}'s firmware (baseline)", wasm_setup(node, base, pir)["free"]),
        ("HC-SR04 node (15 samples) after setup", wasm_setup(node, tmp / "heap-build", sonar)["free"]),
        (
            f"HC-SR04 node (15 samples) after setup, {baseline}'s firmware",
            wasm_setup(node, base, sonar)["free"],
        ),
        ("update mode after setup (updater, MQTT client, Wi-Fi)", up["setup_free"]),
        ("update mode during the transfer (the manifest's files, a chunk, sha256, open .tmp)", up["free"]),
        (
            f"{opened}: Wi-Fi, {baseline}'s firmware",
            config_heap(node, base, pir, wifi, tmp, numbered=takes_numbers(baseline)),
        ),
        (f"{opened}: Wi-Fi", config_heap(node, tmp / "heap-build", pir, wifi, tmp)),
        (f"{opened}: MQTT password", config_heap(node, tmp / "heap-build", pir, password, tmp)),
        (
            f"{opened}: Wi-Fi and MQTT password",
            config_heap(node, tmp / "heap-build", pir, {**wifi, **password}, tmp),
        ),
        (
            f"{opened}: Wi-Fi, broker and MQTT password",
            config_heap(node, tmp / "heap-build", pir, every, tmp),
        ),
    ]


def main() -> None:
    parser = quick_parser(__doc__)
    parser.add_argument("--runs", type=int, default=3, help="updates per condition (default 3)")
    parser.add_argument(
        "--baseline", default="main", help="git revision for the heap baseline (default main)"
    )
    args = parse_quick_args(parser)
    if args.quick:
        args.runs = 1
    with tempfile.TemporaryDirectory(prefix="wsnav-fw-ota-") as tmp_name:
        tmp = Path(tmp_name)
        stubs = build_for_host(tmp / "host")[1]
        consts = SHORT_TRIAL if args.quick else None
        updates = [
            make_update(tmp / f"build-{v}", versioned_sources(tmp / f"src-{v}", v, None, consts))
            for v in VERSIONS
        ]
        creds = tmp / "creds"
        write_credentials(SITE, creds)
        heap = [] if args.quick else heap_rows(tmp, creds, updates[0], args.baseline)
        broker = SiteBroker(SITE, creds, tmp / "broker-data")
        broker.start()
        fs = tmp / "fs"
        fs.mkdir()
        data = json.loads((creds / f"{NODE}.json").read_text())
        data["broker"] = {"host": broker.host, "port": broker.port}
        data["sensor"]["warmup_s"] = 0
        (tmp / "config.json").write_text(NodeConfig.model_validate(data).model_dump_json())
        for name, path in firmware_files(tmp / f"build-{VERSIONS[0]}", tmp / "config.json").items():
            (fs / name).write_bytes(path.read_bytes())
        (tmp / "pins").mkdir()
        board = UnixBoard(fs, stubs, tmp / "serial.log", tmp / "pins")
        op = Credentials.model_validate_json((creds / "operator.json").read_text())
        node_key = NodeConfig.model_validate_json((creds / f"{NODE}.json").read_text()).update_key
        assert node_key is not None  # wsnav broker credentials writes one for every node
        bus = MqttBus(
            broker.host,
            broker.port,
            client_id="operator-bench-ota",
            username=op.username,
            password=op.password,
        ).connect(30)
        times: dict[str, list[tuple[float, float]]] = {"idle": [], "loaded": []}
        try:
            board.power_on()
            time.sleep(5)  # the first version up and connected
            for k in range(2 * args.runs):
                load = ZoneLoad(broker, creds) if k % 2 else None
                if load is not None:
                    load.start()
                    time.sleep(2)
                try:
                    result = one_update(bus, updates[(k + 1) % 2], node_key)
                finally:
                    if load is not None:
                        load.stop()
                condition = "idle" if load is None else "loaded"
                times[condition].append(result)
                print(f"{condition}: {result[0]:.2f} s in all, transfer {result[1]:.2f} s", flush=True)
        finally:
            bus.close()
            board.close()
            broker.kill()
    total_bytes = updates[0].total
    files = len(updates[0].manifest.files)
    idle_total = statistics.median(t for t, _ in times["idle"])
    loaded_total = statistics.median(t for t, _ in times["loaded"])
    idle_xfer = statistics.median(x for _, x in times["idle"])
    loaded_xfer = statistics.median(x for _, x in times["loaded"])
    if args.quick:
        check_ratio("transfer on the loaded broker over the idle one", loaded_xfer / idle_xfer, 5.0)
        finish_quick()
    rows = [
        ("idle broker (baseline)", idle_total, idle_xfer),
        ("8 nodes' zone states at 1 Hz each", loaded_total, loaded_xfer),
    ]
    table = [
        "| broker | command to new version confirmed, s | transfer, s | transfer, ratio to baseline |",
        "| --- | ---: | ---: | ---: |",
        *(f"| {name} | {t:.2f} | {x:.2f} | {x / idle_xfer:.2f} |" for name, t, x in rows),
    ]
    heap_base = heap[1][1]
    heap_table = [
        "| free heap after gc.collect(), 32-bit, 38 KiB | bytes | of the baseline node's |",
        "| --- | ---: | ---: |",
        *(f"| {name} | {value} | {value / heap_base:.2f} |" for name, value in heap),
    ]
    text = (
        f"{machine_note()}, commit {commit()}. The update: {files} modules, {total_bytes} B with the manifest, in 512-byte chunks "
        f"(`wsnav firmware ota`'s, firmware/ota.py), median of {args.runs} runs per broker. The node is the "
        "MicroPython unix port (firmware/unix_board.py), updated through `wsnav broker run` on this machine: the "
        "numbers are the protocol's and the broker's, not an ESP8266's, whose Wi-Fi round trips and flash "
        "writes add to every chunk. `command to new version confirmed` counts the reboot into update mode, the "
        "transfer, the swap, the trial boot, its first connect, and the healthy period the node runs before it "
        "confirms (30 s after boot and two states sent: app._HEALTHY_S, health.py), which `wsnav firmware ota` "
        "waits for.\n\n"
        + "\n".join(table)
        + "\n\nHeap, on MicroPython's WebAssembly port (32-bit: the ESP8266's object sizes; bench/wasm_port, "
        "setup_heap.mjs): the node in normal operation does not load the updater; update mode loads only the "
        "updater, the MQTT client and Wi-Fi (otaboot.py stays loaded under them), and its peak holds the parsed "
        "manifest's file list, a chunk in the client's buffer, the sha256 and the open `.tmp` file (the update key, "
        "64 bytes, is held only while the manifest is checked, before that). A configuration (`wsnav firmware "
        "config`) is opened in update mode by otaconfig.py, measured when it saves its state: the sealed chunk, the "
        "settings and the merged config.json still held (CONFIG_SCRIPT; the chunk read from a file, not fetched; "
        "these figures move by hundreds of bytes with the heap's layout, not only with the settings' size). Those "
        "rows are read inside the call, where the WebAssembly port frees nothing, so they count the setup's garbage "
        "too: bounds below what the board has free there (the other rows are read after a collection). The "
        "board's boot (`_boot.py`, about 1.2 KB, BENCHMARKS.md's firmware heap section) is not taken off.\n\n"
        + "\n".join(heap_table)
        + f"\n\nReproduce: `{COMMAND}` (`--runs N`, `--baseline REF`; needs Node.js and npm for the heap rows)."
    )
    print(text)
    if not args.no_write:
        write_section(SECTION, text)


if __name__ == "__main__":
    main()
