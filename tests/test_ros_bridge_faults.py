# pyright: reportMissingImports=false
"""`wsnav ros bridge` when things go wrong: a map that is not the site's, and a ROS master that goes away."""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import SCHOOL
from tests.ros_fixtures import RosMaster, WsnavChild, bridge_args, require_ros, wait_until
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.ros_bridge.ros_env import LocalRosCore, master_alive
from wsnav.schemas.site import load_site


def publish_map(topic: str, width: int, height: int, resolution: float, origin: tuple[float, float]) -> Any:
    import rospy
    from nav_msgs.msg import OccupancyGrid

    pub = rospy.Publisher(topic, OccupancyGrid, queue_size=1, latch=True)
    msg = OccupancyGrid()
    msg.header.frame_id = "map"
    msg.info.width, msg.info.height, msg.info.resolution = width, height, resolution
    msg.info.origin.position.x, msg.info.origin.position.y = origin
    msg.info.origin.orientation.w = 1.0
    msg.data = [0] * (width * height)
    pub.publish(msg)
    return pub


def test_a_site_whose_map_is_not_the_robots_is_refused_in_one_line(ros_node: RosMaster) -> None:
    with BrokerThread(SCHOOL) as broker:
        grid = load_site(SCHOOL).grid
        origin = (grid.origin[0], grid.origin[1])
        publish_map("/wrong/map", grid.width, grid.height, 0.1, origin)
        args = bridge_args(SCHOOL, broker)
        args[args.index("--map-wait") + 1] = "15"
        bridge = WsnavChild(["ros", "bridge", *args, "--map-topic", "/wrong/map"], ros_node.env())
        assert bridge.finish(60) == 2
        errors = [line for line in bridge.lines if line.startswith("wsnav: error:")]
        assert len(errors) == 1 and "Traceback" not in "\n".join(bridge.lines), bridge.lines
        assert "does not match /wrong/map: resolution 0.1 m, the site's is 0.05 m" in errors[0]

        publish_map("/right/map", grid.width, grid.height, grid.resolution, origin)
        args[args.index("--map-wait") + 1] = "15"
        bridge = WsnavChild(["ros", "bridge", *args, "--map-topic", "/right/map"], ros_node.env())
        try:
            bridge.wait_for("zone bridge for site school", 60)
        finally:
            bridge.stop()


def test_the_bridge_comes_back_when_the_master_is_restarted(tmp_path: Path) -> None:
    require_ros()
    with BrokerThread(SCHOOL) as broker:
        core = LocalRosCore(tmp_path).start()
        bridge = WsnavChild(["ros", "bridge", *bridge_args(SCHOOL, broker)], core.env())
        try:
            bridge.wait_for("zone bridge for site school", 60)
            core.stop()
            assert not master_alive(core.uri)
            bridge.wait_for("lost the ROS master", 30)
            core = LocalRosCore(tmp_path, port=core.port).start()
            wait_until(
                lambda: sum("zone bridge for site school" in line for line in bridge.lines) == 2,
                60,
                "the bridge registered again with the new master",
            )
            echo = subprocess.run(
                ["rostopic", "echo", "-n", "1", "/wsn/zone_grid/info/width"],
                env=core.env(),
                capture_output=True,
                text=True,
                timeout=60,
                check=False,
            )
            assert echo.stdout.startswith("1040"), (echo, bridge.lines)
            assert bridge.proc.poll() is None
        finally:
            bridge.stop()
            core.stop()


@pytest.mark.slow
def test_without_its_broker_the_bridge_serves_the_grid_says_so_and_picks_the_broker_up_later(
    ros_node: RosMaster, tmp_path: Path
) -> None:
    """The bridge gave up after 30 s without its broker and never published the grid, so a StaticLayer waiting
    for its map held move_base's start. It now serves the site's grid at once, says the broker is unreachable
    (and which stale policy applies), and goes live when the broker comes."""
    import rospy
    from nav_msgs.msg import OccupancyGrid

    from wsnav.broker.credentials import write_credentials
    from wsnav.broker.mosquitto.process import free_port

    creds = tmp_path / "creds"
    write_credentials(load_site(SCHOOL).spec, creds)
    port = free_port()
    args = [
        "--site", str(SCHOOL), "--broker", f"127.0.0.1:{port}", "--credentials", str(creds / "robot1.json"),
        "--map-wait", "0", "--connect-timeout", "2",
    ]  # fmt: skip
    bridge = WsnavChild(["ros", "bridge", *args], ros_node.env())
    try:
        bridge.wait_for("MQTT broker unreachable", 60)
        assert "stale policy ('keep')" in bridge.wait_for("MQTT broker unreachable", 1)
        grid = rospy.wait_for_message("/wsn/zone_grid", OccupancyGrid, timeout=30)
        assert (grid.info.width, grid.info.height) == (1040, 640)
        with BrokerThread(SCHOOL, port=port, credentials_dir=creds):
            bridge.wait_for("MQTT broker back", 60)
        assert bridge.proc.poll() is None
    finally:
        bridge.stop()


@pytest.mark.slow
def test_a_goal_held_for_a_move_base_that_never_listens_is_dropped_and_the_robot_says_so(
    ros_node: RosMaster,
) -> None:
    """Goals wait for move_base to listen (rospy drops what nobody hears), but not for ever: sent minutes later,
    one would start a drive nobody awaits any more."""
    import json

    import rospy
    import tf2_ros
    from geometry_msgs.msg import TransformStamped

    from wsnav.runtime.mqtt_bus import connect_with_credentials
    from wsnav.schemas import topics
    from wsnav.schemas.messages import RobotStatus

    tf = TransformStamped()  # where the robot is: the bridge's status needs a pose
    tf.header.stamp = rospy.Time.now()
    tf.header.frame_id, tf.child_frame_id = "map", "base_footprint"
    tf.transform.translation.x, tf.transform.translation.y = 12.0, 7.2
    tf.transform.rotation.w = 1.0
    broadcaster = tf2_ros.StaticTransformBroadcaster()
    broadcaster.sendTransform(tf)
    with BrokerThread(SCHOOL) as broker:
        op = connect_with_credentials(broker.host, broker.port, broker.credentials("operator"))
        op.subscribe(topics.robot_status("school", "robot1"))
        bridge = WsnavChild(
            ["ros", "bridge", *bridge_args(SCHOOL, broker, "--robot", "robot1", "--move-base", "/nobody")],
            ros_node.env(),
        )
        try:
            bridge.wait_for("supervising /nobody for robot1", 30)
            op.publish(topics.robot_goal("school", "robot1"), json.dumps({"goal": "B"}).encode(), qos=1)
            bridge.wait_for("holding goals until it is", 30)
            bridge.wait_for("goals held for move_base dropped after 30 s", 60)
            seen: list[RobotStatus] = []

            def cancelled() -> bool:
                seen.extend(RobotStatus.model_validate_json(m.payload) for m in op.poll() if m.payload)
                return any(s.state == "cancelled" for s in seen)

            wait_until(cancelled, 10, "the robot's status to say the goal is cancelled")
            status = next(s for s in seen if s.state == "cancelled")
            assert status.reason == "move_base did not listen within 30 s", status
        finally:
            bridge.stop()
            op.close()
