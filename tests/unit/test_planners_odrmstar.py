"""ODrM*: optimality (epsilon = 1) against the exhaustive joint search, the grid rules (waiting,
following, rotations), unsolvable and timeout outcomes, epsilon = 10 plans replayed in MapfEnv,
and input checks."""
from __future__ import annotations

import numpy as np
import pytest
from mapf_world.grid import grid_from_text as parse_map
from test_planners_oracle import optimal_sum_of_costs, plan_sum_of_costs, tiny_cases

from mapf_world.evaluate import run_case
from mapf_world.instances import generate_instance
from mapf_world.planners import plan_odrmstar
from mapf_world.planners.solvers import make_odrmstar
from mapf_world.validate import validate_solution

OBJECTIVES = ("sum_of_costs", "free_goal_wait", "goal_keeping")


def free_goal_wait_cost(positions, goals) -> int:
    """Cost of a plan when waits on one's own goal are free: every other agent-step costs 1."""
    pos, goals = np.asarray(positions), np.asarray(goals)
    stay_on_goal = np.all(pos[1:] == pos[:-1], axis=2) & np.all(pos[1:] == goals[None], axis=2)
    return int((~stay_on_goal).sum())


def goal_leaves(positions, goals) -> int:
    """Moves off one's own goal in a plan (goal_keeping charges 1 more for each)."""
    pos, goals = np.asarray(positions), np.asarray(goals)
    return int((np.all(pos[:-1] == goals[None], axis=2) & np.any(pos[1:] != pos[:-1], axis=2)).sum())


def objective_cost(positions, goals, objective: str) -> int:
    if objective == "sum_of_costs":
        return plan_sum_of_costs(positions, goals)
    extra = goal_leaves(positions, goals) if objective == "goal_keeping" else 0
    return free_goal_wait_cost(positions, goals) + extra


def check_optimal(grid, starts, goals, objective: str):
    expected = optimal_sum_of_costs(grid, starts, goals, free_goal_wait=objective != "sum_of_costs",
                                    leave_cost=2 if objective == "goal_keeping" else 1)
    res = plan_odrmstar(grid, starts, goals, epsilon=1.0, time_limit=5.0, objective=objective)
    if expected is None:
        assert res.status == "unsolvable" and res.positions is None
        return res
    assert res.status == "solved", res.message
    validate_solution(grid, starts, goals, res.positions, success=True)
    assert objective_cost(res.positions, goals, objective) == expected
    assert res.sum_of_costs == plan_sum_of_costs(res.positions, goals)
    assert res.makespan == res.positions.shape[0] - 1
    return res


# --- the grid rules, on cases that need them -------------------------------------------------
@pytest.mark.parametrize("objective", OBJECTIVES)
def test_following_in_a_corridor(objective):
    grid = parse_map(". . . .")
    res = check_optimal(grid, [[0, 1], [0, 0]], [[0, 3], [0, 2]], objective)
    # Both agents move at once, the second into the cell the first leaves: 2 steps, cost 4.
    assert res.makespan == 2 and res.sum_of_costs == 4


@pytest.mark.parametrize("objective", OBJECTIVES)
def test_rotation_of_four_agents(objective):
    # A full 2x2 block: the only possible move is all four agents rotating at once.
    grid = parse_map(". .\n. .")
    starts = [[0, 0], [0, 1], [1, 1], [1, 0]]
    goals = [[0, 1], [1, 1], [1, 0], [0, 0]]
    res = check_optimal(grid, starts, goals, objective)
    assert res.makespan == 1 and res.sum_of_costs == 4


@pytest.mark.parametrize("objective, cost", [("sum_of_costs", 8), ("free_goal_wait", 6), ("goal_keeping", 7)])
def test_making_way_from_the_goal(objective, cost):
    # test_planners_oracle.test_oracle_charges_the_wait_before_leaving_the_goal: agent 0 must
    # leave its goal for a pocket to let agent 1 through.
    grid = parse_map(". . . . .\n# # # . #")
    starts, goals = [[0, 3], [0, 0]], [[0, 3], [0, 4]]
    check_optimal(grid, starts, goals, objective)
    res = plan_odrmstar(grid, starts, goals, epsilon=1.0, objective=objective)
    assert objective_cost(res.positions, goals, objective) == cost


