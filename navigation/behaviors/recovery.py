"""Stock move_base's oscillation detection, patience and recovery behaviours (ROS 1 noetic, move_base.cpp).

The bookkeeping only; the navigator (wsnav.navigation.navigator) runs the behaviours. move_base's rules, as its
`executeCycle` has them:

- Oscillation: each control cycle, once the robot is `oscillation_distance` from the pose last noted, the pose
  and time are noted again (and the recovery sequence starts afresh if oscillation had started it). If
  `oscillation_timeout` passes without that, the robot stops and the next recovery behaviour runs.
- Controller patience: the local planner finding no valid command for `controller_patience` seconds since its
  last valid one runs the next behaviour (before that, each failure goes back to planning).
- Planner patience: no global plan for `planner_patience` seconds runs the next behaviour.
- The behaviours, in move_base's default order: conservative reset (the obstacle layer cleared outside a square
  of side `conservative_reset_dist` around the robot), rotate in place, aggressive reset (a square of side four
  circumscribed radii), rotate again. After each, planning starts again and the oscillation clock restarts.
  When all have run and the trouble persists, move_base aborts the goal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from wsnav.navigation.backend import Pose

RecoveryTrigger = Literal["oscillation", "controlling", "planning"]
ABORT_REASONS: dict[RecoveryTrigger, str] = {
    "oscillation": "the robot appears to be oscillating",
    "controlling": "no valid control could be found",
    "planning": "no valid plan could be found",
}
"""move_base's abort messages, by what started the recoveries."""


@dataclass(frozen=True)
class RecoveryParams:
    """ROBOTIS' turtlebot3_navigation (noetic) move_base_params.yaml, and move_base's default behaviours."""

    oscillation_timeout_s: float = 10.0
    oscillation_distance_m: float = 0.2
    planner_patience_s: float = 5.0
    controller_patience_s: float = 15.0
    conservative_reset_dist_m: float = 3.0
    aggressive_reset_dist_m: float = 0.59
    """move_base sets it to 4 x the circumscribed radius: TurtleBot3 Burger's footprint, 4 x 0.148 m."""
    rotate: bool = True
    """clearing_rotation_allowed."""
    rotate_max_vel: float = 1.0
    rotate_min_vel: float = 0.4
    rotate_acc_lim: float = 3.2
    rotate_tolerance: float = 0.1
    """rotate_recovery's defaults (max_rotational_vel, min_in_place_rotational_vel, acc_lim_th,
    yaw_goal_tolerance)."""
    on_no_path: bool = True
    """Planner patience applies (stock). False: no path means waiting for a zone to change (Algorithm 3)."""

    @property
    def behaviours(self) -> tuple[str, ...]:
        if self.rotate:
            return ("conservative_reset", "rotate_recovery", "aggressive_reset", "rotate_recovery")
        return ("conservative_reset", "aggressive_reset")

    def reset_distance(self, behaviour: str) -> float | None:
        """The side of the square kept by a clearing behaviour; None for a rotation."""
        return {
            "conservative_reset": self.conservative_reset_dist_m,
            "aggressive_reset": self.aggressive_reset_dist_m,
        }.get(behaviour)


class MoveBaseRecovery:
    """move_base's recovery state for one goal: which behaviour is next, and the clocks that start them."""

    def __init__(self, params: RecoveryParams | None = None) -> None:
        self.params = params or RecoveryParams()
        self.index = 0
        self.trigger: RecoveryTrigger = "planning"
        self.run = 0
        """Behaviours run, all goals."""
        self._osc_pose: Pose | None = None
        self._osc_reset_t = 0.0
        self._last_valid_control_t = 0.0
        self._no_plan_since: float | None = None

    def start_goal(self, now: float, pose: Pose) -> None:
        """A new goal: move_base's resetState and the clocks taken afresh."""
        self.index, self.trigger = 0, "planning"
        self._osc_pose, self._osc_reset_t = pose, now
        self._last_valid_control_t = now
        self._no_plan_since = None

    def restart_clocks(self, now: float, pose: Pose) -> None:
        """The robot stood still on purpose (it yielded to another robot), which stock move_base never does:
        progress and patience count from now, so the wait itself is not taken for an oscillation."""
        self._osc_pose, self._osc_reset_t = pose, now
        self._last_valid_control_t = now
        self._no_plan_since = None

    def control_cycle(self, now: float, pose: Pose) -> bool:
        """Note progress at the start of a control cycle; True when the robot has oscillated for too long."""
        p = self.params
        if (
            self._osc_pose is None
            or math.hypot(pose[0] - self._osc_pose[0], pose[1] - self._osc_pose[1])
            >= p.oscillation_distance_m
        ):
            self._osc_pose, self._osc_reset_t = pose, now
            if self.trigger == "oscillation":
                self.index = 0
        return p.oscillation_timeout_s > 0 and now > self._osc_reset_t + p.oscillation_timeout_s

    def valid_control(self, now: float) -> None:
        self._last_valid_control_t = now
        if self.trigger == "controlling":
            self.index = 0

    def controller_out_of_patience(self, now: float) -> bool:
        return now > self._last_valid_control_t + self.params.controller_patience_s

    def planned(self, now: float) -> None:
        """A global plan was found."""
        self._no_plan_since = None
        if self.trigger == "planning":
            self.index = 0

    def plan_failed(self, now: float) -> bool:
        """No global plan; True once planner patience has run out (and it applies)."""
        if self._no_plan_since is None:
            self._no_plan_since = now
        return self.params.on_no_path and now > self._no_plan_since + self.params.planner_patience_s

    def next_behaviour(self, trigger: RecoveryTrigger) -> str | None:
        """The behaviour to run now, or None when all have run (move_base aborts)."""
        self.trigger = trigger
        behaviours = self.params.behaviours
        if self.index >= len(behaviours):
            return None
        name = behaviours[self.index]
        self.index += 1
        self.run += 1
        return name

    def behaviour_done(self, now: float) -> None:
        """After a behaviour: the robot gets a fresh oscillation timeout, and planning starts over."""
        self._osc_reset_t = now
        self._no_plan_since = None


@dataclass
class Rotation:
    """rotate_recovery in progress: a full turn in place at its speed profile."""

    last_yaw: float
    turned: float = 0.0

    def step(self, yaw: float, params: RecoveryParams) -> float | None:
        """The angular velocity to command now, or None once the full turn is done."""
        self.turned += abs(math.remainder(yaw - self.last_yaw, math.tau))
        self.last_yaw = yaw
        left = math.tau - self.turned
        if left <= params.rotate_tolerance:
            return None
        speed = math.sqrt(2.0 * params.rotate_acc_lim * left)
        return min(max(speed, params.rotate_min_vel), params.rotate_max_vel)
