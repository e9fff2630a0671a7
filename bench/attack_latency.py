"""A legitimate node's latency to the robot while an insider with one credential attacks the broker.

    ./.venv/bin/python -m bench.attack_latency                 # both brokers, writes BENCHMARKS.md
    ./.venv/bin/python -m bench.attack_latency --broker amqtt --seconds 5 --no-write
    ./.venv/bin/python -m bench.attack_latency --attack flood --attack "none, again" --no-write   # some rows
    ./.venv/bin/python -m bench.attack_latency --quick         # both brokers: baseline and flood, 3 s windows

The broker runs as its own process, as a site runs it: `wsnav broker run` with its default limits on loopback,
or Mosquitto from `wsnav broker mosquitto-config` in a network namespace of its own with the nftables rule of
`wsnav broker firewall` loaded (Mosquitto has no publish rate of its own), the probe and every attacker in
another namespace, each on its own address of the nodes' subnet (tests/netns_fixtures.py; root needed), and
the robot on the broker's loopback. The legitimate node `probe` publishes a zone state every 50 ms (QoS 1,
retained, as a node does); a subscriber with robot1's credentials takes `zones/#` as the agent does and
timestamps each probe state.
First a baseline window with no attack, then one window per attack, each from its own process:
- `subscriptions`: robot2's credential, 16 connections each asking for 6,250 filters (100,000 in all);
- `sessions`: node n1's credential parking persistent sessions under new client ids, as fast as it can;
- `retained`: robot2 publishing 16 KB retained messages under `robots/robot2/...`, as fast as it can;
- `flood`: node n1 publishing QoS 0 zone states as fast as it can;
- `busy (no MQTT)`: no attack, but a process as busy as an attacker (it counts as fast as it can at the same
  nice): what the machine alone does to the probe when a core is taken, the flood's control;
- `none, again`: no attack, the baseline window measured again last (how far the machine alone moves a ratio).
Each attack's p50/p99 is given as a ratio to the baseline of the same run (the goal is <= 2x), and to the busy
control's (what the broker adds beyond what a busy machine does).
Each attacker runs at nice 19 and, on Linux, in the idle scheduling class (it runs when nothing else
wants the CPU): at a site it is a machine of its own, and what is measured is what the broker does with its
traffic. On this shared 2-core machine an attacker at nice 0 took a core for its own sending
loop, from the probe, the robot and the broker alike (the flood's p99 2.3-2.7x its baseline; the attack
itself, which never needed that core to go far over every limit, is the same at nice 19).
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
import paho.mqtt.client as mqtt
import psutil
import yaml
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.reasoncodes import ReasonCode

from bench.bench_broker import BROKERS, in_group_of_own, site_broker
from bench.benchmarks_md import commit, machine_note, write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser
from bench.zone_fanin import PROBE, SITE, Probe, fanin_site
from tests.netns_fixtures import enter_namespace, exec_in, in_namespace, namespace_pair
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.config import CONF, MosquittoOptions, write_mosquitto_config
from wsnav.broker.mosquitto.firewall import nft_rules
from wsnav.schemas import topics
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.site import load_site

SECTION = "## A legitimate node's latency during an insider's attack on the broker"
COMMAND = "./.venv/bin/python -m bench.attack_latency"
BUSY = "busy (no MQTT)"
ATTACKS = ("subscriptions", "sessions", "retained", "flood", BUSY, "none, again")
DESCRIPTION = "\n\n".join((__doc__ or "").split("\n\n")[2:]).strip()
READING = (
    "How to read it: amqtt holds every attack to its identity's limits (wsnav.broker.identity_limits: 64 "
    "subscriptions a session, subscribe, login and node publish rates by backpressure; retained messages bounded "
    "by the ACL). Mosquitto 2.0 keeps one session per identity and refuses the retained flood by its ACL, but has "
    "no publish rate of its own: its rows run as a site runs it, with the per-source byte rate of `wsnav broker "
    "firewall` loaded and every attacker on its own address of the nodes' subnet, so a connection sending over "
    "4 kB/s is reset (the flood and the subscription attack's SUBSCRIBE packets alike), and nothing the flooder "
    "queued reaches the robot after it left (`none, again` takes no other zone message). Without the rule a "
    "node's QoS 0 flood delayed the other nodes by seconds (`bench.mosquitto_flood_firewall`). Each attacker runs "
    "at nice 19 in the idle scheduling class (a machine of its own at a site). p99 is the 4th slowest of about "
    "400 states in 20 s windows (the 2nd of 160 in 8 s ones), so one stall of the shared machine moves it, in the "
    "baseline window too; the `busy (no MQTT)` row is what a busy machine alone does, and a ratio over it near "
    "1x says the broker added nothing of its own; `none, again` says how far the machine moved the ratios."
)
T = TypeVar("T")
WARMUP_S = 2.0
"""The attack runs this long before the window opens (the subscriptions are being asked for, the flood is on)."""


ATTACKER_NICE = 19
"""The attacker's process yields the machine's CPU to the broker, the probe and the robot (module docstring)."""
ATTACKER_BIND = [""]
"""The source address the attacker's clients connect from (set in the attacker's own process)."""


def _client(host: str, port: int, creds: Path, ident: str, client_id: str, clean: bool = True) -> mqtt.Client:
    c = load_credentials(creds / f"{ident}.json")
    client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=client_id, clean_session=clean)
    client.username_pw_set(c.username, c.password)
    client.connect(host, port, keepalive=60, bind_address=ATTACKER_BIND[0])
    return client


def attack_subscriptions(host: str, port: int, creds: Path, stop: threading.Event) -> str:
    clients = [_client(host, port, creds, "robot2", f"robot2-sub{i}") for i in range(16)]
    granted: list[int] = []

    def on_subscribe(_c: object, _u: object, _m: int, reasons: list[ReasonCode], _p: object) -> None:
        granted.extend(1 for r in reasons if not r.is_failure)

    for i, c in enumerate(clients):
        c.on_subscribe = on_subscribe
        c.loop_start()
        for batch in range(0, 6250, 250):
            if stop.is_set():
                break
            c.subscribe([(f"wsn/{SITE}/zones/z{i}/state/x{batch + k}", 1) for k in range(250)])
    stop.wait()
    for c in clients:
        c.disconnect()
        c.loop_stop()
    return f"{len(granted)} of {16 * 6250} filters granted"


def attack_sessions(host: str, port: int, creds: Path, stop: threading.Event) -> str:
    made = 0
    while not stop.is_set():
        try:
            c = _client(host, port, creds, "n1", f"n1-park-{made}", clean=False)
            c.loop(timeout=0.2)
            c.disconnect()
            made += 1
        except OSError:
            time.sleep(0.05)
    return f"{made} logins with new client ids and a persistent session tried"


def attack_retained(host: str, port: int, creds: Path, stop: threading.Event) -> str:
    c = _client(host, port, creds, "robot2", "robot2")
    c.loop_start()
    sent, acknowledged, payload = 0, 0, b"x" * 16_000
    while not stop.is_set():
        info = c.publish(f"wsn/{SITE}/robots/robot2/junk/{sent}", payload, qos=1, retain=True)
        sent += 1
        if info.rc != mqtt.MQTT_ERR_SUCCESS:
            time.sleep(0.001)  # not connected (reset, refused): paho's thread reconnects
            continue
        with contextlib.suppress(RuntimeError, ValueError):
            info.wait_for_publish(5)
            acknowledged += info.is_published()
    c.disconnect()
    c.loop_stop()
    return f"{sent} retained 16 KB messages tried, {acknowledged} acknowledged (none stored)"


def attack_flood(host: str, port: int, creds: Path, stop: threading.Event) -> str:
    c = _client(host, port, creds, "n1", "n1")
    c.loop_start()
    topic, sent, tried = topics.zone_state(SITE, "z0", "n1"), 0, 0
    while not stop.is_set():
        info = c.publish(
            topic, b'{"v": 1, "zone": "z0", "node": "n1", "state": "blocked", "seq": %d}' % tried
        )
        tried += 1
        sent += info.rc == mqtt.MQTT_ERR_SUCCESS
        if tried % 200 == 0:
            time.sleep(0.001)  # let paho's thread write: the flood is bounded by the socket, not by a queue
    c.disconnect()
    c.loop_stop()
    return f"{sent} QoS 0 messages queued by its client ({tried - sent} tried while it was not connected)"


def attack_busy(_host: str, _port: int, _creds: Path, stop: threading.Event) -> str:
    counted = 0
    while not stop.is_set():
        for _ in range(10_000):
            counted += 1
    return f"no attack: a process counting to {counted} as fast as it can, the flood's control"


def attack_none(_host: str, _port: int, _creds: Path, stop: threading.Event) -> str:
    stop.wait()
    return "no attack: the baseline measured again, how far this machine moves the ratios by itself"


ATTACK: dict[str, Callable[[str, int, Path, threading.Event], str]] = {
    "none, again": attack_none,
    "subscriptions": attack_subscriptions,
    "sessions": attack_sessions,
    "retained": attack_retained,
    "flood": attack_flood,
    BUSY: attack_busy,
}


def _attacker(name: str, where: Where, creds: str, seconds: float, out: mp.Queue[str]) -> None:
    """One attack, in a process of its own (in the nodes' namespace, from its own address, where there is one)."""
    os.nice(ATTACKER_NICE)
    with contextlib.suppress(OSError, AttributeError):  # (Linux) runs only on CPU nobody else wants
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    if where.nodes_ns is not None:
        enter_namespace(where.nodes_ns)
    ATTACKER_BIND[0] = where.attacker_bind
    host, port = where.host, where.port
    stop = threading.Event()
    threading.Timer(seconds, stop.set).start()
    try:
        out.put(ATTACK[name](host, port, Path(creds), stop))
    except Exception as exc:
        out.put(f"attacker failed: {exc}")


@dataclass(frozen=True)
class Where:
    """Where each client connects to, and from: the nodes (probe, attackers) to `host:port`, from `nodes_ns`
    (None: this one) and their own addresses; the robot to `robot_host:port` from `robot_ns`."""

    host: str
    port: int
    robot_host: str
    robot_ns: str | None = None
    nodes_ns: str | None = None
    probe_bind: str = ""
    attacker_bind: str = ""
    placement: str = "loopback"


def _made_in(ns: str | None, make: Callable[[], T]) -> T:
    return make() if ns is None else in_namespace(ns, make)


@contextlib.contextmanager
def broker_as_a_site_runs_it(
    kind: str, site: Path, creds: Path, root: Path, nice: int | None = None
) -> Iterator[Where]:
    """amqtt on loopback (its limits are its own); Mosquitto in its namespace with the per-source rule loaded.
    `nice`: amqtt in a scheduling group of its own with that nice (Mosquitto stays in this process's group)."""
    if kind != "mosquitto":
        with site_broker(kind, site, creds, root, nice=nice) as broker:
            yield Where(broker.host, broker.port, broker.host)
        return
    if os.geteuid() != 0:
        raise SystemExit("Mosquitto's rows need root (network namespaces and nftables, as a site runs them)")
    with namespace_pair("10.99.39", "a", node_addresses=2) as pair:
        options = MosquittoOptions(("0.0.0.0", 1883), root / "mq-data", user="root")
        write_mosquitto_config(load_site(site).spec, creds, root / "mq", options)
        rules = root / "mqtt.nft"
        rules.write_text(nft_rules(pair.subnet))
        subprocess.run([*exec_in(pair.broker), "nft", "-f", str(rules)], check=True)
        broker = subprocess.Popen(
            [*exec_in(pair.broker), "mosquitto", "-c", str(root / "mq" / CONF)], stderr=subprocess.DEVNULL
        )
        try:
            _made_in(pair.nodes, lambda: _wait_listening(pair.broker_address, 1883))
            yield Where(
                pair.broker_address,
                1883,
                "127.0.0.1",
                robot_ns=pair.broker,
                nodes_ns=pair.nodes,
                probe_bind=pair.node_address(1),
                attacker_bind=pair.node_address(2),
                placement=f"namespaces, `wsnav broker firewall` rule on {pair.subnet}",
            )
        finally:
            broker.terminate()
            broker.wait(30)


def _wait_listening(host: str, port: int, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            socket.create_connection((host, port), timeout=1).close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


class Robot:
    """robot1's subscriber on `zones/#`: arrival time of each probe seq (the agent's subscription)."""

    def __init__(self, host: str, port: int, creds: Path) -> None:
        self.arrived: dict[int, float] = {}
        self.other = 0
        self.client = _client(host, port, creds, "robot1", "robot1")
        self.client.on_message = self._on_message
        self.client.subscribe(topics.all_zone_states(SITE), 1)
        self.client.loop_start()

    def _on_message(self, _c: object, _u: object, msg: mqtt.MQTTMessage) -> None:
        if msg.topic.endswith(f"/{PROBE}"):
            seq = int(json.loads(msg.payload)["seq"])
            self.arrived.setdefault(seq, time.monotonic())
        else:
            self.other += 1

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def window(probe: Probe, robot: Robot, seconds: float) -> dict[str, float]:
    """Probe states sent during `seconds`: latency p50/p99 (ms) and how many never arrived within 5 s."""
    first = len(probe.sent)
    time.sleep(seconds)
    last = len(probe.sent)
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and not all(s in robot.arrived for s, _ in probe.sent[first:last]):
        time.sleep(0.1)
    lags = np.array([(robot.arrived[s] - t) * 1000 for s, t in probe.sent[first:last] if s in robot.arrived])
    lost = sum(1 for s, _ in probe.sent[first:last] if s not in robot.arrived)
    p50, p99 = (
        (float(np.percentile(lags, 50)), float(np.percentile(lags, 99))) if lags.size else (np.nan, np.nan)
    )
    return {"p50": p50, "p99": p99, "lost": float(lost), "sent": float(last - first)}


def measure(
    kind: str,
    seconds: float,
    attacks: tuple[str, ...] = ATTACKS,
    warmup_s: float = WARMUP_S,
    nice: int | None = None,
) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        site = fanin_site(root / "site", nodes=4)
        spec = yaml.safe_load((site / "site.yaml").read_text())
        spec["robots"] = [{"id": "robot1"}, {"id": "robot2"}]
        (site / "site.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
        creds = root / "creds"
        write_credentials(load_site(site).spec, creds)
        with broker_as_a_site_runs_it(kind, site, creds, root / kind, nice) as where:
            robot = _made_in(where.robot_ns, lambda: Robot(where.robot_host, where.port, creds))
            probe = _made_in(where.nodes_ns, lambda: Probe(where.host, where.port, creds, where.probe_bind))
            probe.start()
            time.sleep(1.0)
            base = window(probe, robot, seconds)
            rows.append({"broker": kind, "attack": "none (baseline)", **base, "note": where.placement})
            print(f"{kind:9} baseline       p50 {base['p50']:7.2f} ms  p99 {base['p99']:7.2f} ms", flush=True)
            ctx = mp.get_context("spawn")
            for name in attacks:
                out: mp.Queue[str] = ctx.Queue()
                proc = ctx.Process(target=_attacker, args=(name, where, str(creds), warmup_s + seconds, out))
                proc.start()
                time.sleep(warmup_s)
                others = robot.other
                cpu = _cpu_s(proc.pid)
                r = window(probe, robot, seconds)
                cpu = (_cpu_s(proc.pid) - cpu) / seconds
                others = robot.other - others
                proc.join(60)
                note = out.get(timeout=30) if proc.exitcode == 0 else f"attacker exit {proc.exitcode}"
                note += f"; the robot took {others} other zone messages in the window; the attacker's process used {100 * cpu:.0f} % of a core"
                rows.append({"broker": kind, "attack": name, **r, "note": note})
                print(
                    f"{kind:9} {name:14} p50 {r['p50']:7.2f} ms ({r['p50'] / base['p50']:.1f}x)  "
                    f"p99 {r['p99']:7.2f} ms ({r['p99'] / base['p99']:.1f}x)  lost {r['lost']:.0f}  {note}",
                    flush=True,
                )
                if name != attacks[-1]:
                    time.sleep(3.0)  # the broker settles before the next attack
            probe.close()
            robot.close()
    return rows


def _cpu_s(pid: int | None) -> float:
    """CPU seconds the process has used so far (0 once it has ended; its window's share is then not known)."""
    try:
        times = psutil.Process(pid).cpu_times() if pid is not None else None
    except psutil.Error:
        return 0.0
    return 0.0 if times is None else float(times.user + times.system)


def table(rows: list[dict[str, object]]) -> str:
    lines = [
        "| broker | attack | p50 | p99 | p50 / baseline | p99 / baseline | p50 / p99 over the busy control "
        "| lost | the attacker got |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    base: dict[object, dict[str, object]] = {r["broker"]: r for r in rows if r["attack"] == "none (baseline)"}
    busy: dict[object, dict[str, object]] = {r["broker"]: r for r in rows if r["attack"] == BUSY}
    for r in rows:
        b = base[r["broker"]]
        p50, p99 = float(r["p50"]), float(r["p99"])  # type: ignore[arg-type]
        ratio50 = p50 / float(b["p50"])  # type: ignore[arg-type]
        ratio99 = p99 / float(b["p99"])  # type: ignore[arg-type]
        control = busy.get(r["broker"])
        over_busy = (
            f"{p50 / float(control['p50']):.1f}x / {p99 / float(control['p99']):.1f}x"  # type: ignore[arg-type]
            if control is not None
            else "-"
        )
        lines.append(
            f"| {r['broker']} | {r['attack']} | {p50:.2f} ms | {p99:.2f} ms | {ratio50:.1f}x | {ratio99:.1f}x | "
            f"{over_busy} | {float(r['lost']):.0f} of {float(r['sent']):.0f} | {r['note']} |"  # type: ignore[arg-type]
        )
    return "\n".join(lines)


QUICK_SECONDS = 2.0
QUICK_BOUND = 10.0
"""The probe's p50 during a node's flood over its baseline p50 in the same run, per broker: the goal is 2x, and
0.8-3.9x was measured at load 5-14 with 2-3 s windows; a flood without its limit gave 1,000-6,500x. Quick mode
checks p50 only: of 60 states, p99 is the slowest one, a single stall of the loaded machine (0.8 ms against
32 ms in one run with nothing wrong). It takes about 75 s at load 5, over the convention's minute: most of it
starts the two brokers, the namespaces and the attacker's process, not the 2 s windows."""


def main(argv: list[str] | None = None) -> int:
    parser = quick_parser(__doc__)
    parser.add_argument("--broker", choices=(*BROKERS, "both"), default="both")
    parser.add_argument("--seconds", type=float, default=8.0, help="each window (default 8)")
    parser.add_argument(
        "--attack",
        action="append",
        choices=ATTACKS,
        help="only this attack's window after the baseline (again for more; default every one)",
    )
    parser.add_argument(
        "--clients-nice",
        type=int,
        help="this benchmark (probe, robot, attackers at nice 19 inside it, Mosquitto) and amqtt each in a "
        "scheduling group of their own with nice N (negative, as root): other jobs on the machine then take "
        "less of the CPU from them",
    )
    args = parse_quick_args(parser, argv)
    if not -20 <= (args.clients_nice or 0) <= 19:
        parser.error("--clients-nice must be -20..19")
    if (
        args.clients_nice is not None
        and (exit_code := in_group_of_own(args.clients_nice, "bench.attack_latency", argv)) is not None
    ):
        return exit_code
    kinds = BROKERS if args.broker == "both" else (args.broker,)
    if args.quick:
        rows = [row for kind in kinds for row in measure(kind, QUICK_SECONDS, ("flood",), warmup_s=0.5)]
        print(table(rows))
        base = {r["broker"]: r for r in rows if r["attack"] == "none (baseline)"}
        for r in rows:
            if r["attack"] == "flood":
                ratio = float(r["p50"]) / float(base[r["broker"]]["p50"])  # type: ignore[arg-type]
                check_ratio(f"{r['broker']}: probe p50 during a node's flood / baseline", ratio, QUICK_BOUND)
                lost = float(r["lost"]) / max(float(r["sent"]), 1.0)  # type: ignore[arg-type]
                check_ratio(f"{r['broker']}: probe states lost during the flood / sent", lost, 0.1)
        finish_quick()
    attacks = tuple(a for a in ATTACKS if a in args.attack) if args.attack else ATTACKS
    rows = [row for kind in kinds for row in measure(kind, args.seconds, attacks, nice=args.clients_nice)]
    text = table(rows)
    print(text)
    if not args.no_write and attacks == ATTACKS:
        write_section(
            SECTION,
            f"```sh\n{' '.join([COMMAND, *(sys.argv[1:] if argv is None else argv)])}\n```\n\n{DESCRIPTION}\n\nMeasured at commit {commit()} with {machine_note()}"
            f" (`uptime` load averages {' '.join(f'{x:.2f}' for x in os.getloadavg())}):\n\n{text}\n\n{READING}",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
