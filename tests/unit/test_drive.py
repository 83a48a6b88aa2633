"""Differential-drive cell kinematics (mapf_policy.drive): limits, exact landing, frame convention."""
import math

import pytest

from mapf_policy.drive import (DriveLimits, Pose2D, cell_to_xy, integrate, plan_cell_move,
                               quaternion_from_yaw, rollout, turn_time, wrap_angle, xy_to_cell,
                               yaw_from_quaternion)

LIMITS = DriveLimits(0.2, 1.57)
DT = 0.05
CELL = 0.3
MOVES = {1: (-1, 0), 2: (1, 0), 3: (0, -1), 4: (0, 1)}  # up, down, left, right as (drow, dcol)


def test_frame_convention_up_is_plus_y_right_is_plus_x():
    assert cell_to_xy((0, 0), CELL) == (0.0, 0.0)
    x, y = cell_to_xy((2, 3), CELL)
    assert (x, y) == pytest.approx((0.9, -0.6))
    assert xy_to_cell(x + 0.1, y - 0.1, CELL) == (2, 3)
    up = cell_to_xy((1, 3), CELL)
    assert up[1] > y and up[0] == pytest.approx(x)


@pytest.mark.parametrize("yaw0", [0.0, math.pi / 2, math.pi, -math.pi / 2, 0.3, -2.9])
@pytest.mark.parametrize("action", [1, 2, 3, 4])
def test_move_lands_on_target_cell_within_limits(yaw0, action):
    start = (4, 4)
    target = (start[0] + MOVES[action][0], start[1] + MOVES[action][1])
    pose = Pose2D(*cell_to_xy(start, CELL), yaw0)
    commands = plan_cell_move(pose, cell_to_xy(target, CELL), LIMITS, DT)
    assert commands, "a real move needs commands"
    for v, w in commands:
        assert abs(v) <= LIMITS.max_linear + 1e-12
        assert abs(w) <= LIMITS.max_angular + 1e-12
        assert v == 0.0 or w == 0.0, "turn in place, then drive straight: never both"
        assert v >= 0.0, "the robot faces the target and drives forwards"
    final = rollout(pose, commands, DT)[-1]
    tx, ty = cell_to_xy(target, CELL)
    assert math.hypot(final.x - tx, final.y - ty) < 1e-9
    heading = math.atan2(ty - pose.y, tx - pose.x)
    assert abs(wrap_angle(final.yaw - heading)) < 1e-9


def test_durations_are_the_physical_minimum_rounded_up_to_periods():
    pose = Pose2D(0.0, 0.0, 0.0)
    # Facing the target: no turn, 0.3 m at 0.2 m/s = 1.5 s = 30 periods.
    commands = plan_cell_move(pose, (0.3, 0.0), LIMITS, DT)
    assert len(commands) == 30 and all(c == (pytest.approx(0.2), 0.0) for c in commands)
    # Target behind: a half turn at 1.57 rad/s takes ceil(pi / 1.57 / 0.05) = 41 periods.
    commands = plan_cell_move(pose, (-0.3, 0.0), LIMITS, DT)
    turns = [c for c in commands if c[1] != 0.0]
    assert len(turns) == math.ceil(math.pi / 1.57 / DT)
    assert turn_time(pose, (-0.3, 0.0), LIMITS, DT) == pytest.approx(len(turns) * DT)


def test_stay_gives_no_motion():
    pose = Pose2D(*cell_to_xy((2, 2), CELL), 1.0)
    assert plan_cell_move(pose, cell_to_xy((2, 2), CELL), LIMITS, DT) == []
    assert turn_time(pose, cell_to_xy((2, 2), CELL), LIMITS, DT) == 0.0


def test_drive_start_makes_the_drive_wait_for_the_common_start():
    pose = Pose2D(0.0, 0.0, 0.0)
    commands = plan_cell_move(pose, (0.3, 0.0), LIMITS, DT, drive_start_s=1.0)
    first_drive = next(k for k, (v, _) in enumerate(commands) if v > 0)
    assert first_drive == 20  # 1.0 s / 0.05 s
    assert all(c == (0.0, 0.0) for c in commands[:20])
    # A turn longer than drive_start_s delays the drive instead of being cut short.
    commands = plan_cell_move(pose, (-0.3, 0.0), LIMITS, DT, drive_start_s=0.5)
    first_drive = next(k for k, (v, _) in enumerate(commands) if v > 0)
    assert first_drive == math.ceil(math.pi / 1.57 / DT)


def test_integrate_arc_matches_small_steps():
    pose = Pose2D(0.1, -0.2, 0.4)
    exact = integrate(pose, 0.2, 0.8, 1.0)
    approx = pose
    for _ in range(10000):
        approx = integrate(approx, 0.2, 0.0, 1e-4)
        approx = Pose2D(approx.x, approx.y, approx.yaw + 0.8e-4)
    assert exact.x == pytest.approx(approx.x, abs=1e-4)
    assert exact.y == pytest.approx(approx.y, abs=1e-4)


def test_quaternion_round_trip():
    for yaw in (-3.0, -1.0, 0.0, 0.5, 3.0):
        _, _, qz, qw = quaternion_from_yaw(yaw)
        assert wrap_angle(yaw_from_quaternion(qz, qw) - yaw) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("bad", [dict(dt=0.0), dict(dt=float("nan")), dict(drive_start_s=-1.0)])
def test_bad_arguments_are_refused(bad):
    args = dict(dt=DT, drive_start_s=0.0) | bad
    with pytest.raises(ValueError):
        plan_cell_move(Pose2D(0, 0, 0), (0.3, 0.0), LIMITS, args["dt"], args["drive_start_s"])


def test_bad_limits_are_refused():
    with pytest.raises(ValueError, match="max_linear"):
        DriveLimits(0.0, 1.57)
    with pytest.raises(ValueError, match="max_angular"):
        DriveLimits(0.2, -1.0)
