# pyright: reportMissingImports=false, reportUnknownMemberType=false, reportUnknownVariableType=false, reportUnknownArgumentType=false, reportAttributeAccessIssue=false
"""The ROS tests' move_base stand-in (tests/test_ros_bridge_move_base.py's FakeMoveBase) as a process that drives:
`python -m tests.move_base_standin`, the command `wsnav experiment --backend ros --move-base-cmd` starts in CI,
where no move_base is installed (Debian does not package it).

It is the same actionlib MoveBaseAction server, plan topic and modelled master costmap, named move_base; what it
adds is a drive: it publishes a straight plan from where /odom says the robot is to the goal and steers /cmd_vel
along it (turn toward the goal, then go at the Burger's 0.22 m/s), and ends SUCCEEDED within 0.1 m. What it
leaves out: navfn's plan round walls, DWA, the costmaps' use and every recovery, so a run on it says that the
experiment's ROS backend starts, drives, times and measures a move_base, not where move_base would go.
"""

from __future__ import annotations

import math
import time
from typing import Any

from tests.test_ros_bridge_move_base import FakeMoveBase

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
        self._plan_pub.publish(path)
        while not rospy.is_shutdown():
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

    rospy.init_node("move_base", disable_signals=True)
    DrivingMoveBase().start()
    print("move_base stand-in ready", flush=True)
    rospy.spin()


if __name__ == "__main__":
    main()
