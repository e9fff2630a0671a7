"""Console benchmark: 1000 nodes at 1 Hz and 20 robots at 2 Hz with the page open in Chromium.

    ./.venv/bin/python -m bench.console_feed [--nodes 1000] [--robots 20] [--seconds 30] [--no-write]

A generated site (bench.zone_fanin's 20 x 20 m map, 2 nodes a zone), Mosquitto (from `wsnav broker mosquitto-config`), the zone
simulator (one process, a link per node, heart-beating at 1 Hz), 20 robot links publishing full statuses (with
their 24-point path) at 2 Hz, `wsnav console` as its own process, and Debian's Chromium logged in to the page.
The page's own event stream is tapped (an init script wraps EventSource) to stamp when each node's (id, seq)
reached the browser. Delays: simulator socket write -> browser, and the console's MQTT intake -> browser; the
baseline is a plain MQTT subscriber on the same broker in the same run (simulator -> subscriber). CPU: the
console process before the page is opened (same traffic) and with it open.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import yaml

from bench.bench_broker import mosquitto_broker
from bench.benchmarks_md import bench_parser, machine_note, write_section
from bench.zone_fanin import cpu_s, fanin_site, simulate, subscribe_all
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.process import free_port
from wsnav.runtime.mqtt_bus import connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.messages import ROBOT_PATH_POINTS, RobotStatus
from wsnav.schemas.site import load_site

SITE = "fanin"
SECTION = "## Operator console: 1000 nodes and 20 robots to the browser"
COMMAND = "./.venv/bin/python -m bench.console_feed"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip
TAP = """
window.__arrivals = [];
const Native = window.EventSource;
window.EventSource = function (url) {
  const es = new Native(url);
  es.addEventListener("message", (e) => {
    const at = Date.now(); // the system wall clock, as Python's time.time() on this machine
    const ev = JSON.parse(e.data);
    if (ev.type !== "update") return; // a snapshot (page opened, or fell behind) repeats what was already due
    for (const n of ev.nodes || []) if (n.seq != null) window.__arrivals.push([n.id, n.seq, n.heard_at, at]);
    for (const [id, [seq, heard]] of Object.entries(ev.heard || {})) window.__arrivals.push([id, seq, heard, at]);
  });
  return es;
};
"""


def site_with_robots(directory: Path, nodes: int, robots: int) -> Path:
    site = fanin_site(directory, nodes, per_zone=2, probe=False)  # no node the page would show as silent
    spec = yaml.safe_load((site / "site.yaml").read_text())
    spec["robots"] = [{"id": f"robot{i + 1}"} for i in range(robots + 1)]  # robot1 is the baseline subscriber
    (site / "site.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
    return site


def drive_robots(host: str, port: int, creds: Path, robots: int, stop: threading.Event) -> None:
    """Robots 2.. each on its own link, a full status twice a second, circling the map."""
    names = [f"robot{i + 2}" for i in range(robots)]
    buses = [connect_with_credentials(host, port, load_credentials(creds / f"{name}.json")) for name in names]
    k = 0
    while not stop.wait(0.5):
        k += 1
        for i, (name, bus) in enumerate(zip(names, buses, strict=True)):
            a = 0.05 * k + i
            x, y = 10 + 6 * math.cos(a), 10 + 6 * math.sin(a)
            path = [
                (round(10 + 6 * math.cos(a + j * 0.1), 2), round(10 + 6 * math.sin(a + j * 0.1), 2))
                for j in range(ROBOT_PATH_POINTS)
            ]
            status = RobotStatus(robot=name, state="navigating", pose=(round(x, 3), round(y, 3), round(a + 1.57, 3)),
                                 goal=(10.0, 16.0, 0.0), blocked_zones=["z3", "z17"], replans=k // 10, plan_length_m=12.3, path=path, t=time.time())  # fmt: skip
            bus.publish(topics.robot_status(SITE, name), status.to_payload(), qos=0)
    for bus in buses:
        bus.close()


def commit() -> str:
    """The commit measured (with `+dirty` when the tree has changes), for BENCHMARKS.md."""
    here = Path(__file__).resolve().parent
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True)
    dirty = subprocess.run(["git", "status", "--porcelain"], cwd=here, capture_output=True, text=True)
    return rev.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


def measure(nodes: int, robots: int, seconds: float) -> dict[str, float]:
    from playwright.sync_api import sync_playwright

    load_start = os.getloadavg()[0]
    wall_minus_mono = time.time() - time.monotonic()
    with tempfile.TemporaryDirectory(prefix="wsnav-console-") as tmp:
        root = Path(tmp)
        site_dir = site_with_robots(root / "site", nodes, robots)
        creds = root / "creds"
        spec = load_site(site_dir).spec
        write_credentials(spec, creds)
        with mosquitto_broker(spec, creds, root) as running:
            host, broker_port = running.host, running.port
            addr = f"{host}:{broker_port}"
            sub, got = subscribe_all(host, broker_port, creds, [n.id for n in spec.nodes])
            ctx = mp.get_context("spawn")
            ready, go = ctx.Queue(), ctx.Event()
            out = str(root / "sent.npy")
            sim = ctx.Process(
                target=simulate,
                args=(str(site_dir), str(creds), host, broker_port, seconds + 20, out, ready, go),
            )
            sim.start()
            online, _ = ready.get(timeout=400)
            port = free_port()
            console = subprocess.Popen(
                [sys.executable, "-m", "wsnav.cli", "console", "--site", str(site_dir), "--broker", addr,
                 "--credentials", str(creds / "operator.json"), "--bind", f"127.0.0.1:{port}",
                 "--state-dir", str(root / "console-state")],
                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            )  # fmt: skip
            console_ps = psutil.Process(console.pid)
            stop = threading.Event()
            driver = threading.Thread(target=drive_robots, args=(host, broker_port, creds, robots, stop))
            driver.start()
            go.set()
            time.sleep(5.0)  # the console takes in the retained states and settles
            c0, t0 = cpu_s(console_ps), time.monotonic()
            time.sleep(10.0)
            idle_pct = 100 * (cpu_s(console_ps) - c0) / (time.monotonic() - t0)
            password = json.loads((creds / "operator.json").read_text())["password"]
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
                page = browser.new_context(
                    viewport={"width": 1400, "height": 900}, bypass_csp=True
                ).new_page()
                page.add_init_script(TAP)
                page.goto(f"http://127.0.0.1:{port}/")
                page.fill("input[name=password]", password)
                page.click("button[type=submit]")
                page.wait_for_url(f"http://127.0.0.1:{port}/")
                page.wait_for_function("window.__arrivals.length > 0", timeout=60000)
                time.sleep(2.0)
                page.evaluate("window.__arrivals.length = 0")
                c1, t1 = cpu_s(console_ps), time.monotonic()
                open_from = t1 + wall_minus_mono
                time.sleep(seconds)
                c2, t2 = cpu_s(console_ps), time.monotonic()
                arrivals = page.evaluate("window.__arrivals")
                if os.environ.get("WSNAV_BENCH_DUMP"):
                    Path(os.environ["WSNAV_BENCH_DUMP"]).write_text(json.dumps(arrivals))
                shown = page.evaluate("document.querySelectorAll('#layer-robots .robot').length")
                browser.close()
            stop.set()
            driver.join(30)
            console.terminate()
            console.wait(20)
            sim.join(120)
            sub.disconnect()
            sub.loop_stop()
            sent = np.load(out)
    open_to = t2 + wall_minus_mono
    index = {n.id: i for i, n in enumerate(spec.nodes)}
    sent_at = {(int(n), int(q)): t + wall_minus_mono for n, q, t in sent}
    first: dict[tuple[str, int], list[Any]] = {}
    for a in arrivals:  # the first time each (node, seq) reached the page
        first.setdefault((a[0], a[1]), a)
    arrivals = list(first.values())
    to_browser = [at / 1000 - sent_at[(index[i], q)] for i, q, _h, at in arrivals if (index[i], q) in sent_at]
    console_to_browser = [at / 1000 - heard for _i, _q, heard, at in arrivals if heard is not None]
    baseline = [
        t + wall_minus_mono - sent_at[(n, q)]
        for n, q, t in got
        if (n, q) in sent_at and open_from <= t + wall_minus_mono <= open_to
    ]
    sent_in_window = sum(1 for t in sent_at.values() if open_from + 1 <= t <= open_to - 3)
    reached = {
        (index[i], q)
        for i, q, _h, at in arrivals
        if open_from + 1 <= sent_at.get((index[i], q), 0) <= open_to - 3
    }
    per_second: dict[int, list[float]] = {}
    for _i, _q, heard, at in arrivals:
        if heard is None:  # a retained replay: no live message to time
            continue
        per_second.setdefault(int(at / 1000 - open_from), []).append(at / 1000 - heard)
    slow_seconds = sum(1 for xs in per_second.values() if np.percentile(xs, 99) > 0.5)
    ms = lambda xs, p: 1000 * float(np.percentile(xs, p))  # noqa: E731
    return {
        "nodes": nodes, "online": online, "robots": robots, "robots_drawn": shown, "seconds": t2 - t1,
        "idle_cpu_pct": idle_pct, "open_cpu_pct": 100 * (c2 - c1) / (t2 - t1),
        "p50_ms": ms(to_browser, 50), "p99_ms": ms(to_browser, 99), "max_ms": 1000 * max(to_browser),
        "console_p50_ms": ms(console_to_browser, 50), "console_p99_ms": ms(console_to_browser, 99),
        "base_p50_ms": ms(baseline, 50), "base_p99_ms": ms(baseline, 99),
        "reached_pct": 100 * len(reached) / max(1, sent_in_window),
        "slow_seconds": slow_seconds,
        "measured_seconds": len(per_second),
        "load_start": load_start, "load_end": os.getloadavg()[0],
    }  # fmt: skip


def report(r: dict[str, float]) -> str:
    return "\n".join(
        [
            f"| {int(r['nodes'])} nodes ({int(r['online'])} online), {int(r['robots'])} robots ({int(r['robots_drawn'])} drawn) | value | baseline, same run | ratio |",
            "| --- | --- | --- | --- |",
            f"| message -> browser, p50 | {r['p50_ms']:.0f} ms | {r['base_p50_ms']:.0f} ms (plain MQTT subscriber) | {r['p50_ms'] / max(r['base_p50_ms'], 0.1):.1f}x |",
            f"| message -> browser, p99 | {r['p99_ms']:.0f} ms | {r['base_p99_ms']:.0f} ms (plain MQTT subscriber) | {r['p99_ms'] / max(r['base_p99_ms'], 0.1):.1f}x |",
            f"| console intake -> browser, p50 / p99 | {r['console_p50_ms']:.0f} / {r['console_p99_ms']:.0f} ms | | |",
            f"| console CPU, page open | {r['open_cpu_pct']:.0f} % of a core | {r['idle_cpu_pct']:.0f} % (no page open) | {r['open_cpu_pct'] / max(r['idle_cpu_pct'], 0.1):.1f}x |",
            f"| node heartbeats of the window seen by the page | {r['reached_pct']:.1f} % | | |",
            f"| one-second slices with console -> browser p99 over 0.5 s | {int(r['slow_seconds'])} of {int(r['measured_seconds'])} | | |",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--nodes", type=int, default=1000)
    parser.add_argument("--robots", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=30.0)
    args = parser.parse_args(argv)
    r = measure(args.nodes, args.robots, args.seconds)
    table = report(r)
    note = machine_note()
    print(f"console feed, {note}, {r['seconds']:.0f} s window")
    print(table)
    if not args.no_write:
        body = (
            f"```\n{COMMAND}\n```\n\n"
            f"{note}. {int(r['nodes'])} emulated nodes heart-beating at 1 Hz (2 a zone), {int(r['robots'])} robots'\n"
            "full statuses at 2 Hz, Mosquitto (from `wsnav broker mosquitto-config`), `wsnav console` and Chromium with the page open, for a\n"
            f'{r["seconds"]:.0f} s window. "message -> browser": simulator socket write to the page\'s event handler; the\n'
            "baseline is a plain MQTT subscriber on the same broker at the same time (what the broker alone costs).\n"
            '"console intake": from the console\'s MQTT callback to the page. Target (issue 32): p99 <= 250 ms from\n'
            "the MQTT message, every state change shown (heartbeats may be coalesced).\n"
            f"Commit {commit()}; load over the run {r['load_start']:.1f} -> {r['load_end']:.1f} (1-minute average).\n\n"
            f"{table}\n"
        )
        write_section(SECTION, body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
