"""The local controller: regulated pure pursuit (Nav2's RPP) over the global plan, checked against the local costmap.

Pure pursuit steers toward a carrot one lookahead ahead on the path; RPP slows down in tight turns, near
obstacles (read from the inflation cost under the robot) and near the goal, and turns in place when the
path points away. Before each command the path ahead and the arc the robot is about to drive are checked
against the local costmap: inscribed or lethal cost there means `blocked`, the robot is told to stop and
the navigator replans (costmap_2d: the robot's centre on an inscribed cell means its footprint touches).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from wsnav.navigation.backend import DriveLimits, Pose, Velocity
from wsnav.navigation.planning.astar import densify, steps_to
from wsnav.zones.cost_values import FREE_SPACE, INSCRIBED_INFLATED_OBSTACLE, LETHAL_OBSTACLE, NO_INFORMATION
from wsnav.zones.geometry import GridFrame

Status = Literal["following", "arrived", "blocked", "idle"]


@dataclass(frozen=True)
class ControllerParams:
    """RPP's parameters; defaults follow Nav2's RPP tuned for a TurtleBot3 Burger (0.22 m/s)."""

    desired_linear: float = 0.22
    lookahead_dist: float = 0.5
    """Used when the lookahead is not scaled by speed."""
    min_lookahead: float = 0.3
    max_lookahead: float = 0.9
    lookahead_time: float = 1.5
    use_velocity_scaled_lookahead: bool = True
    use_regulated_linear_velocity_scaling: bool = True
    regulated_min_radius: float = 0.9
    """Curvature regulation: turns tighter than this radius slow the robot proportionally."""
    regulated_min_speed: float = 0.05
    use_cost_regulated_linear_velocity_scaling: bool = True
    cost_scaling_dist: float = 0.4
    cost_scaling_gain: float = 1.0
    inflation_cost_scaling_factor: float = 3.0
    """Must match the costmap's inflation (to read distance to obstacles back from cost)."""
    inscribed_radius: float = 0.105
    approach_velocity_scaling_dist: float = 0.5
    min_approach_linear: float = 0.05
    use_rotate_to_heading: bool = True
    rotate_to_heading_min_angle: float = 0.785
    rotate_to_heading_angular: float = 1.8
    xy_goal_tolerance: float = 0.07
    yaw_goal_tolerance: float = 0.15
    collision_horizon_s: float = 1.0
    """How far ahead in time the commanded arc is checked."""
    path_check_distance: float = 1.0
    """How far ahead along the path (m) lethal/inscribed cost makes the path `blocked`."""
    unknown_is_obstacle: bool = False
    """Treat NO_INFORMATION cells as blocking (a local costmap that tracks unknown space)."""
    path_step: float = 0.025
    """The path is densified to this spacing (m)."""
    control_dt: float = 0.05
    """Expected period between `compute` calls, for the acceleration limits."""

    def __post_init__(self) -> None:
        if not 0 < self.min_lookahead <= self.max_lookahead:
            raise ValueError("need 0 < min_lookahead <= max_lookahead")
        if self.xy_goal_tolerance <= 0 or self.path_step <= 0 or self.control_dt <= 0:
            raise ValueError("xy_goal_tolerance, path_step and control_dt must be positive")


@dataclass(frozen=True)
class ControlResult:
    velocity: Velocity
    status: Status
    reason: str = ""


STOP = Velocity(0.0, 0.0)


