# pyright: reportMissingImports=false
"""Zone message on MQTT -> OccupancyGridUpdate received on ROS, through `wsnav ros bridge`; bytes per update.

    ./.venv/bin/python -m bench.ros_zone_grid [--changes 100] [--no-write]

For the school site and Nav2's warehouse map: a real roscore on a free port, the broker in this process, the bridge
as its own process (`--update-hold 0`, so each update is the window one change touched). A node flips its zone
between `blocked` and `clear`; each change is timed from just before the MQTT publish to the update's arrival
in this process's rospy subscriber. Baseline in the same run: the same message reaching a plain MQTT subscriber.
Needs Debian's ROS 1 packages (see .ci/run). Writes its section of BENCHMARKS.md. `--quick`: 20 changes on the
school site alone; the update's p50 over the plain subscriber's at most 5 (measured 1.6).
"""

from __future__ import annotations

import io
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench.benchmarks_md import machine_note, write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser, quick_skipped
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.ros_bridge.ros_env import LocalRosCore, stop_process_group
from wsnav.runtime.clock import WallClock
from wsnav.runtime.mqtt_bus import connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.messages import ZoneState
from wsnav.schemas.site import load_site

REPO = Path(__file__).resolve().parent.parent
SITES = {"school": REPO / "sites" / "school", "warehouse": REPO / "sites" / "warehouse"}
SECTION = "## ROS: zone message -> OccupancyGridUpdate (`wsnav ros bridge`)"
COMMAND = "./.venv/bin/python -m bench.ros_zone_grid"


@dataclass
class Result:
    site: str
    cells: int
    grid_bytes: int
    update_bytes: list[int]
    ros_ms: list[float]
    mqtt_ms: list[float]


def serialized_size(msg: Any) -> int:
    buf = io.BytesIO()
    msg.serialize(buf)
    return len(buf.getvalue())


def measure(name: str, site_dir: Path, changes: int, env: dict[str, str]) -> Result:
    import rospy
    from map_msgs.msg import OccupancyGridUpdate
    from nav_msgs.msg import OccupancyGrid

    site = load_site(site_dir)
    node = site.spec.nodes[0]
    arrived = threading.Condition()
    updates: list[tuple[float, int]] = []
    grids: list[int] = []

    def on_update(msg: Any) -> None:
        with arrived:
            updates.append((time.perf_counter(), serialized_size(msg)))
            arrived.notify_all()

    def on_grid(msg: Any) -> None:
        grids.append(serialized_size(msg))

    with BrokerThread(site_dir) as broker:
        creds = broker.credentials_dir / "robot1.json"
        bridge = subprocess.Popen(
            [sys.executable, "-m", "wsnav.cli", "ros", "bridge", "--site", str(site_dir), "--broker",
             f"{broker.host}:{broker.port}", "--credentials", str(creds), "--map-wait", "0", "--update-hold", "0"],
            env=env, stdout=subprocess.PIPE, text=True, start_new_session=True,
        )  # fmt: skip
        subs = [
            rospy.Subscriber("/wsn/zone_grid_updates", OccupancyGridUpdate, on_update, queue_size=10),
            rospy.Subscriber("/wsn/zone_grid", OccupancyGrid, on_grid, queue_size=1),
        ]
        publisher = connect_with_credentials(broker.host, broker.port, broker.credentials(node.id))
        clock = WallClock()
        watcher = connect_with_credentials(
            broker.host, broker.port, broker.credentials("operator"), clock=clock
        )
        topic = topics.zone_state(site.name, node.zone, node.id)
        watcher.subscribe(topic)
        ros_ms: list[float] = []
        mqtt_ms: list[float] = []
        sizes: list[int] = []
        try:
            assert bridge.stdout is not None
            if "zone bridge for site" not in bridge.stdout.readline():
                raise RuntimeError("the bridge did not start")
            deadline = time.monotonic() + 30
            while not grids or subs[0].get_num_connections() == 0:
                if time.monotonic() > deadline:
                    raise RuntimeError("no zone grid from the bridge")
                time.sleep(0.05)
            for i in range(changes + 5):
                with arrived:
                    n = len(updates)
                watcher.poll()
                sent, sent_clock = time.perf_counter(), clock.now()
                state = "blocked" if i % 2 == 0 else "clear"
                msg = ZoneState(zone=node.zone, node=node.id, state=state, seq=1000 + i)
                publisher.publish(topic, msg.to_payload(), qos=1, retain=True)
                # The first change may wait for the bridge's own MQTT login (retained, it arrives with it): on a
                # loaded machine that took over 10 s once (CI, beside other tests).
                wait_s = 60 if i == 0 else 10
                with arrived:
                    if not arrived.wait_for(lambda: len(updates) > n, wait_s):  # noqa: B023
                        raise RuntimeError(f"change {i}: no update within {wait_s} s")
                    got, size = updates[n]
                watcher.wait(5)
                copies = watcher.poll()
                if i >= 5:  # warm-up
                    ros_ms.append((got - sent) * 1000)
                    mqtt_ms.append((copies[0].received_at - sent_clock) * 1000 if copies else float("nan"))
                    sizes.append(size)
                time.sleep(0.05)
        finally:
            for sub in subs:
                sub.unregister()
            publisher.close()
            watcher.close()
            stop_process_group(bridge)
    return Result(name, site.grid.width * site.grid.height, grids[0], sizes, ros_ms, mqtt_ms)


