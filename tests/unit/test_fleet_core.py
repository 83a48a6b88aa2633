"""The world node's step protocol (mapf_world.fleet_core), without ROS."""
import math

import numpy as np
import pytest

from mapf_world.fleet_core import (OUTCOME_BLOCKED, OUTCOME_OK, OUTCOME_REJECTED, OUTCOME_TIMEOUT, Deadline,
                                   FleetCore, Phase, State, common_drive_start, describe_moves, xy_to_cell,
                                   cell_to_xy)
from mapf_world.grid import DOWN, LEFT, RIGHT, STAY

GRID = np.array([[0, 0, 0, 0],
                 [0, 1, 0, 0],   # one obstacle at (1, 1)
                 [0, 0, 0, 0]], dtype=np.uint8)


def make(starts, goals, max_steps=10):
    return FleetCore(GRID, np.array(starts), np.array(goals), max_steps)


def test_a_step_moves_robots_and_success_ends_the_run():
    core = make([(0, 0), (2, 3)], [(0, 1), (2, 2)])
    assert core.begin_step() == 0
    assert core.offer_action(0, 0, 0, RIGHT).accepted
    assert not core.all_answered() and core.waiting_for() == [1]
    assert core.offer_action(1, 0, 1, LEFT).accepted
    assert core.all_answered()
    moves = core.close_step()
    assert moves.outcomes.tolist() == [OUTCOME_OK, OUTCOME_OK]
    assert moves.to_cells.tolist() == [[0, 1], [2, 2]]
    assert core.phase == Phase.SETTLING
    core.settle()
    assert core.done and core.state == State.SUCCESS and core.step == 1
    assert core.summary()["success"] and len(core.summary()["positions"]) == 2


def test_the_interlock_turns_a_failed_move_into_stay():
    core = make([(0, 1), (2, 1)], [(0, 3), (2, 3)])
    core.begin_step()
    core.offer_action(0, 0, 0, DOWN)   # into the obstacle at (1, 1)
    core.offer_action(1, 0, 1, RIGHT)
    moves = core.close_step()
    assert moves.requested.tolist() == [DOWN, RIGHT]
    assert moves.actions.tolist() == [STAY, RIGHT]
    assert moves.outcomes.tolist() == [OUTCOME_BLOCKED, OUTCOME_OK]
    assert moves.to_cells.tolist() == [[0, 1], [2, 2]]
    assert core.failed_moves == 1


def test_swap_is_blocked_by_the_rules():
    core = make([(0, 0), (0, 1)], [(0, 1), (0, 0)])
    core.begin_step()
    core.offer_action(0, 0, 0, RIGHT)
    core.offer_action(1, 0, 1, LEFT)
    moves = core.close_step()
    assert moves.outcomes.tolist() == [OUTCOME_BLOCKED, OUTCOME_BLOCKED]
    assert moves.to_cells.tolist() == moves.from_cells.tolist()


def test_silent_robot_times_out_and_stays_others_go_on():
    core = make([(0, 0), (2, 0)], [(0, 3), (2, 3)])
    core.begin_step()
    core.offer_action(0, 0, 0, RIGHT)
    moves = core.close_step()
    assert moves.outcomes.tolist() == [OUTCOME_OK, OUTCOME_TIMEOUT]
    assert moves.actions.tolist() == [RIGHT, STAY]
    assert core.timeouts == 1


def test_action_outside_range_is_rejected_and_the_robot_stays_at_once():
    core = make([(0, 0), (2, 0)], [(0, 3), (2, 3)])
    core.begin_step()
    v = core.offer_action(1, 0, 1, 7)
    assert not v.accepted and v.final and "outside 0..4" in v.reason
    # Its action is fixed: a later valid one does not count.
    assert not core.offer_action(1, 0, 1, RIGHT).accepted
    core.offer_action(0, 0, 0, RIGHT)
    assert core.all_answered()
    moves = core.close_step()
    assert moves.outcomes.tolist() == [OUTCOME_OK, OUTCOME_REJECTED]
    assert moves.to_cells[1].tolist() == [2, 0]
    assert core.rejected == 1


def test_wrong_step_or_robot_id_is_rejected_but_the_robot_may_still_answer():
    core = make([(0, 0), (2, 0)], [(0, 3), (2, 3)])
    core.begin_step()
    v = core.offer_action(0, 5, 0, RIGHT)
    assert not v.accepted and not v.final and "step 5" in v.reason
    v = core.offer_action(0, 0, 1, RIGHT)
    assert not v.accepted and "robot_id 1" in v.reason
    assert core.offer_action(0, 0, 0, RIGHT).accepted
    moves = core.close_step()   # robot 1: only silence -> timeout; robot 0: its valid action
    assert moves.outcomes.tolist() == [OUTCOME_OK, OUTCOME_TIMEOUT]
    assert core.rejected == 2


def test_only_rejected_messages_give_outcome_rejected():
    core = make([(0, 0), (2, 0)], [(0, 3), (2, 3)])
    core.begin_step()
    core.offer_action(1, 3, 1, RIGHT)   # stale/future step only
    core.offer_action(0, 0, 0, STAY)
    moves = core.close_step()
    assert moves.outcomes.tolist() == [OUTCOME_OK, OUTCOME_REJECTED]


def test_actions_between_steps_are_rejected():
    core = make([(0, 0), (2, 0)], [(0, 3), (2, 3)])
    v = core.offer_action(0, 0, 0, RIGHT)  # before begin_step
    assert not v.accepted and "no step collecting" in v.reason
    core.begin_step()
    core.offer_action(0, 0, 0, RIGHT)
    core.offer_action(1, 0, 1, RIGHT)
    core.close_step()
    v = core.offer_action(0, 0, 0, RIGHT)  # late duplicate while settling
    assert not v.accepted


