"""Mosquitto: what keeping an acknowledged operator block through a kill -9 costs (issue 37): saving the store on
every change, against saves every 60 or 2 s, and against wsnav's plugin journaling only the blocks.

A bare Mosquitto 2.0 (persistence on, the store on this machine's disk) holds `--topics` retained messages
(150 B, a zone state's size); one client publishes retained QoS 1 updates over them at `--rate` a second (1000
nodes at 1 Hz), another subscribes to all and measures each update's latency, and an operator sets a retained
QoS 1 block every 0.1-0.3 s (random gaps) and times its PUBACK. Per configuration: Mosquitto's CPU (from /proc),
the bytes it wrote (/proc/<pid>/io), the updates' latency p50/p99 and the blocks' PUBACK p50/p99. With
`autosave_on_changes` and `autosave_interval 1`, Mosquitto rewrites its whole store after every change; with
wsnav's plugin (`broker/mosquitto/store_guard.c`, built here) each block is written and fdatasync'd to a journal
before its PUBACK: either way a block acknowledged just before a kill -9 survives (tests/test_broker_process.py).

    python -m bench.mosquitto_autosave [--topics 1000] [--rate 1000] [--seconds 10] [--no-write]
    python -m bench.mosquitto_autosave --quick    # 60 s, 2 s and 2 s + the plugin: 500 topics, 500/s, 4 s
"""

from __future__ import annotations

import os
import random
import shutil
import statistics
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from bench.benchmarks_md import commit, machine_note, write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser
from wsnav.broker.mosquitto.plugin import PluginBuildError, build_plugin
from wsnav.broker.mosquitto.process import free_port

HEADING = "## Mosquitto: saving the store on every change (kill -9 safety) vs every 60 s"
BLOCKS = "bench/blocks/"
"""The operator blocks' topics here (the plugin's prefix); the zone updates go to bench/z<i>."""
CONFIGS = {
    "every 60 s (before)": ["autosave_interval 60"],
    "every 6 s (`autosave_interval 5`)": ["autosave_interval 5"],
    "every 2 s (`autosave_interval 1`)": ["autosave_interval 1"],
    "after 100 changes": ["autosave_on_changes true", "autosave_interval 100"],
    "after every change": ["autosave_on_changes true", "autosave_interval 1"],
    "every 2 s + wsnav's plugin journaling blocks (chosen)": [
        "autosave_interval 1",
        "plugin {plugin}",
        "plugin_opt_journal {data}/operator-blocks.journal",
        f"plugin_opt_topic_prefix {BLOCKS}",
        "plugin_opt_store {data}/mosquitto.db",
    ],
}
CHOSEN = "every 2 s + wsnav's plugin journaling blocks (chosen)"
WITHOUT_PLUGIN = "every 2 s (`autosave_interval 1`)"


@dataclass(frozen=True)
class Result:
    name: str
    cpu_s: float
    written_mb: float
    p50_ms: float
    p99_ms: float
    received: int
    sent: int
    ack_p50_ms: float
    ack_p99_ms: float
    blocks: int


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _written(pid: int) -> int:
    for line in Path(f"/proc/{pid}/io").read_text().splitlines():
        if line.startswith("write_bytes:"):
            return int(line.split()[1])
    return 0


def _percentiles(values: list[float]) -> tuple[float, float]:
    """p50 and p99 in ms (nan when empty)."""
    ordered = sorted(values) or [float("nan")]
    return statistics.median(ordered) * 1000, ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))] * 1000


