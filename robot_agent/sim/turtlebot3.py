"""A simulated TurtleBot3 Burger: acceleration-limited differential drive, a circular bumper, an LDS-01 lidar.

It implements wsnav.navigation.backend.RobotBackend. Time is whatever the owner passes to `step` (simulated time),
so the same robot runs in lock-step with the rest of a simulation, faster than real time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from wsnav.navigation.backend import BURGER_RADIUS_M, DriveLimits, LaserScan, Pose, Velocity
from wsnav.robot_agent.sim.lidar import LidarParams, cast_scan
from wsnav.robot_agent.sim.world_grid import SimWorldGrid

_BURGER = DriveLimits()
"""The controller's default limits are the Burger's: one place for the numbers."""


@dataclass(frozen=True)
class TurtleBot3Params:
    """TurtleBot3 Burger limits (ROBOTIS e-Manual; accelerations as in its Nav2 configuration)."""

    max_linear: float = _BURGER.max_linear
    max_angular: float = _BURGER.max_angular
    linear_accel: float = _BURGER.linear_accel
    angular_accel: float = _BURGER.angular_accel
    radius: float = BURGER_RADIUS_M
    max_substep: float = 0.02
    """Physics substep (s): a long `step` is integrated in pieces no longer than this."""
    velocity_noise: float = 0.0
    """Relative standard deviation of the velocity the wheels deliver against the one commanded (slip, motor
    response), drawn afresh at each command; 0 for an exact drive. Odometry (`distance_m`) sees the real motion."""

    def __post_init__(self) -> None:
        values = (self.max_linear, self.max_angular, self.linear_accel, self.angular_accel, self.radius)
        if min(values) <= 0 or self.max_substep <= 0:
            raise ValueError("TurtleBot3 limits, radius and substep must be positive")
        if not 0 <= self.velocity_noise < 0.5:
            raise ValueError("velocity_noise must be in [0, 0.5)")


class SimTurtleBot3:
    """The simulated robot; `step` advances it, the RobotBackend methods read and command it."""

    def __init__(
        self,
        robot_id: str,
        world: SimWorldGrid,
        start: Pose,
        params: TurtleBot3Params | None = None,
        lidar: LidarParams | None = None,
        seed: int = 0,
    ) -> None:
        self._id = robot_id
        self.world = world
        self.params = params or TurtleBot3Params()
        self.lidar = lidar or LidarParams()
        self._rng = np.random.default_rng(seed)
        self._x, self._y, self._yaw = float(start[0]), float(start[1]), _wrap(float(start[2]))
        self._v = 0.0
        self._w = 0.0
        self._cmd = Velocity(0.0, 0.0)
        self._delivered = self._cmd
        """What the wheels deliver of `_cmd` (equal to it without velocity_noise)."""
        self._scan: LaserScan | None = None
        self._next_scan: float | None = None
        self._in_contact = False
        self.collisions = 0
        """Collision events: each time the bumper meets something after having been free of contact.

        An obstacle placed on top of the robot is not a collision: the robot may drive out of it freely.
        """
        self.distance_m = 0.0
        """Odometry: path length travelled (m)."""
        self.time_s = 0.0
        """Simulated time integrated so far (s)."""
        self.world.place_robot(robot_id, self._x, self._y, self.params.radius)

    # RobotBackend
    @property
    def robot_id(self) -> str:
        return self._id

    @property
    def radius(self) -> float:
        return self.params.radius

    def pose(self) -> Pose:
        return self._x, self._y, self._yaw

    def velocity(self) -> Velocity:
        return Velocity(self._v, self._w)

    def scan(self) -> LaserScan | None:
        return self._scan

    def command(self, velocity: Velocity) -> None:
        p = self.params
        linear = _finite(velocity.linear)
        angular = _finite(velocity.angular)
        self._cmd = Velocity(
            min(max(linear, -p.max_linear), p.max_linear), min(max(angular, -p.max_angular), p.max_angular)
        )
        self._delivered = self._cmd
        if p.velocity_noise > 0:
            slip = 1.0 + p.velocity_noise * self._rng.standard_normal(2)
            self._delivered = Velocity(self._cmd.linear * float(slip[0]), self._cmd.angular * float(slip[1]))

    def stop(self) -> None:
        self._cmd = Velocity(0.0, 0.0)
        self._delivered = self._cmd

    @property
    def commanded(self) -> Velocity:
        """The last command after clamping to the limits."""
        return self._cmd

    @property
    def in_contact(self) -> bool:
        return self._in_contact

    # Simulation
    def step(self, dt: float, now: float) -> None:
        """Advance `dt` seconds, ending at simulated time `now`; take a scan when one is due."""
        if dt < 0 or not math.isfinite(dt):
            raise ValueError(f"dt must be a finite non-negative number, got {dt}")
        remaining = dt
        while remaining > 1e-12:
            h = min(remaining, self.params.max_substep)
            self._integrate(h)
            remaining -= h
        self.time_s += dt
        self.world.place_robot(self._id, self._x, self._y, self.params.radius)
        period = 1.0 / self.lidar.rate_hz
        if self._next_scan is None or now >= self._next_scan - 1e-9:
            self._scan = cast_scan(
                self.world.occupied_seen_by(self._id),
                self.world.frame,
                self.pose(),
                self.lidar,
                now,
                self._rng,
            )
            due = now + period if self._next_scan is None else self._next_scan + period
            self._next_scan = due if due > now else now + period

    def _integrate(self, h: float) -> None:
        p = self.params
        dv = p.linear_accel * h
        dw = p.angular_accel * h
        self._v += min(max(self._delivered.linear - self._v, -dv), dv)
        self._w += min(max(self._delivered.angular - self._w, -dw), dw)
        if self._v == 0.0 and self._w == 0.0:
            return
        x1, y1, yaw1 = _arc(self._x, self._y, self._yaw, self._v, self._w, h)
        moved = math.hypot(x1 - self._x, y1 - self._y)
        if moved == 0.0 or not self.overlaps(x1, y1) or self.overlaps(self._x, self._y):
            self._x, self._y, self._yaw = x1, y1, yaw1
            self.distance_m += moved
            if moved > 0.0:
                self._in_contact = False
            return
        # Contact: advance only as far as the bumper allows (bisection on the fraction of the step), then stop.
        lo, hi = 0.0, 1.0
        for _ in range(8):
            mid = 0.5 * (lo + hi)
            xm, ym, _ = _arc(self._x, self._y, self._yaw, self._v, self._w, h * mid)
            if self.overlaps(xm, ym):
                hi = mid
            else:
                lo = mid
        xl, yl, yawl = _arc(self._x, self._y, self._yaw, self._v, self._w, h * lo)
        self.distance_m += math.hypot(xl - self._x, yl - self._y)
        self._x, self._y, self._yaw = xl, yl, yawl
        self._v = 0.0
        self._w = 0.0
        if not self._in_contact:
            self.collisions += 1
        self._in_contact = True

    def overlaps(self, x: float, y: float) -> bool:
        """Whether the footprint circle at (x, y) overlaps an occupied cell's square or another robot."""
        radius = self.params.radius
        return self.clearance(x, y) < radius or self.world.robot_touching(self._id, x, y, radius) is not None

    def clearance(self, x: float, y: float, reach: float | None = None) -> float:
        """Distance (m) from (x, y) to the nearest occupied cell's square, capped at `reach` (default radius+1 cell)."""
        frame = self.world.frame
        res = frame.resolution
        limit = reach if reach is not None else self.params.radius + res
        u = (x - frame.origin_x) / res
        v = (y - frame.origin_y) / res
        span = math.ceil(limit / res) + 1
        c0, c1 = max(math.floor(u) - span, 0), min(math.floor(u) + span + 1, frame.width)
        r0, r1 = max(math.floor(v) - span, 0), min(math.floor(v) + span + 1, frame.height)
        if c1 <= c0 or r1 <= r0:
            return limit
        row, col = math.floor(v), math.floor(u)
        # A point in this cell is at most one cell diagonal nearer an occupied square than the centres are.
        if (
            0 <= row < frame.height
            and 0 <= col < frame.width
            and float(self.world.centre_clearance()[row, col]) - math.sqrt(2.0) * res >= limit
        ):
            return limit
        window = self.world.occupied[r0:r1, c0:c1]
        if not bool(window.any()):
            return limit
        rows, cols = np.nonzero(window)
        # Nearest point of each occupied square [c, c+1] x [r, r+1] to (u, v), in cells.
        cx = np.clip(u, cols + c0, cols + c0 + 1.0)
        cy = np.clip(v, rows + r0, rows + r0 + 1.0)
        d = float(np.min(np.hypot(cx - u, cy - v))) * res
        return min(d, limit)


def _arc(x: float, y: float, yaw: float, v: float, w: float, h: float) -> Pose:
    """Exact unicycle motion over h seconds at constant v, w."""
    if abs(w) < 1e-9:
        return x + v * h * math.cos(yaw), y + v * h * math.sin(yaw), yaw
    yaw1 = yaw + w * h
    r = v / w
    return x + r * (math.sin(yaw1) - math.sin(yaw)), y - r * (math.cos(yaw1) - math.cos(yaw)), _wrap(yaw1)


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


def _finite(value: float) -> float:
    return float(value) if math.isfinite(value) else 0.0
