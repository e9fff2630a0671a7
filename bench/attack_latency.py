"""A legitimate node's latency to the robot while an insider with one credential attacks the broker.

    ./.venv/bin/python -m bench.attack_latency                 # both brokers, writes BENCHMARKS.md
    ./.venv/bin/python -m bench.attack_latency --broker amqtt --seconds 5 --no-write

The broker (`wsnav broker run` with its default limits, or Mosquitto from `wsnav broker mosquitto-config`) runs
as its own process. The legitimate node `probe` publishes a zone state every 50 ms (QoS 1, retained, as a node
does); a subscriber with robot1's credentials takes `zones/#` as the agent does and timestamps each probe state.
First a baseline window with no attack, then one window per attack, each from its own process:
- `subscriptions`: robot2's credential, 16 connections each asking for 6,250 filters (100,000 in all);
- `sessions`: node n1's credential parking persistent sessions under new client ids, as fast as it can;
- `retained`: robot2 publishing 16 KB retained messages under `robots/robot2/...`, as fast as it can;
- `flood`: node n1 publishing QoS 0 zone states as fast as it can.
Each attack's p50/p99 is given as a ratio to the baseline of the same run (the goal is <= 2x).
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import paho.mqtt.client as mqtt
import yaml
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.reasoncodes import ReasonCode

from bench.bench_broker import BROKERS, site_broker
from bench.benchmarks_md import bench_parser, machine_note, write_section
from bench.zone_fanin import PROBE, SITE, Probe, fanin_site
from wsnav.broker.credentials import write_credentials
from wsnav.schemas import topics
from wsnav.schemas.credentials import load_credentials

SECTION = "## A legitimate node's latency during an insider's attack on the broker"
COMMAND = "./.venv/bin/python -m bench.attack_latency"
ATTACKS = ("subscriptions", "sessions", "retained", "flood")
DESCRIPTION = "\n\n".join((__doc__ or "").split("\n\n")[2:]).strip()
READING = (
    "How to read it: amqtt holds every attack to its identity's limits (wsnav.broker.identity_limits: 64 "
    "subscriptions a session, subscribe, login and node publish rates by backpressure; retained messages bounded "
    "by the ACL). Mosquitto 2.0 keeps one session per identity (16 connections of robot2 take each other over, so "
    "one holds 6,250 filters) and refuses the retained flood by its ACL, but has no publish rate: a node's QoS 0 "
    "flood reaches every robot subscribed to `zones/#` and delays the legitimate node's states (the robot's "
    "client is the bottleneck). On Mosquitto, limit each node's packet rate in the firewall (docs/security.md)."
)
WARMUP_S = 2.0
"""The attack runs this long before the window opens (the subscriptions are being asked for, the flood is on)."""


def _client(host: str, port: int, creds: Path, ident: str, client_id: str, clean: bool = True) -> mqtt.Client:
    c = load_credentials(creds / f"{ident}.json")
    client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=client_id, clean_session=clean)
    client.username_pw_set(c.username, c.password)
    client.connect(host, port, keepalive=60)
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
    sent, payload = 0, b"x" * 16_000
    while not stop.is_set():
        info = c.publish(f"wsn/{SITE}/robots/robot2/junk/{sent}", payload, qos=1, retain=True)
        with contextlib.suppress(RuntimeError, ValueError):
            info.wait_for_publish(5)
        sent += 1
    c.disconnect()
    c.loop_stop()
    return f"{sent} retained 16 KB messages published (each acknowledged, none stored)"


def attack_flood(host: str, port: int, creds: Path, stop: threading.Event) -> str:
    c = _client(host, port, creds, "n1", "n1")
    c.loop_start()
    topic, sent = topics.zone_state(SITE, "z0", "n1"), 0
    while not stop.is_set():
        c.publish(topic, b'{"v": 1, "zone": "z0", "node": "n1", "state": "blocked", "seq": %d}' % sent, qos=0)
        sent += 1
        if sent % 200 == 0:
            time.sleep(0.001)  # let paho's thread write: the flood is bounded by the socket, not by a queue
    c.disconnect()
    c.loop_stop()
    return f"{sent} QoS 0 messages queued by its client"


ATTACK: dict[str, Callable[[str, int, Path, threading.Event], str]] = {
    "subscriptions": attack_subscriptions,
    "sessions": attack_sessions,
    "retained": attack_retained,
    "flood": attack_flood,
}


def _attacker(name: str, host: str, port: int, creds: str, seconds: float, out: mp.Queue[str]) -> None:
    stop = threading.Event()
    threading.Timer(seconds, stop.set).start()
    try:
        out.put(ATTACK[name](host, port, Path(creds), stop))
    except Exception as exc:
        out.put(f"attacker failed: {exc}")


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


def measure(kind: str, seconds: float) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        site = fanin_site(root / "site", nodes=4)
        spec = yaml.safe_load((site / "site.yaml").read_text())
        spec["robots"] = [{"id": "robot1"}, {"id": "robot2"}]
        (site / "site.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
        creds = root / "creds"
        from wsnav.schemas.site import load_site

        write_credentials(load_site(site).spec, creds)
        with site_broker(kind, site, creds, root / kind) as broker:
            robot = Robot(broker.host, broker.port, creds)
            probe = Probe(broker.host, broker.port, creds)
            probe.start()
            time.sleep(1.0)
            base = window(probe, robot, seconds)
            rows.append({"broker": kind, "attack": "none (baseline)", **base, "note": ""})
            print(f"{kind:9} baseline       p50 {base['p50']:7.2f} ms  p99 {base['p99']:7.2f} ms", flush=True)
            ctx = mp.get_context("spawn")
            for name in ATTACKS:
                out: mp.Queue[str] = ctx.Queue()
                proc = ctx.Process(
                    target=_attacker,
                    args=(name, broker.host, broker.port, str(creds), WARMUP_S + seconds, out),
                )
                proc.start()
                time.sleep(WARMUP_S)
                others = robot.other
                r = window(probe, robot, seconds)
                others = robot.other - others
                proc.join(60)
                note = out.get(timeout=30) if proc.exitcode == 0 else f"attacker exit {proc.exitcode}"
                note += f"; the robot took {others} other zone messages in the window"
                rows.append({"broker": kind, "attack": name, **r, "note": note})
                print(
                    f"{kind:9} {name:14} p50 {r['p50']:7.2f} ms ({r['p50'] / base['p50']:.1f}x)  "
                    f"p99 {r['p99']:7.2f} ms ({r['p99'] / base['p99']:.1f}x)  lost {r['lost']:.0f}  {note}",
                    flush=True,
                )
                time.sleep(3.0)  # the broker settles before the next attack
            probe.close()
            robot.close()
    return rows


def table(rows: list[dict[str, object]]) -> str:
    lines = [
        "| broker | attack | p50 | p99 | p50 / baseline | p99 / baseline | lost | the attacker got |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    base: dict[object, dict[str, object]] = {r["broker"]: r for r in rows if r["attack"] == "none (baseline)"}
    for r in rows:
        b = base[r["broker"]]
        p50, p99 = float(r["p50"]), float(r["p99"])  # type: ignore[arg-type]
        ratio50 = p50 / float(b["p50"])  # type: ignore[arg-type]
        ratio99 = p99 / float(b["p99"])  # type: ignore[arg-type]
        lines.append(
            f"| {r['broker']} | {r['attack']} | {p50:.2f} ms | {p99:.2f} ms | {ratio50:.1f}x | {ratio99:.1f}x | "
            f"{float(r['lost']):.0f} of {float(r['sent']):.0f} | {r['note']} |"  # type: ignore[arg-type]
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--broker", choices=(*BROKERS, "both"), default="both")
    parser.add_argument("--seconds", type=float, default=8.0, help="each window (default 8)")
    args = parser.parse_args(argv)
    kinds = BROKERS if args.broker == "both" else (args.broker,)
    rows = [row for kind in kinds for row in measure(kind, args.seconds)]
    text = table(rows)
    print(text)
    if not args.no_write:
        write_section(
            SECTION,
            f"```sh\n{COMMAND}\n```\n\n{DESCRIPTION}\n\nMeasured with {machine_note()}:\n\n{text}\n\n{READING}",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