def test_goal_keeping_goes_round_an_agent_on_its_goal():
    # Agent 1 rests on its goal between agent 0 and agent 0's goal. Going round (4 moves) and agent 1
    # stepping aside and back (2 + 2 moves) cost the same without the surcharge; with it, agent 1 stays.
    grid = parse_map(". . .\n. . .")
    starts, goals = [[1, 0], [1, 1]], [[1, 2], [1, 1]]
    assert optimal_sum_of_costs(grid, starts, goals, free_goal_wait=True) == 4
    res = plan_odrmstar(grid, starts, goals, epsilon=1.0, time_limit=5.0, objective="goal_keeping")
    assert res.status == "solved"
    validate_solution(grid, starts, goals, res.positions, success=True)
    assert np.all(res.positions[:, 1] == [1, 1]) and res.sum_of_costs == 4
    # With the inflated heuristic (epsilon 10) the search takes agent 0's shorter distance first and agent 1
    # makes way: the surcharge decides ties of cost, not of heuristic (Args.expert_objective says so).
    res = plan_odrmstar(grid, starts, goals, epsilon=10.0, time_limit=5.0, objective="goal_keeping")
    assert res.status == "solved" and goal_leaves(res.positions, goals) == 1


def test_goal_keeping_still_gives_way_where_there_is_no_way_round():
    # A corridor with one side pocket below agent 1's goal: it must step into the pocket and back.
    grid = parse_map(". . .\n# . #")
    starts, goals = [[0, 0], [0, 1]], [[0, 2], [0, 1]]
    res = plan_odrmstar(grid, starts, goals, epsilon=10.0, time_limit=5.0, objective="goal_keeping")
    assert res.status == "solved"
    validate_solution(grid, starts, goals, res.positions, success=True)
    assert goal_leaves(res.positions, goals) == 1


@pytest.mark.parametrize("objective", OBJECTIVES)
def test_waiting_at_a_junction(objective):
    # Agent 1 must cross the column agent 0 walks down: one of them waits a step.
    grid = parse_map("# . #\n. . .\n# . #")
    res = check_optimal(grid, [[0, 1], [1, 0]], [[2, 1], [1, 2]], objective)
    assert res.sum_of_costs == 5


@pytest.mark.parametrize("objective", OBJECTIVES)
def test_unsolvable_cases_are_proven(objective):
    corridor = parse_map(". . .")
    res = check_optimal(corridor, [[0, 0], [0, 1]], [[0, 1], [0, 0]], objective)
    assert res.status == "unsolvable"
    # Three agents in a dead end whose order must reverse, with room to move but never to pass.
    pocket = parse_map(". . . .\n# # # .")
    res = check_optimal(pocket, [[0, 0], [0, 1], [1, 3]], [[0, 1], [0, 0], [0, 3]], objective)
    assert res.status == "unsolvable"


@pytest.mark.parametrize("objective", OBJECTIVES)
def test_random_tiny_instances_are_optimal(objective):
    for grid, starts, goals in tiny_cases(seed=1, count=40):
        check_optimal(grid, starts, goals, objective)


def test_start_on_goals_is_a_zero_step_plan():
    grid = parse_map(". .\n. .")
    res = plan_odrmstar(grid, [[0, 0], [1, 1]], [[0, 0], [1, 1]])
    assert res.status == "solved" and res.makespan == 0 and res.sum_of_costs == 0
    assert res.positions.shape == (1, 2, 2)