def test_step_limit_ends_the_run():
    core = make([(0, 0), (2, 0)], [(0, 3), (2, 3)], max_steps=2)
    for _ in range(2):
        core.begin_step()
        core.close_step()
        core.settle()
    assert core.done and core.state == State.MAX_STEPS and core.timeouts == 4
    assert "step limit 2" in core.detail


def test_protocol_order_is_enforced():
    core = make([(0, 0)], [(0, 3)])
    with pytest.raises(RuntimeError):
        core.close_step()
    with pytest.raises(RuntimeError):
        core.settle()
    core.begin_step()
    with pytest.raises(RuntimeError):
        core.begin_step()


@pytest.mark.parametrize("bad, match", [
    (dict(starts=[(1, 1)], goals=[(0, 0)]), "obstacle"),
    (dict(starts=[(0, 0), (0, 0)], goals=[(0, 1), (0, 2)]), "share cell"),
    (dict(starts=[(0, 0)], goals=[(0, 1), (0, 2)]), "1 starts but 2 goals"),
    (dict(starts=[(0, 9)], goals=[(0, 1)]), "off the"),
    (dict(starts=[(0, 0)], goals=[(0, 1)], max_steps=0), "max_steps"),
])
def test_bad_instances_are_refused(bad, match):
    args = dict(max_steps=5) | bad
    with pytest.raises(ValueError, match=match):
        FleetCore(GRID, np.array(args["starts"]), np.array(args["goals"]), args["max_steps"])


def test_robot_index_out_of_range_is_an_error():
    core = make([(0, 0)], [(0, 3)])
    core.begin_step()
    with pytest.raises(ValueError, match="robot index 3"):
        core.offer_action(3, 0, 3, STAY)


def test_frame_and_drive_start():
    assert cell_to_xy((2, 3), 0.5) == (1.5, -1.0)
    assert xy_to_cell(1.45, -1.1, 0.5) == (2, 3)
    # Robot 0 faces right and moves right (no turn); robot 1 faces right and moves up (quarter turn);
    # robot 2 stays (ignored even though it faces the wrong way).
    start = common_drive_start([0.0, 0.0, math.pi], [(1, 1), (3, 3), (0, 0)], [(1, 2), (2, 3), (0, 0)], 1.57)
    assert start == pytest.approx((math.pi / 2) / 1.57)
    assert common_drive_start([0.0], [(0, 0)], [(0, 0)], 1.57) == 0.0


def test_describe_moves_names_outcomes():
    core = make([(0, 1), (2, 1)], [(0, 3), (2, 3)])
    core.begin_step()
    core.offer_action(0, 0, 0, DOWN)
    text = describe_moves(core.close_step())
    assert "r0:stay(blocked down)" in text and "r1:stay(timeout)" in text


def test_robot_id_from_namespace_and_parameter():
    from mapf_world.fleet_core import resolve_robot_id
    assert resolve_robot_id(-1, "/robot_2") == 2
    assert resolve_robot_id(-1, "/lab/robot_11") == 11
    assert resolve_robot_id(4, "/") == 4
    assert resolve_robot_id(2, "/robot_2") == 2
    with pytest.raises(ValueError, match="does not end in 'robot_<i>'"):
        resolve_robot_id(-1, "/")
    with pytest.raises(ValueError, match="disagrees"):
        resolve_robot_id(1, "/robot_2")
    with pytest.raises(ValueError, match=">= 0"):
        resolve_robot_id(-3, "/robot_2")


@pytest.mark.parametrize("mode,expected", [("requested", [DOWN, RIGHT]), ("executed", [0, RIGHT])])
def test_last_actions_follow_mapf_env_in_either_mode(mode, expected):
    from mapf_world.env import MapfEnv
    starts, goals = np.array([(0, 1), (2, 1)]), np.array([(0, 3), (2, 3)])
    core = FleetCore(GRID, starts, goals, 64, last_action=mode)
    env = MapfEnv(GRID, starts, goals, last_action=mode)
    env.reset()
    core.begin_step()
    core.offer_action(0, 0, 0, DOWN)   # fails: obstacle
    core.offer_action(1, 0, 1, RIGHT)
    core.close_step()
    core.settle()
    env.step([DOWN, RIGHT])
    assert core.last_actions.tolist() == env.last_actions.tolist() == expected
    assert core.positions.tolist() == env.positions.tolist()
    with pytest.raises(ValueError, match="last_action"):
        FleetCore(GRID, starts, goals, 64, last_action="planned")


def test_deadline_holds_on_ticks_and_gives_grace_after_a_stall_of_its_process():
    d = Deadline(stall_s=0.1, grace_s=0.1)
    assert not d.expired(5.0)                      # never set: no limit
    d.set(10.0, 0.4)
    ticks = [10.0 + 0.01 * k for k in range(1, 41)]
    assert not any(d.expired(t) for t in ticks[:-1])
    assert d.expired(10.41)                        # regular ticks: due at the first tick past the limit
    d.set(20.0, 0.4)
    assert not d.expired(20.01)
    assert not d.expired(21.0)                     # ticks stopped for 1 s across the limit: grace
    assert not d.expired(21.05)
    assert d.expired(21.1)                         # grace over
    d.set(30.0, 0.4)
    for t in (30.15, 30.3, 30.45):                 # slow at every tick: one grace only, then due
        assert not d.expired(t)
    assert d.expired(30.6)
