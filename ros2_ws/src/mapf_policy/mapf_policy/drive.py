"""Pure differential-drive kinematics for one grid cell move (no ROS).

Grid-to-world frame, written once for the whole fleet (docs/FLEET.md):
    x = col * cell_size,  y = -row * cell_size,  z up (right-handed, REP 103).
So the map is seen from above with row 0 at the top: "up" (row - 1) is +y, "right" (col + 1) is +x.
yaw 0 faces +x (right), yaw +pi/2 faces +y (up).

A cell move is executed as: turn in place (angular speed <= max_angular) to face the target cell,
optionally wait until a common drive start time (so robots that follow each other drive in
lockstep), then drive straight (linear speed <= max_linear) onto the target. The motion is a time
series of constant (v, w) commands, each held for one control period dt. Each phase uses the
fewest periods that respect the limit and a constant speed within the phase, so integrating the
commands lands exactly on the target (up to floating point); odometry is that integration.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Sequence, Tuple

Command = Tuple[float, float]  # (linear m/s, angular rad/s), held for one period dt

MAX_LINEAR = 0.2     # m/s, the paper's robots (section V-B)
MAX_ANGULAR = 1.57   # rad/s


@dataclass(frozen=True)
class Pose2D:
    x: float
    y: float
    yaw: float


@dataclass(frozen=True)
class DriveLimits:
    max_linear: float = MAX_LINEAR
    max_angular: float = MAX_ANGULAR

    def __post_init__(self):
        for name in ("max_linear", "max_angular"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"DriveLimits.{name} must be a positive finite number, got {value!r}")


def cell_to_xy(cell: Sequence[int], cell_size: float) -> Tuple[float, float]:
    """Centre of cell (row, col) in the world frame."""
    row, col = int(cell[0]), int(cell[1])
    return col * cell_size, -row * cell_size


def xy_to_cell(x: float, y: float, cell_size: float) -> Tuple[int, int]:
    """Cell (row, col) whose centre is nearest to (x, y)."""
    return int(round(-y / cell_size)), int(round(x / cell_size))


def wrap_angle(angle: float) -> float:
    """Angle in [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def yaw_from_quaternion(qz: float, qw: float) -> float:
    """Yaw of a rotation about z given as quaternion (0, 0, qz, qw)."""
    return 2.0 * math.atan2(qz, qw)


def quaternion_from_yaw(yaw: float) -> Tuple[float, float, float, float]:
    """(x, y, z, w) quaternion of a rotation by yaw about z."""
    return 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def _constant_phase(amount: float, limit: float, dt: float) -> Tuple[int, float]:
    """Fewest periods of dt covering |amount| at speed <= limit, and the constant speed to use."""
    if amount == 0.0:
        return 0, 0.0
    # The small slack keeps an exact multiple (e.g. 0.2 m at 0.2 m/s in 10 x 0.1 s) from
    # becoming one extra period through rounding.
    periods = max(1, math.ceil(abs(amount) / (limit * dt) - 1e-9))
    return periods, amount / (periods * dt)


def turn_time(pose: Pose2D, target_xy: Tuple[float, float], limits: DriveLimits,
              dt: float, min_distance: float = 1e-6) -> float:
    """Seconds the turn phase of plan_cell_move would take (0 when there is nothing to drive)."""
    dx, dy = target_xy[0] - pose.x, target_xy[1] - pose.y
    if math.hypot(dx, dy) < min_distance:
        return 0.0
    periods, _ = _constant_phase(wrap_angle(math.atan2(dy, dx) - pose.yaw), limits.max_angular, dt)
    return periods * dt


def plan_cell_move(pose: Pose2D, target_xy: Tuple[float, float], limits: DriveLimits, dt: float,
                   drive_start_s: float = 0.0, min_distance: float = 1e-6) -> List[Command]:
    """Commands (each held for dt) that turn to face target_xy, then drive onto it.

    drive_start_s: the straight drive does not begin before this many seconds after the move
    starts (zero commands fill the wait); a turn longer than that delays the drive instead.
    A target closer than min_distance gives no commands (a stay).
    """
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"control period dt must be a positive finite number, got {dt!r}")
    if not (math.isfinite(drive_start_s) and drive_start_s >= 0):
        raise ValueError(f"drive_start_s must be a finite number >= 0, got {drive_start_s!r}")
    dx, dy = target_xy[0] - pose.x, target_xy[1] - pose.y
    distance = math.hypot(dx, dy)
    if distance < min_distance:
        return []
    turn_periods, w = _constant_phase(wrap_angle(math.atan2(dy, dx) - pose.yaw), limits.max_angular, dt)
    wait_periods = max(0, math.ceil(drive_start_s / dt - 1e-9) - turn_periods)
    drive_periods, v = _constant_phase(distance, limits.max_linear, dt)
    return [(0.0, w)] * turn_periods + [(0.0, 0.0)] * wait_periods + [(v, 0.0)] * drive_periods


def integrate(pose: Pose2D, v: float, w: float, dt: float) -> Pose2D:
    """Pose after holding (v, w) for dt (exact unicycle integration)."""
    if abs(w) < 1e-12:
        return Pose2D(pose.x + v * dt * math.cos(pose.yaw), pose.y + v * dt * math.sin(pose.yaw), pose.yaw)
    yaw1 = pose.yaw + w * dt
    radius = v / w
    return Pose2D(pose.x + radius * (math.sin(yaw1) - math.sin(pose.yaw)),
                  pose.y - radius * (math.cos(yaw1) - math.cos(pose.yaw)),
                  wrap_angle(yaw1))


def rollout(pose: Pose2D, commands: Sequence[Command], dt: float) -> List[Pose2D]:
    """Poses at the start of every period and after the last one (len(commands) + 1 poses)."""
    poses = [pose]
    for v, w in commands:
        poses.append(integrate(poses[-1], v, w, dt))
    return poses
