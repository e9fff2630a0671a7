# pyright: reportMissingImports=false, reportUnknownMemberType=false, reportUnknownVariableType=false, reportUnknownArgumentType=false, reportAttributeAccessIssue=false
"""`wsnav sim --ros`: the simulated TurtleBot3 and its world as a ROS 1 node, a Gazebo-free test bed that any ROS
software (wsnav's own `robot --ros`, move_base, a teleop) can drive.

Out: `/scan` (sensor_msgs/LaserScan, 5 Hz, frame base_scan), `/odom` (nav_msgs/Odometry) and tf
odom -> base_footprint at `--rate`, static tf map -> odom (identity: the simulated odometry is exact and starts in
map coordinates) and base_footprint -> base_scan (identity: the simulated lidar sits on the robot's centre).
With `--clock` it also publishes `/clock` (rosgraph_msgs/Clock, simulated time advanced by each step, at the
loop's pace) and stamps everything with it, so nodes run with `/use_sim_time` (the experiment's ROS backend).
In: `/cmd_vel` (geometry_msgs/Twist); no command for `--cmd-timeout` stops the robot, as the real base's
watchdog does, so a driver that dies does not leave the robot running. The world is the site's map, plus the
obstacles the zone simulator publishes on MQTT (`sim/world`, retained) when a broker is given. Every collision is
one line on stdout and a count on `~collisions` (std_msgs/UInt32, latched); the last line sums up the run.
"""

from __future__ import annotations

import argparse
import math
import signal
import threading
import time
from types import FrameType
from typing import Any

from wsnav.navigation.backend import LaserScan, Velocity
from wsnav.navigation.planning.offline_plan import parse_point
from wsnav.robot_agent.sim.turtlebot3 import SimTurtleBot3
from wsnav.robot_agent.sim.world_grid import SimWorldGrid
from wsnav.ros_bridge.ros_env import master_uri, require_rospy, wait_for_master
from wsnav.runtime.bus import Bus
from wsnav.runtime.cli_support import CliError, read_robot_credentials
from wsnav.runtime.clock import WallClock
from wsnav.runtime.mqtt_bus import BusError, connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.messages import MAX_OPERATOR_PAYLOAD_BYTES, PayloadError, SimWorld, parse_payload
from wsnav.schemas.site import SiteError, load_site

ODOM_FRAME = "odom"
MAP_FRAME = "map"
BASE_FRAME = "base_footprint"
SCAN_FRAME = "base_scan"
SIM_TIME_START_S = 1.0
"""Where simulated time starts on /clock (ROS reads a zero time as "not set yet")."""