def main() -> int:
    parser = quick_parser(__doc__)
    parser.add_argument("--changes", type=int, default=100)
    args = parse_quick_args(parser)
    if args.quick:
        args.changes = min(args.changes, 20)
    if shutil.which("roscore") is None:
        if args.quick:
            quick_skipped("no roscore: apt-get install ros-core python3-rospy ...")
        print("bench.ros_zone_grid: skipped (no roscore: apt-get install ros-core python3-rospy ...)")
        return 0
    import rospy

    results: list[Result] = []
    with tempfile.TemporaryDirectory(prefix="wsnav-bench-ros-") as tmp, LocalRosCore(Path(tmp)) as core:
        os.environ.update(ROS_MASTER_URI=core.uri, ROS_HOSTNAME="127.0.0.1", ROS_LOG_DIR=tmp)
        rospy.init_node("wsnav_bench", anonymous=True, disable_signals=True)
        for name, site_dir in list(SITES.items())[: 1 if args.quick else None]:
            print(f"{name}: {args.changes} changes ...", flush=True)
            results.append(measure(name, site_dir, args.changes, core.env()))
        rospy.signal_shutdown("done")
    rows = [
        "| site (grid) | MQTT -> update p50 / p99 | plain MQTT p50 / p99 (baseline) | p99 ratio | bytes per update | whole grid | ratio |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in results:
        ros50, ros99 = np.percentile(r.ros_ms, [50, 99])
        mq50, mq99 = np.nanpercentile(r.mqtt_ms, [50, 99])
        upd = int(np.median(r.update_bytes))
        rows.append(
            f"| {r.site} ({r.cells:,} cells) | {ros50:.2f} / {ros99:.2f} ms | {mq50:.2f} / {mq99:.2f} ms | "
            f"{ros99 / mq99:.1f}x | {upd:,} B | {r.grid_bytes:,} B | {upd / r.grid_bytes:.4f} |"
        )
    table = "\n".join(rows)
    print(table)
    if args.quick:
        r = results[0]
        check_ratio(
            f"MQTT -> OccupancyGridUpdate p50 / plain MQTT p50 ({r.site})",
            float(np.percentile(r.ros_ms, 50) / np.nanpercentile(r.mqtt_ms, 50)),
            5.0,
        )
        finish_quick()
    text = f"""```
{COMMAND}
```

{args.changes} zone changes per site (after 5 warm-up), one at a time, QoS 1, the broker embedded in the
benchmark and the bridge as its own process; timed from just before the MQTT publish to the
OccupancyGridUpdate's arrival in a rospy subscriber, against the same message reaching a plain MQTT subscriber
(the baseline, same run). Bytes: serialized ROS messages (an update is the zone's window; the whole grid is what
a subscriber gets once when it connects). {machine_note()}:

{table}
"""
    if not args.no_write:
        write_section(SECTION, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