class PathFollower:
    """Follows one path at a time; call `compute` at the control rate with the robot's pose and odometry."""

    def __init__(self, params: ControllerParams | None = None, robot: DriveLimits | None = None) -> None:
        self.params = params or ControllerParams()
        self.robot = robot or DriveLimits()
        self._path: NDArray[np.float64] = np.zeros((0, 2))
        self._cum: NDArray[np.float64] = np.zeros(0)
        self._progress = 0
        self._goal_yaw: float | None = None
        self._arrived = False
        self._rotating = False

    @property
    def path(self) -> NDArray[np.float64]:
        return self._path

    @property
    def active(self) -> bool:
        return len(self._path) > 0 and not self._arrived

    def set_path(self, path: NDArray[np.float64], goal_yaw: float | None = None) -> None:
        """Follow `path` ((n, 2) metres, start to goal); `goal_yaw` also turns to that heading at the end."""
        pts = np.asarray(path, dtype=np.float64).reshape(-1, 2)
        if len(pts) == 0:
            self.clear()
            return
        dense = densify(pts, self.params.path_step) if len(pts) > 1 else pts.copy()
        self._path = dense
        seg = np.hypot(*np.diff(dense, axis=0).T) if len(dense) > 1 else np.zeros(0)
        self._cum = np.concatenate([[0.0], np.cumsum(seg)])
        self._progress = 0
        self._goal_yaw = goal_yaw
        self._arrived = False
        self._rotating = False

    def clear(self) -> None:
        self._path = np.zeros((0, 2))
        self._cum = np.zeros(0)
        self._progress = 0
        self._goal_yaw = None
        self._arrived = False
        self._rotating = False

    def remaining_m(self) -> float:
        """Path length still ahead of the robot's closest point."""
        if len(self._path) == 0:
            return 0.0
        return float(self._cum[-1] - self._cum[self._progress])

    def compute(
        self, pose: Pose, odom: Velocity, costs: NDArray[np.uint8], frame: GridFrame
    ) -> ControlResult:
        """The velocity to command now, and whether the robot is following, has arrived or is blocked."""
        if len(self._path) == 0:
            return ControlResult(STOP, "idle")
        p = self.params
        x, y, yaw = pose
        goal = self._path[-1]
        self._advance(x, y)
        goal_dist = math.hypot(goal[0] - x, goal[1] - y)

        if (
            self._arrived
            or goal_dist <= p.xy_goal_tolerance
            or (self._progress == len(self._path) - 1 and goal_dist <= 2 * p.xy_goal_tolerance)
        ):
            if self._goal_yaw is not None:
                err = _wrap(self._goal_yaw - yaw)
                if abs(err) > p.yaw_goal_tolerance:
                    self._arrived = True
                    return ControlResult(
                        Velocity(0.0, self._rotate(err, odom)), "following", "turning to goal"
                    )
            self._arrived = True
            return ControlResult(STOP, "arrived")

        blocked = self._path_blocked(x, y, costs, frame)
        if blocked:
            return ControlResult(STOP, "blocked", blocked)

        lookahead = self._lookahead(odom)
        carrot = self._carrot(x, y, lookahead)
        dx, dy = carrot[0] - x, carrot[1] - y
        c, s = math.cos(yaw), math.sin(yaw)
        lx, ly = c * dx + s * dy, -s * dx + c * dy
        angle = math.atan2(ly, lx)
        # Hysteresis: once turning in place, keep turning until nearly aligned.
        threshold = p.rotate_to_heading_min_angle * (0.35 if self._rotating else 1.0)
        if p.use_rotate_to_heading and abs(angle) > threshold:
            self._rotating = True
            return ControlResult(Velocity(0.0, self._rotate(angle, odom)), "following", "turning to path")
        self._rotating = False

        dist2 = lx * lx + ly * ly
        curvature = 2.0 * ly / dist2 if dist2 > 1e-9 else 0.0
        linear = self._regulated_linear(curvature, x, y, costs, frame)
        linear = min(
            linear, max(p.min_approach_linear, p.desired_linear * min(1.0, self._approach(goal_dist)))
        )
        dv = self.robot.linear_accel * p.control_dt
        linear = min(max(linear, odom.linear - dv), odom.linear + dv)
        linear = min(max(linear, 0.0), self.robot.max_linear)
        angular = linear * curvature
        angular = min(max(angular, -self.robot.max_angular), self.robot.max_angular)
        if self._arc_collides(pose, linear, angular, costs, frame):
            return ControlResult(STOP, "blocked", "the arc ahead meets an obstacle")
        return ControlResult(Velocity(linear, angular), "following")

    # --- pieces of RPP

    def _advance(self, x: float, y: float) -> None:
        """Move the progress index to the path point closest to the robot, never backwards, within a window."""
        window_m = self.params.max_lookahead + 0.5
        end = int(np.searchsorted(self._cum, self._cum[self._progress] + window_m, side="right"))
        seg = self._path[self._progress : max(end, self._progress + 1)]
        d2 = (seg[:, 0] - x) ** 2 + (seg[:, 1] - y) ** 2
        self._progress += int(np.argmin(d2))

    def _lookahead(self, odom: Velocity) -> float:
        p = self.params
        if not p.use_velocity_scaled_lookahead:
            return p.lookahead_dist
        return min(max(abs(odom.linear) * p.lookahead_time, p.min_lookahead), p.max_lookahead)

    def _carrot(self, x: float, y: float, lookahead: float) -> NDArray[np.float64]:
        """First path point at least `lookahead` from the robot (interpolated on the circle), else the goal.

        The path ahead is measured in growing stretches from the robot on, not whole: the carrot is a few
        dozen points ahead of thousands."""
        ahead = self._path[self._progress :]
        start, size = 0, 64
        before = np.float64(0.0)
        while start < len(ahead):
            part = ahead[start : start + size]
            d = np.hypot(part[:, 0] - x, part[:, 1] - y)
            beyond = np.flatnonzero(d >= lookahead)
            if len(beyond) > 0:
                k = int(beyond[0])
                i = start + k
                if i == 0:
                    return ahead[0]
                a, b = ahead[i - 1], ahead[i]
                da, db = (d[k - 1] if k > 0 else before), d[k]
                t = (lookahead - da) / (db - da) if db > da else 1.0
                return a + (b - a) * t
            before = d[-1]
            start, size = start + size, 2 * size
        return self._path[-1]

    def _approach(self, goal_dist: float) -> float:
        p = self.params
        if p.approach_velocity_scaling_dist <= 0:
            return 1.0
        remaining = min(goal_dist, self.remaining_m() + goal_dist)
        return remaining / p.approach_velocity_scaling_dist

    def _regulated_linear(
        self, curvature: float, x: float, y: float, costs: NDArray[np.uint8], frame: GridFrame
    ) -> float:
        p = self.params
        linear = min(p.desired_linear, self.robot.max_linear)
        if p.use_regulated_linear_velocity_scaling and abs(curvature) > 1e-9:
            radius = 1.0 / abs(curvature)
            if radius < p.regulated_min_radius:
                linear *= radius / p.regulated_min_radius
        if p.use_cost_regulated_linear_velocity_scaling:
            cost = _cost_at(costs, frame, x, y)
            if cost is not None and FREE_SPACE < cost < NO_INFORMATION:
                if cost >= INSCRIBED_INFLATED_OBSTACLE:
                    distance = p.inscribed_radius
                else:
                    distance = (
                        -math.log(cost / (INSCRIBED_INFLATED_OBSTACLE - 1)) / p.inflation_cost_scaling_factor
                        + p.inscribed_radius
                    )
                if distance < p.cost_scaling_dist:
                    linear *= p.cost_scaling_gain * distance / p.cost_scaling_dist
        return max(linear, p.regulated_min_speed)

    def _rotate(self, angle_error: float, odom: Velocity) -> float:
        """In-place turn toward `angle_error`, slowing so as to stop on the heading (no overshoot)."""
        p = self.params
        a = self.robot.angular_accel
        speed = min(
            p.rotate_to_heading_angular, self.robot.max_angular, math.sqrt(2.0 * a * abs(angle_error))
        )
        target = math.copysign(speed, angle_error)
        dw = a * p.control_dt
        return min(max(target, odom.angular - dw), odom.angular + dw)

    def _blocking(self, cost: NDArray[np.uint8]) -> NDArray[np.bool_]:
        blocking = (cost >= INSCRIBED_INFLATED_OBSTACLE) & (cost != NO_INFORMATION)
        if self.params.unknown_is_obstacle:
            blocking |= cost == NO_INFORMATION
        return blocking

    def _path_blocked(self, x: float, y: float, costs: NDArray[np.uint8], frame: GridFrame) -> str:
        """Why the path ahead (up to path_check_distance) is impassable, or '' when it is not."""
        p = self.params
        start = self._progress
        end = int(np.searchsorted(self._cum, self._cum[start] + p.path_check_distance, side="right"))
        pts = self._path[start:end]
        cost, known = _costs_at(costs, frame, pts)
        blocking = self._blocking(cost) & known
        if not bool(blocking.any()):
            return ""
        blocking = _ignore_stretch_being_left(blocking, cost, known, _cost_at(costs, frame, x, y))
        if not bool(blocking.any()):
            return ""
        k = int(np.argmax(blocking))
        ahead = float(self._cum[start + k] - self._cum[start])
        what = (
            "lethal"
            if cost[k] == LETHAL_OBSTACLE
            else "inscribed"
            if cost[k] != NO_INFORMATION
            else "unknown"
        )
        return f"path crosses {what} cost {ahead:.2f} m ahead"

    def _arc_collides(
        self, pose: Pose, linear: float, angular: float, costs: NDArray[np.uint8], frame: GridFrame
    ) -> bool:
        """Project the commanded arc over collision_horizon_s at cell-sized steps and look for blocking cost."""
        p = self.params
        travel = abs(linear) * p.collision_horizon_s
        if travel <= 0:
            return False
        n = max(1, math.ceil(travel / frame.resolution))
        t = steps_to(p.collision_horizon_s, n)
        x, y, yaw = pose
        if abs(angular) < 1e-9:
            px = x + linear * t * math.cos(yaw)
            py = y + linear * t * math.sin(yaw)
        else:
            r = linear / angular
            yaws = yaw + angular * t
            px = x + r * (np.sin(yaws) - math.sin(yaw))
            py = y - r * (np.cos(yaws) - math.cos(yaw))
        cost, known = _costs_at(costs, frame, np.column_stack([px, py]))
        blocking = self._blocking(cost) & known
        blocking = _ignore_stretch_being_left(blocking, cost, known, _cost_at(costs, frame, x, y))
        return bool(blocking.any())


