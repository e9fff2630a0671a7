# pyright: reportMissingImports=false
"""Zone message on MQTT -> the zone in move_base's master costmap, on the REAL move_base (costmap_2d, navfn).

    ./.venv/bin/python -m bench.ros_master_latency --devel WS/devel [--changes 60] [--no-write]

move_base is not packaged for Debian: build it from the noetic sources as docs/ros.md ("Tests") says and give
its catkin `devel` folder. A roscore of its own, map_server with the school map, move_base loaded with the shipped
TurtleBot3 costmap set (ros_bridge/catkin/wsnav_ros/config, 10 Hz global costmap), `wsnav ros bridge` as its own
process, static tf (robot at the south corridor); the broker in this process. Node n5 flips zone z4 between
`blocked` and `clear`, one change every 1 to 2 s at random (so the changes fall at every phase of the
costmap's 10 Hz cycles, not always at the same one); each is timed from just before the MQTT publish to (a) the
bridge's `/wsn/zone_grid_updates` and (b) the first `/move_base/global_costmap/costmap_updates` whose cell at
the zone's centre shows the new state (lethal, or free). (a) is the baseline of the same run.
`--quick`: 10 changes, (b)'s p50 over (a)'s at most 200 (measured 17-26 on 2026-11-28); without move_base it is skipped (CI cannot
fetch move_base's sources, docs/ros.md).
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.benchmarks_md import machine_note, write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser, quick_skipped
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.ros_bridge.ros_env import LocalRosCore, stop_process_group
from wsnav.runtime.mqtt_bus import connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.messages import ZoneState

REPO = Path(__file__).resolve().parent.parent
SITE = REPO / "sites" / "school"
CONFIG = REPO / "ros_bridge" / "catkin" / "wsnav_ros" / "config"
SECTION = "## ROS: zone message -> move_base's master costmap (the real costmap_2d)"
COMMAND = "./.venv/bin/python -m bench.ros_master_latency --devel WS/devel"
ZONE, NODE, CENTRE = "z4", "n5", (25.0, 15.0)
ROBOT_AT = (25.0, 7.2)


def _in_devel(devel: Path, command: str, env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        ["bash", "-c", f"source {devel}/setup.bash && exec {command}"],
        env=env, stdout=log.open("wb"), stderr=subprocess.STDOUT, start_new_session=True,
    )  # fmt: skip


def _static_tf() -> Any:
    import rospy
    import tf2_ros
    from geometry_msgs.msg import TransformStamped

    def tf(parent: str, child: str, x: float = 0.0, y: float = 0.0) -> Any:
        t = TransformStamped()
        t.header.stamp = rospy.Time.now()
        t.header.frame_id, t.child_frame_id = parent, child
        t.transform.translation.x, t.transform.translation.y = x, y
        t.transform.rotation.w = 1.0
        return t

    broadcaster = tf2_ros.StaticTransformBroadcaster()
    broadcaster.sendTransform(
        [tf("map", "odom"), tf("odom", "base_footprint", *ROBOT_AT), tf("base_footprint", "base_scan")]
    )
    return broadcaster


def measure(devel: Path, changes: int, work: Path) -> tuple[list[float], list[float]]:
    with LocalRosCore(work) as core:
        env = core.env()
        os.environ.update(ROS_MASTER_URI=core.uri, ROS_HOSTNAME="127.0.0.1", ROS_LOG_DIR=str(work))
        import rospy
        from map_msgs.msg import OccupancyGridUpdate
        from nav_msgs.msg import OccupancyGrid

        rospy.init_node("wsnav_bench_master", anonymous=True, disable_signals=True)
        keep = _static_tf()
        for ns, name in [
            ("/move_base/global_costmap", "costmap_common_params_burger.yaml"),
            ("/move_base/local_costmap", "costmap_common_params_burger.yaml"),
            ("/move_base", "global_costmap_params.yaml"),
            ("/move_base", "local_costmap_params.yaml"),
        ]:
            subprocess.run(["rosparam", "load", str(CONFIG / name), ns], env=env, check=True)
        procs = [
            _in_devel(devel, f"{devel}/lib/map_server/map_server {SITE}/map.yaml", env, work / "map.log"),
            _in_devel(
                devel, f"{devel}/lib/move_base/move_base __name:=move_base", env, work / "move_base.log"
            ),
        ]
        grid_at: list[float] = []
        master: list[tuple[float, int]] = []
        frame: dict[str, float] = {}
        lock = threading.Condition()

        def on_master(msg: Any) -> None:
            frame.update(
                res=msg.info.resolution, ox=msg.info.origin.position.x, oy=msg.info.origin.position.y
            )

        def cell(msg: Any) -> int | None:
            if not frame:
                return None
            col = int((CENTRE[0] - frame["ox"]) / frame["res"]) - msg.x
            row = int((CENTRE[1] - frame["oy"]) / frame["res"]) - msg.y
            if 0 <= col < msg.width and 0 <= row < msg.height:
                return int(msg.data[row * msg.width + col])
            return None

        def on_master_update(msg: Any) -> None:
            value = cell(msg)
            if value is not None:
                with lock:
                    master.append((time.perf_counter(), value))
                    lock.notify_all()

        def on_grid_update(_msg: Any) -> None:
            with lock:
                grid_at.append(time.perf_counter())
                lock.notify_all()

        subs = [
            rospy.Subscriber("/move_base/global_costmap/costmap", OccupancyGrid, on_master, queue_size=1),
            rospy.Subscriber(
                "/move_base/global_costmap/costmap_updates",
                OccupancyGridUpdate,
                on_master_update,
                queue_size=50,
            ),
            rospy.Subscriber("/wsn/zone_grid_updates", OccupancyGridUpdate, on_grid_update, queue_size=50),
        ]
        with BrokerThread(SITE) as broker:
            bridge = subprocess.Popen(
                [sys.executable, "-m", "wsnav.cli", "ros", "bridge", "--site", str(SITE), "--broker",
                 f"{broker.host}:{broker.port}", "--credentials", str(broker.credentials_dir / "robot1.json"),
                 "--map-wait", "0"],
                env=env, stdout=(work / "bridge.log").open("wb"), stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip
            node = connect_with_credentials(broker.host, broker.port, broker.credentials(NODE))
            grid_ms: list[float] = []
            master_ms: list[float] = []
            try:
                deadline = time.monotonic() + 60
                while not frame:
                    if time.monotonic() > deadline:
                        raise SystemExit("move_base's global costmap never came up (see move_base.log)")
                    time.sleep(0.2)
                topic = topics.zone_state("school", ZONE, NODE)
                spacing = random.Random(1)
                for i in range(changes + 4):
                    blocked = i % 2 == 0
                    with lock:
                        n_grid, n_master = len(grid_at), len(master)
                    sent = time.perf_counter()
                    state = ZoneState(
                        zone=ZONE, node=NODE, state="blocked" if blocked else "clear", seq=100 + i
                    )
                    node.publish(topic, state.to_payload(), qos=1, retain=True)

                    def shown() -> bool:
                        return any((v == 100) == blocked for _, v in master[n_master:])  # noqa: B023

                    with lock:
                        if not lock.wait_for(lambda: len(grid_at) > n_grid and shown(), 10):  # noqa: B023
                            raise SystemExit(f"change {i}: not in the master costmap within 10 s")
                        got_grid = grid_at[n_grid]
                        got_master = next(t for t, v in master[n_master:] if (v == 100) == blocked)
                    if i >= 4:  # warm-up
                        grid_ms.append((got_grid - sent) * 1000)
                        master_ms.append((got_master - sent) * 1000)
                    time.sleep(spacing.uniform(1.0, 2.0))  # every phase of the 10 Hz cycles
            finally:
                node.close()
                stop_process_group(bridge)
                for sub in subs:
                    sub.unregister()
                for proc in procs:
                    stop_process_group(proc)
                del keep
    return grid_ms, master_ms


def main() -> int:
    parser = quick_parser(__doc__)
    parser.add_argument(
        "--devel",
        type=Path,
        default=os.environ.get("WSNAV_MOVE_BASE_DEVEL"),
        help="the catkin devel folder of move_base (default: $WSNAV_MOVE_BASE_DEVEL)",
    )
    parser.add_argument("--changes", type=int, default=60)
    args = parse_quick_args(parser)
    if args.quick:
        args.changes = min(args.changes, 10)
    if args.devel is None:
        if args.quick:
            quick_skipped("needs move_base built from source (--devel, docs/ros.md), which CI cannot fetch")
        print("bench.ros_master_latency: skipped: needs move_base built from source (--devel, docs/ros.md)")
        return 0
    args.devel = Path(args.devel)
    if not (args.devel / "lib" / "move_base" / "move_base").is_file():
        raise SystemExit(f"{args.devel}: no lib/move_base/move_base (build it as docs/ros.md says)")
    with tempfile.TemporaryDirectory() as tmp:
        grid_ms, master_ms = measure(args.devel.resolve(), args.changes, Path(tmp))
    g, m = np.array(grid_ms), np.array(master_ms)
    rows = [
        "| stage | changes | p50 | p99 | max | ratio to the update (p50) |",
        "| --- | --- | --- | --- | --- | --- |",
        f"| MQTT -> `/wsn/zone_grid_updates` (baseline) | {g.size} | {np.percentile(g, 50):.1f} ms | "
        f"{np.percentile(g, 99):.1f} ms | {g.max():.1f} ms | 1.0x |",
        f"| MQTT -> zone in `/move_base/global_costmap/costmap_updates` | {m.size} | {np.percentile(m, 50):.1f} ms | "
        f"{np.percentile(m, 99):.1f} ms | {m.max():.1f} ms | {np.percentile(m, 50) / np.percentile(g, 50):.0f}x |",
    ]
    text = "\n".join(rows)
    print(text)
    if args.quick:
        check_ratio(
            "MQTT -> master costmap p50 / MQTT -> zone grid update p50",
            np.percentile(m, 50) / np.percentile(g, 50),
            200.0,
        )
        finish_quick()
    if not args.no_write:
        doc = "\n\n".join((__doc__ or "").split("\n\n")[2:]).strip()
        write_section(
            SECTION,
            f"```sh\n{COMMAND}\n```\n\n{doc}\n\nMeasured with {machine_note()}:\n\n{text}\n\n"
            "The master's share is costmap_2d's update cycle (10 Hz here: up to 100 ms until the next cycle reads "
            "the layer) plus its publish cycle (`publish_frequency` 10 Hz); the bridge re-sends a replanned goal "
            "only once the master shows the change.",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