def run(
    name: str, lines: list[str], topics: int, rate: float, seconds: float, root: Path, plugin: Path | None
) -> Result:
    exe = shutil.which("mosquitto")
    if exe is None:
        raise SystemExit("mosquitto is not installed (Debian: apt-get install mosquitto)")
    data = root / "".join(c if c.isalnum() else "-" for c in name)
    data.mkdir(parents=True)
    port = free_port()
    conf = data / "mosquitto.conf"
    user = ["user root"] if os.geteuid() == 0 else []
    conf.write_text(
        "\n".join(
            [f"listener {port} 127.0.0.1", "allow_anonymous true", "persistence true",
             f"persistence_location {data}/", "max_queued_messages 100000", "log_dest none", *user,
             *(line.format(plugin=plugin, data=data) for line in lines)]
        ) + "\n"
    )  # fmt: skip
    proc = subprocess.Popen([exe, "-c", str(conf)], stderr=subprocess.DEVNULL)
    latencies: list[float] = []
    acks: list[float] = []
    block_sent: dict[int, float] = {}
    rng = random.Random(7)
    try:
        time.sleep(0.5)
        sub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-sub")

        def on_message(_c: object, _u: object, msg: mqtt.MQTTMessage) -> None:
            if not msg.retain and not msg.topic.startswith(BLOCKS):
                latencies.append(time.monotonic() - float(msg.payload[:20]))

        sub.on_message = on_message
        sub.connect("127.0.0.1", port)
        sub.loop_start()
        sub.subscribe("bench/#", 1)
        pub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-pub")
        pub.max_inflight_messages_set(1000)
        pub.max_queued_messages_set(0)
        pub.connect("127.0.0.1", port)
        pub.loop_start()
        operator = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-operator")

        def on_publish(_c: object, _u: object, mid: int, _rc: object, _p: object) -> None:
            sent_at = block_sent.pop(mid, None)
            if sent_at is not None:
                acks.append(time.monotonic() - sent_at)

        operator.on_publish = on_publish
        operator.connect("127.0.0.1", port)
        operator.loop_start()
        for i in range(topics):  # the site's retained messages, before the measurement
            pub.publish(
                f"bench/z{i}", b"%20.6f" % time.monotonic() + b"x" * 130, qos=1, retain=True
            ).wait_for_publish(10)
        time.sleep(1.0)
        latencies.clear()
        cpu0, written0 = _cpu_s(proc.pid), _written(proc.pid)
        start = time.monotonic()
        sent = blocks = 0
        next_block = start + rng.uniform(0.1, 0.3)
        while (now := time.monotonic()) < start + seconds:
            if now >= next_block:
                payload = b'{"zone": "z%d", "reason": "spill"}' % (blocks % 10)
                at = time.monotonic()
                info = operator.publish(f"{BLOCKS}b{blocks % 10}", payload, qos=1, retain=True)
                block_sent[info.mid] = at
                blocks += 1
                next_block = now + rng.uniform(0.1, 0.3)
            due = int((now - start) * rate)
            while sent < due:
                pub.publish(
                    f"bench/z{sent % topics}", b"%20.6f" % time.monotonic() + b"x" * 130, qos=1, retain=True
                )
                sent += 1
            time.sleep(0.005)
        time.sleep(1.0)
        cpu, written = _cpu_s(proc.pid) - cpu0, _written(proc.pid) - written0
        pub.loop_stop()
        sub.loop_stop()
        operator.loop_stop()
    finally:
        proc.terminate()
        proc.wait(30)
    p50, p99 = _percentiles(latencies)
    ack_p50, ack_p99 = _percentiles(acks)
    return Result(name, cpu, written / 1e6, p50, p99, len(latencies), sent, ack_p50, ack_p99, blocks)


QUICK = {"topics": 500, "rate": 500.0, "seconds": 4.0}
QUICK_CONFIGS = ("every 60 s (before)", WITHOUT_PLUGIN, CHOSEN)
QUICK_BOUNDS = {"CPU": 5.0, "latency p50": 10.0}
"""The chosen save (every 2 s and the plugin) over every 60 s, same run: about 1.2x CPU and 1x latency
measured; saving after every change gave 4.4-17.8x CPU."""


