# pyright: reportMissingImports=false, reportUnknownMemberType=false, reportUnknownVariableType=false, reportUnknownArgumentType=false, reportAttributeAccessIssue=false
"""The ROS tests' move_base stand-in, where no move_base is installed (Debian does not package it).

`FakeMoveBase`: the one tests/test_ros_bridge_move_base.py runs in its own process (see there what it leaves out).
`python -m tests.move_base_standin`: the same server as a process that drives, the command
`wsnav experiment --backend ros --move-base-cmd` starts in CI (tests/test_experiment_ros.py). Its node calls
itself move_base_node, as the real binary does, so its `~` parameters are read only where the experiment names
the node move_base (`__name:=move_base`, as TurtleBot3's launch file does). What it adds is a
drive: it publishes a straight plan from where /odom says the robot is to the goal, and again at its
`~planner_frequency` in /clock time as move_base replans (none at 0), each plan twice with its time as navfn
publishes it, and steers /cmd_vel along it (turn toward
the goal, then go at the Burger's 0.22 m/s), and ends SUCCEEDED within 0.1 m. What it leaves out: navfn's plan
round walls, DWA, the costmaps' use and every recovery (it publishes no /move_base/recovery_status), so a run on
it says that the experiment's ROS backend starts, drives, times and measures a move_base, not where move_base
would go.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field
from typing import Any

PLAN = [(12.0, 7.2), (25.0, 7.2), (25.0, 22.8), (29.0, 22.8)]
MASTER_DELAY_S = 0.3
"""A -> B by the south corridor (through z1) and the middle one (through z4)."""


@dataclass
class FakeMoveBase:
    """The boundary fake: records goals and cancels, publishes a plan for each goal, never arrives."""

    goals: list[tuple[str, float, float]] = field(default_factory=list)
    preempted: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    arrive: bool = False
    """Set by a test: the goal in progress ends SUCCEEDED."""
    goal_times: list[float] = field(default_factory=list)
    """When each goal of `goals` arrived (time.monotonic)."""
    master_updates: list[float] = field(default_factory=list)
    """When each update of the (modelled) master costmap went out."""

    def start(self) -> FakeMoveBase:
        import actionlib
        import rospy
        from move_base_msgs.msg import MoveBaseAction
        from nav_msgs.msg import Path as RosPath

        self._plan_pub = rospy.Publisher("/move_base/NavfnROS/plan", RosPath, queue_size=2, latch=True)
        self._path_type = RosPath
        self.server = actionlib.SimpleActionServer(
            "/move_base", MoveBaseAction, self._execute, auto_start=False
        )
        self.server.start()
        from geometry_msgs.msg import PoseStamped
        from move_base_msgs.msg import MoveBaseActionGoal

        relay = rospy.Publisher("/move_base/goal", MoveBaseActionGoal, queue_size=5)

        def rviz_goal(msg: Any) -> None:  # move_base.cpp's goalCB: the goal id is left empty
            action_goal = MoveBaseActionGoal()
            action_goal.header.stamp = rospy.Time.now()
            action_goal.goal.target_pose = msg
            relay.publish(action_goal)

        self._rviz = rospy.Subscriber("/move_base_simple/goal", PoseStamped, rviz_goal, queue_size=5)
        self._model_master_costmap()
        return self

    def _model_master_costmap(self) -> None:
        """move_base's global costmap as far as the bridge reads it: its `costmap` (the zone grid's cells, as a
        StaticLayer on the site's map gives) and `costmap_updates`, each zone update showing in the master
        MASTER_DELAY_S later (measured on the real costmap_2d: 6-102 ms, median 57). Costs are the zone grid's
        own values: the model leaves out the other layers and inflation."""
        import threading

        import rospy
        from map_msgs.msg import OccupancyGridUpdate
        from nav_msgs.msg import OccupancyGrid

        grid_pub = rospy.Publisher(
            "/move_base/global_costmap/costmap", OccupancyGrid, queue_size=1, latch=True
        )
        update_pub = rospy.Publisher(
            "/move_base/global_costmap/costmap_updates", OccupancyGridUpdate, queue_size=20
        )

        def show(msg: Any) -> None:
            update_pub.publish(msg)
            self.master_updates.append(time.monotonic())

        self._master = [
            rospy.Subscriber("/wsn/zone_grid", OccupancyGrid, grid_pub.publish, queue_size=1),
            rospy.Subscriber(
                "/wsn/zone_grid_updates",
                OccupancyGridUpdate,
                lambda msg: threading.Timer(MASTER_DELAY_S, show, (msg,)).start(),
                queue_size=20,
            ),
        ]

    def _execute(self, goal: Any) -> None:
        try:
            self._serve(goal)
        except Exception as exc:
            self.errors.append(repr(exc))
            raise

    def _serve(self, goal: Any) -> None:
        import rospy
        from geometry_msgs.msg import PoseStamped

        p = goal.target_pose.pose.position
        goal_id = self.server.current_goal.get_goal_id().id
        self.goals.append((goal_id, p.x, p.y))
        self.goal_times.append(time.monotonic())
        path = self._path_type()
        path.header.frame_id = "map"
        pts: list[tuple[float, float]] = []
        for (x0, y0), (x1, y1) in itertools.pairwise(PLAN):
            n = int(max(abs(x1 - x0), abs(y1 - y0)) / 0.05)
            pts.extend((x0 + (x1 - x0) * i / n, y0 + (y1 - y0) * i / n) for i in range(n))
        for x, y in pts:
            pose = PoseStamped()
            pose.pose.position.x, pose.pose.position.y = x, y
            path.poses.append(pose)
        self._plan_pub.publish(path)
        while not rospy.is_shutdown():
            if self.arrive:
                self.arrive = False
                self.server.set_succeeded()
                return
            if self.server.is_preempt_requested():
                self.preempted.append(goal_id)
                self.server.set_preempted()
                return
            time.sleep(0.02)


ARRIVED_M = 0.1
SPEED_MPS = 0.22
RATE_S = 0.05


class DrivingMoveBase(FakeMoveBase):
    """FakeMoveBase whose goals are driven to, not held until a test says so."""

    pose: tuple[float, float, float] | None = None

    def start(self) -> DrivingMoveBase:
        import rospy
        from geometry_msgs.msg import Twist
        from nav_msgs.msg import Odometry

        self._cmd = rospy.Publisher("/cmd_vel", Twist, queue_size=1)
        self._twist = Twist
        rospy.Subscriber("/odom", Odometry, self._on_odom, queue_size=1)
        super().start()
        return self

    def _navfn_publish(self, path: Any) -> None:
        """One makePlan's plan as navfn publishes it: twice, both stamped with the plan's time, first from
        getPlanFromPotential and then, the goal pose appended, at the end of makePlan."""
        import copy

        import rospy

        path.header.stamp = rospy.Time.now()
        first = copy.deepcopy(path)
        first.poses = first.poses[:-1]
        self._plan_pub.publish(first)
        self._plan_pub.publish(path)

    def _on_odom(self, msg: Any) -> None:
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        self.pose = (float(p.x), float(p.y), 2 * math.atan2(float(q.z), float(q.w)))

    def _drive(self, linear: float, angular: float) -> None:
        twist = self._twist()
        twist.linear.x, twist.angular.z = linear, angular
        self._cmd.publish(twist)

    def _serve(self, goal: Any) -> None:
        import rospy
        from geometry_msgs.msg import PoseStamped

        gx, gy = goal.target_pose.pose.position.x, goal.target_pose.pose.position.y
        self.goals.append((self.server.current_goal.get_goal_id().id, gx, gy))
        while self.pose is None and not rospy.is_shutdown():
            time.sleep(RATE_S)
        assert self.pose is not None
        path = self._path_type()
        path.header.frame_id = "map"
        for i in range(21):
            pose = PoseStamped()
            pose.pose.position.x = self.pose[0] + (gx - self.pose[0]) * i / 20
            pose.pose.position.y = self.pose[1] + (gy - self.pose[1]) * i / 20
            path.poses.append(pose)
        self._navfn_publish(path)
        frequency = float(rospy.get_param("~planner_frequency", 0.0))
        planned = rospy.get_time()
        while not rospy.is_shutdown():
            if frequency > 0 and rospy.get_time() - planned >= 1.0 / frequency:
                planned = rospy.get_time()
                self._navfn_publish(path)  # move_base's planner thread making its plan again
            if self.server.is_preempt_requested():
                self._drive(0.0, 0.0)
                self.server.set_preempted()
                return
            x, y, yaw = self.pose
            if math.hypot(gx - x, gy - y) < ARRIVED_M:
                self._drive(0.0, 0.0)
                self.server.set_succeeded()
                return
            error = math.remainder(math.atan2(gy - y, gx - x) - yaw, math.tau)
            self._drive(SPEED_MPS if abs(error) < 0.3 else 0.0, max(-1.5, min(1.5, 2.0 * error)))
            time.sleep(RATE_S)


def main() -> None:
    import rospy

    rospy.init_node("move_base_node", disable_signals=True)  # the real binary's name; `__name:=` renames it
    DrivingMoveBase().start()
    print("move_base stand-in ready", flush=True)
    rospy.spin()


if __name__ == "__main__":
    main()
