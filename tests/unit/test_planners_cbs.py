"""CBS: optimal sums of costs against the exhaustive joint search, the grid rules, timeouts, plans
replayed in MapfEnv, and input checks."""
from __future__ import annotations

import numpy as np
import pytest
from mapf_world.grid import grid_from_text as parse_map
from test_planners_oracle import optimal_sum_of_costs, plan_sum_of_costs, tiny_cases

from mapf_world.evaluate import run_case
from mapf_world.instances import generate_instance
from mapf_world.planners import plan_cbs
from mapf_world.planners.solvers import make_cbs
from mapf_world.validate import validate_solution


def check_optimal(grid, starts, goals):
    expected = optimal_sum_of_costs(grid, starts, goals)
    assert expected is not None, "CBS tests use solvable cases (CBS cannot prove unsolvability in general)"
    res = plan_cbs(grid, starts, goals, time_limit=5.0)
    assert res.status == "solved", res.message
    validate_solution(grid, starts, goals, res.positions, success=True)
    assert res.sum_of_costs == plan_sum_of_costs(res.positions, goals) == expected
    assert res.makespan == res.positions.shape[0] - 1
    return res


def test_following_rotation_waiting_and_making_way():
    check_optimal(parse_map(". . . ."), [[0, 1], [0, 0]], [[0, 3], [0, 2]])  # following: cost 4
    block = parse_map(". .\n. .")
    res = check_optimal(block, [[0, 0], [0, 1], [1, 1], [1, 0]], [[0, 1], [1, 1], [1, 0], [0, 0]])
    assert res.makespan == 1 and res.sum_of_costs == 4  # a rotation of four
    check_optimal(parse_map("# . #\n. . .\n# . #"), [[0, 1], [1, 0]], [[2, 1], [1, 2]])  # a wait: 5
    # An agent resting on its goal makes way and pays for its waiting there too: 8.
    res = check_optimal(parse_map(". . . . .\n# # # . #"), [[0, 3], [0, 0]], [[0, 3], [0, 4]])
    assert res.sum_of_costs == 8


def test_random_tiny_instances_are_optimal():
    checked = 0
    for grid, starts, goals in tiny_cases(seed=1, count=40):
        if optimal_sum_of_costs(grid, starts, goals) is None:
            continue
        check_optimal(grid, starts, goals)
        checked += 1
    assert checked >= 30


@pytest.mark.parametrize("seed, n_agents", [(0, 4), (1, 8), (2, 16)])
def test_plans_execute_without_failed_moves(seed, n_agents):
    inst = generate_instance(seed, size=40, density=0.3, n_agents=n_agents)
    solver = make_cbs(time_limit=10.0)
    result = run_case(solver, inst, max_steps=256)
    assert result.success and result.failed_moves == 0
    assert result.sum_of_costs == solver.last_result.sum_of_costs


def test_timeout_on_a_hard_swap():
    # Three agents that must reorder through a narrow passage: CBS branches on symmetric conflicts
    # for a very long time (the joint optimum, 32, is found by ODrM* in milliseconds).
    grid = np.array([[0, 0, 1, 1, 0], [0, 0, 0, 1, 0], [1, 0, 0, 1, 0], [1, 1, 0, 0, 0]], np.uint8)
    starts, goals = [[2, 4], [2, 1], [0, 4]], [[3, 2], [1, 4], [3, 3]]
    res = plan_cbs(grid, starts, goals, time_limit=0.2)
    assert res.status == "timeout" and res.positions is None and res.seconds < 1.0


def test_unsolvable_case_ends_in_timeout():
    # Two agents swapping in a corridor: CBS keeps branching (it cannot prove that no plan exists
    # here), so it must stop at the time limit and say so.
    res = plan_cbs(parse_map(". . ."), [[0, 0], [0, 1]], [[0, 1], [0, 0]], time_limit=0.2)
    assert res.status == "timeout" and res.positions is None


@pytest.mark.parametrize("kwargs, match", [
    ({"time_limit": 0}, "time_limit must be a finite number of seconds > 0"),
    ({"time_limit": None}, "time_limit must be a number"),
])
def test_bad_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        plan_cbs(parse_map(". ."), [[0, 0]], [[0, 1]], **kwargs)


def test_bad_cells():
    with pytest.raises(ValueError, match="goals: agent 0 cell \\(0, 1\\) is on an obstacle"):
        plan_cbs(parse_map(". #"), [[0, 0]], [[0, 1]])