def main(argv: list[str] | None = None) -> int:
    parser = quick_parser(__doc__)
    parser.add_argument("--topics", type=int, default=1000)
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parse_quick_args(parser, argv)
    if args.quick:
        args.topics, args.rate, args.seconds = int(QUICK["topics"]), QUICK["rate"], QUICK["seconds"]
    configs = {n: c for n, c in CONFIGS.items() if not args.quick or n in QUICK_CONFIGS}
    with tempfile.TemporaryDirectory(dir=os.environ.get("WSNAV_BENCH_DIR", "/var/tmp")) as root:
        try:
            plugin = build_plugin(Path(root) / "plugin")
        except PluginBuildError as exc:
            raise SystemExit(f"cannot build wsnav's Mosquitto plugin: {exc}") from None
        results = [
            run(n, lines, args.topics, args.rate, args.seconds, Path(root), plugin)
            for n, lines in configs.items()
        ]
    base = results[0]
    rows = [
        "| store saved | Mosquitto CPU | written | update latency p50 / p99 | received | block PUBACK p50 / p99 |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for r in results:
        rows.append(
            f"| {r.name} | {r.cpu_s:.2f} s ({r.cpu_s / max(base.cpu_s, 1e-9):.1f}x) | {r.written_mb:.1f} MB "
            f"| {r.p50_ms:.2f} / {r.p99_ms:.2f} ms "
            f"({r.p50_ms / base.p50_ms:.1f}x / {r.p99_ms / base.p99_ms:.1f}x) | {r.received}/{r.sent} "
            f"| {r.ack_p50_ms:.2f} / {r.ack_p99_ms:.2f} ms "
            f"({r.ack_p50_ms / base.ack_p50_ms:.1f}x / {r.ack_p99_ms / base.ack_p99_ms:.1f}x) |"
        )
    text = (
        f"`python -m bench.mosquitto_autosave --topics {args.topics} --rate {args.rate:g} --seconds "
        f"{args.seconds:g}` (commit {commit()}, {machine_note()}; `uptime` load averages "
        f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}): a bare Mosquitto "
        f"{_version()} holding {args.topics} retained messages, {args.rate:g} retained QoS 1 updates a second over "
        f"them for {args.seconds:g} s, and an operator block every 0.1-0.3 s; the store and the plugin's journal on "
        f"{_filesystem()}; ratios to the first row, measured in the same run.\n\n"
        + "\n".join(rows)
        + "\n\nMosquitto saves once more than `autosave_interval` whole seconds have passed (1 means every 2 s) "
        "and rewrites its whole store each time. After every change (the only setting that keeps a block "
        "acknowledged just before a kill -9) it rewrites the whole store hundreds of times a second, at many "
        "times the CPU (the table; 4.4x and deliveries seconds late in a run at load 8); after 100 changes still writes tens of MB and leaves a quiet site's block unsaved "
        "until 99 other changes come. Every 2 s costs about what every 60 s costs but loses what was acknowledged "
        "in the last 2 s. wsnav's plugin (`wsnav broker mosquitto-config --store-guard`) writes and fdatasyncs "
        "only the operator blocks, before their PUBACK, so a block survives a kill -9 "
        "(`tests/test_broker_process.py`) for the price of one small synced write per block (the PUBACK column) "
        "and nothing on the zone updates: the generated config's choice with `--store-guard`. The zone states "
        "themselves are not journaled: the nodes' next heartbeat brings them back. p99 is noisy on a loaded "
        "machine."
    )
    print(text)
    if args.quick:
        chosen = next(r for r in results if r.name == CHOSEN)
        check_ratio(
            "Mosquitto CPU, the chosen save / every 60 s",
            chosen.cpu_s / max(base.cpu_s, 0.01),
            QUICK_BOUNDS["CPU"],
        )
        check_ratio(
            "latency p50, the chosen save / every 60 s",
            chosen.p50_ms / max(base.p50_ms, 0.01),
            QUICK_BOUNDS["latency p50"],
        )
        finish_quick()
    if not args.no_write:
        write_section(HEADING, text)
    return 0


def _filesystem() -> str:
    """The bench folder's filesystem type (a synced write costs what that disk makes it cost)."""
    folder = os.path.realpath(os.environ.get("WSNAV_BENCH_DIR", "/var/tmp"))
    best = ("", "?")
    for line in Path("/proc/mounts").read_text().splitlines():
        _, mount, kind, *_ = line.split()
        if (folder == mount or folder.startswith(mount.rstrip("/") + "/")) and len(mount) >= len(best[0]):
            best = (mount, kind)
    return f"{best[1]} ({folder})"


def _version() -> str:
    out = subprocess.run(["mosquitto", "-h"], capture_output=True, text=True, check=False).stdout
    return out.split()[2] if out.startswith("mosquitto version") else "2.0"


if __name__ == "__main__":
    raise SystemExit(main())