def _ignore_stretch_being_left(
    blocking: NDArray[np.bool_], cost: NDArray[np.uint8], known: NDArray[np.bool_], here: int | None
) -> NDArray[np.bool_]:
    """`blocking` without the stretch the robot is leaving: it may start (or be pushed) into inscribed space, and
    the inscribed cells it drives out through do not count; lethal ones (a real obstacle) still do."""
    if here is None or here < INSCRIBED_INFLATED_OBSTACLE:
        return blocking
    lethal = known & (cost == LETHAL_OBSTACLE)
    return blocking & ~np.cumprod(blocking & ~lethal).astype(bool)


def _costs_at(
    costs: NDArray[np.uint8], frame: GridFrame, pts: NDArray[np.float64]
) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
    """Cost under each point and whether the point lies inside the costmap (outside: cost FREE, not known)."""
    rows, cols = frame.world_to_cells(pts[:, 0], pts[:, 1])
    h, w = costs.shape
    known = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    out = np.zeros(len(pts), dtype=np.uint8)
    out[known] = costs[rows[known], cols[known]]
    return out, known


def _cost_at(costs: NDArray[np.uint8], frame: GridFrame, x: float, y: float) -> int | None:
    row, col = frame.world_to_cell(x, y)
    h, w = costs.shape
    if 0 <= row < h and 0 <= col < w:
        return int(costs[row, col])
    return None


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))