def sim_command(args: argparse.Namespace) -> int:
    if not args.ros:
        raise CliError(
            "only the ROS node exists: pass --ros (the simulated robot without ROS is `wsnav robot --sim`)"
        )
    require_rospy()
    try:
        site = load_site(args.site)
    except SiteError as exc:
        raise CliError(str(exc)) from None
    if (args.broker is None) != (args.credentials is None):
        raise CliError("--broker and --credentials go together (the world's obstacles come over MQTT)")
    robot_id = site.spec.robots[0].id if site.spec.robots else "robot"
    creds = read_robot_credentials(args.credentials, site) if args.credentials is not None else None
    if creds is not None:
        robot_id = creds.username
    start = parse_point(site, args.start, "--start")
    for name in ("rate", "cmd_timeout"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            raise CliError(f"--{name.replace('_', '-')} {value:g}: expected a positive number")
    world = SimWorldGrid(site.grid)
    robot = SimTurtleBot3(robot_id, world, start)
    uri = master_uri()
    wait_for_master(uri)
    bus: Bus | None = None
    if creds is not None:
        host, port = args.broker
        try:
            bus = connect_with_credentials(
                host,
                port,
                creds,
                client_id=f"{creds.username}-sim",
                clock=WallClock(),
                timeout_s=args.connect_timeout,
            )
        except BusError as exc:
            raise CliError(str(exc)) from None
        bus.subscribe(topics.sim_world(site.name), qos=1)
    try:
        node = SimNode(robot, world, bus, site.name, args.rate, args.cmd_timeout, clock=args.clock)
        print(
            f"simulated TurtleBot3 {robot_id} on {site.name} at {args.start} for ROS master {uri}"
            + (
                f", world from MQTT {args.broker[0]}:{args.broker[1]}"
                if bus is not None
                else ", the map alone"
            ),
            flush=True,
        )
        node.run()
    finally:
        if bus is not None:
            bus.close()
    return 0


class SimNode:
    """The real-time loop: step the robot, publish what its sensors see, take in commands and the world."""

    def __init__(
        self,
        robot: SimTurtleBot3,
        world: SimWorldGrid,
        bus: Bus | None,
        site: str,
        rate_hz: float,
        cmd_timeout_s: float,
        *,
        clock: bool = False,
    ) -> None:
        """`clock`: publish simulated time on /clock and stamp with it (else the ROS time of this node)."""
        import rospy
        import tf2_ros
        from geometry_msgs.msg import TransformStamped, Twist
        from nav_msgs.msg import Odometry
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import LaserScan as LaserScanMsg
        from std_msgs.msg import UInt32

        self.robot = robot
        self.world = world
        self.bus = bus
        self.world_topic = topics.sim_world(site)
        self.period_s = 1.0 / rate_hz
        self.cmd_timeout_s = cmd_timeout_s
        self._rospy = rospy
        self._lock = threading.Lock()
        """Held while the robot steps and while a command is applied (rospy calls back on its own thread)."""
        self._clock = WallClock()
        self._last_cmd = -math.inf
        """When the last /cmd_vel came, on `_clock` (the watchdog compares it with the loop's now)."""
        self._stopped_by_watchdog = True
        self._published_scan: LaserScan | None = None
        self._odom_type, self._scan_type, self._tf_type, self._count_type = (
            Odometry,
            LaserScanMsg,
            TransformStamped,
            UInt32,
        )
        rospy.init_node(f"wsnav_sim_{robot.robot_id}", disable_signals=True)  # Ctrl-C and SIGTERM are ours
        self.sim_t: float | None = SIM_TIME_START_S if clock else None
        """Simulated time (s) when publishing /clock: what every stamp says."""
        self.clock_pub = rospy.Publisher("/clock", Clock, queue_size=10) if clock else None
        self._clock_type = Clock
        self.odom_pub = rospy.Publisher("/odom", Odometry, queue_size=5)
        self.scan_pub = rospy.Publisher("/scan", LaserScanMsg, queue_size=2)
        self.collisions_pub = rospy.Publisher("~collisions", UInt32, queue_size=1, latch=True)
        self.collisions_pub.publish(UInt32(0))
        self.tf = tf2_ros.TransformBroadcaster()
        self.static_tf = tf2_ros.StaticTransformBroadcaster()
        self.static_tf.sendTransform(
            [
                self._transform(MAP_FRAME, ODOM_FRAME, 0.0, 0.0, 0.0),
                self._transform(BASE_FRAME, SCAN_FRAME, 0.0, 0.0, 0.0),
            ]
        )
        rospy.Subscriber("/cmd_vel", Twist, self._on_cmd_vel, queue_size=1)
        self._stop = threading.Event()

    def run(self) -> None:
        def on_signal(_sig: int, _frame: FrameType | None) -> None:
            self._stop.set()

        previous = signal.signal(signal.SIGTERM, on_signal)
        clock = self._clock
        last = clock.now()
        collisions = 0
        try:
            while not self._stop.is_set() and not self._rospy.is_shutdown():
                now = clock.now()
                self._take_world()
                with self._lock:
                    if now - self._last_cmd > self.cmd_timeout_s and not self._stopped_by_watchdog:
                        self.robot.stop()
                        self._stopped_by_watchdog = True
                    dt = min(now - last, 0.2)
                    self.robot.step(dt, now)
                last = now
                self._tick(dt)
                self._publish()
                if self.robot.collisions > collisions:
                    collisions = self.robot.collisions
                    x, y, yaw = self.robot.pose()
                    print(f"collision {collisions} at [{x:.2f}, {y:.2f}, {yaw:.2f}]", flush=True)
                    self.collisions_pub.publish(self._count_type(collisions))
                wait = last + self.period_s - clock.now()
                if wait > 0:
                    if self.bus is not None:
                        self.bus.wait(wait)
                    else:
                        time.sleep(wait)
        except KeyboardInterrupt:
            pass
        finally:
            signal.signal(signal.SIGTERM, previous)
            self.robot.stop()
            self._rospy.signal_shutdown("wsnav sim done")
        x, y, yaw = self.robot.pose()
        print(
            f"sim done: pose=[{x:.2f}, {y:.2f}, {yaw:.2f}] distance={self.robot.distance_m:.2f}m "
            f"collisions={self.robot.collisions}",
            flush=True,
        )

    # -- in ----------------------------------------------------------------------------------------------

    def _on_cmd_vel(self, msg: Any) -> None:
        with self._lock:
            self.robot.command(Velocity(float(msg.linear.x), float(msg.angular.z)))
            self._last_cmd = self._clock.now()
            self._stopped_by_watchdog = False

    def _take_world(self) -> None:
        if self.bus is None:
            return
        for message in self.bus.poll():
            if message.topic != self.world_topic:
                continue
            try:
                world = parse_payload(SimWorld, message.payload, max_bytes=MAX_OPERATOR_PAYLOAD_BYTES * 8)
            except PayloadError as exc:
                print(f"sim/world dropped (the world stays as it was): {exc}", flush=True)
                continue
            with self._lock:
                self.world.apply(world)
            print(
                f"world: {len(world.obstacles)} obstacle(s) {', '.join(self.world.obstacle_ids) or '-'}",
                flush=True,
            )

    # -- out ---------------------------------------------------------------------------------------------

    def _stamp(self) -> Any:
        if self.sim_t is None:
            return self._rospy.Time.now()
        return self._rospy.Time.from_sec(self.sim_t)

    def _tick(self, dt: float) -> None:
        """Advance simulated time by the step just taken and say so on /clock."""
        if self.sim_t is None or self.clock_pub is None:
            return
        self.sim_t += dt
        self.clock_pub.publish(self._clock_type(clock=self._stamp()))

    def _publish(self) -> None:
        stamp = self._stamp()
        x, y, yaw = self.robot.pose()
        v = self.robot.velocity()
        self.tf.sendTransform(self._transform(ODOM_FRAME, BASE_FRAME, x, y, yaw, stamp))
        odom = self._odom_type()
        odom.header.stamp, odom.header.frame_id, odom.child_frame_id = stamp, ODOM_FRAME, BASE_FRAME
        odom.pose.pose.position.x, odom.pose.pose.position.y = x, y
        odom.pose.pose.orientation.z, odom.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        odom.twist.twist.linear.x, odom.twist.twist.angular.z = v.linear, v.angular
        self.odom_pub.publish(odom)
        scan = self.robot.scan()
        if scan is not None and scan is not self._published_scan:
            self._published_scan = scan
            self.scan_pub.publish(self._scan_message(scan, stamp))

    def _scan_message(self, scan: LaserScan, stamp: Any) -> Any:
        msg = self._scan_type()
        msg.header.stamp, msg.header.frame_id = stamp, SCAN_FRAME
        n = len(scan.ranges)
        msg.angle_min = scan.angle_min
        msg.angle_increment = scan.angle_increment
        msg.angle_max = scan.angle_min + scan.angle_increment * (n - 1)
        period = 1.0 / self.robot.lidar.rate_hz
        msg.scan_time, msg.time_increment = period, period / n
        msg.range_min, msg.range_max = scan.range_min, scan.range_max
        msg.ranges = scan.ranges.tolist()
        return msg

    def _transform(self, parent: str, child: str, x: float, y: float, yaw: float, stamp: Any = None) -> Any:
        t = self._tf_type()
        t.header.stamp = stamp if stamp is not None else self._stamp()
        t.header.frame_id, t.child_frame_id = parent, child
        t.transform.translation.x, t.transform.translation.y = x, y
        t.transform.rotation.z, t.transform.rotation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        return t