# --- epsilon = 10 on generated 40x40 cases, replayed through MapfEnv ---------------------------
@pytest.mark.parametrize("seed, n_agents", [(0, 4), (1, 8), (2, 16), (3, 32), (4, 32)])
def test_inflated_plans_execute_without_failed_moves(seed, n_agents):
    inst = generate_instance(seed, size=40, density=0.3, n_agents=n_agents)
    solver = make_odrmstar(epsilon=10.0, time_limit=10.0)
    result = run_case(solver, inst, max_steps=256)
    assert result.success and result.failed_moves == 0
    plan = solver.last_result
    assert result.steps == plan.makespan
    assert result.sum_of_costs == plan.sum_of_costs
    np.testing.assert_array_equal(result.positions, plan.positions)


def test_inflated_cost_within_epsilon_of_optimal():
    for grid, starts, goals in tiny_cases(seed=2, count=15):
        best = optimal_sum_of_costs(grid, starts, goals)
        if best is None:
            continue
        res = plan_odrmstar(grid, starts, goals, epsilon=3.0, objective="sum_of_costs")
        assert best <= res.sum_of_costs <= 3 * best


# --- outcomes ----------------------------------------------------------------------------------
def test_timeout_is_reported():
    # 64 agents on a 12x12 open map with epsilon = 1: far more than 50 ms of search.
    inst = generate_instance(5, size=12, density=0.0, n_agents=40)
    res = plan_odrmstar(inst.grid, inst.starts, inst.goals, epsilon=1.0, time_limit=0.05, objective="sum_of_costs")
    assert res.status == "timeout" and res.positions is None and res.sum_of_costs is None
    assert res.seconds < 1.0


def test_cancel_flag_stops_the_search():
    inst = generate_instance(5, size=12, density=0.0, n_agents=40)
    cancel = np.ones(1, dtype=np.int32)
    res = plan_odrmstar(inst.grid, inst.starts, inst.goals, epsilon=1.0, time_limit=30.0, cancel=cancel,
                        objective="sum_of_costs")
    assert res.status == "timeout" and res.seconds < 1.0


# --- bad input ---------------------------------------------------------------------------------
GRID = parse_map(". . .\n. # .\n. . .")


@pytest.mark.parametrize("kwargs, match", [
    ({"epsilon": 0.5}, "epsilon must be a finite number >= 1"),
    ({"epsilon": float("nan")}, "epsilon"),
    ({"epsilon": True}, "epsilon must be a number"),
    ({"time_limit": 0.0}, "time_limit must be a finite number of seconds > 0"),
    ({"time_limit": -1}, "time_limit"),
    ({"time_limit": float("inf")}, "time_limit"),
    ({"time_limit": "5"}, "time_limit must be a number"),
    ({"objective": "makespan"}, "objective must be one of"),
])
def test_bad_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        plan_odrmstar(GRID, [[0, 0]], [[2, 2]], **kwargs)


@pytest.mark.parametrize("starts, goals, match", [
    ([[1, 1]], [[0, 0]], "starts: agent 0 cell \\(1, 1\\) is on an obstacle"),
    ([[0, 0]], [[3, 0]], "goals: agent 0 cell \\(3, 0\\) is off the 3x3 map"),
    ([[0, 0], [0, 0]], [[2, 2], [2, 1]], "starts: agents \\[0, 1\\] share cell"),
    ([[0, 0], [0, 1]], [[2, 2]], "2 starts but 1 goals"),
])
def test_bad_cells(starts, goals, match):
    with pytest.raises(ValueError, match=match):
        plan_odrmstar(GRID, starts, goals)


def test_unreachable_goal_and_too_many_agents():
    walled = parse_map(". # .")
    with pytest.raises(ValueError, match="agent 0: goal \\[0, 2\\] is unreachable"):
        plan_odrmstar(walled, [[0, 0]], [[0, 2]])
    grid = np.zeros((10, 14), np.uint8)
    cells = np.argwhere(grid == 0)
    with pytest.raises(ValueError, match="at most 64 agents, got 65"):
        plan_odrmstar(grid, cells[:65], cells[65:130])
    with pytest.raises(ValueError, match="grid must"):
        plan_odrmstar(np.full((2, 2), 2), [[0, 0]], [[1, 1]])
