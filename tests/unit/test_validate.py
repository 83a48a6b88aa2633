"""validate_solution: accepts what the rules allow, rejects each kind of bad run with a precise message."""
from __future__ import annotations

import numpy as np
import pytest

from mapf_world.env import MapfEnv
from mapf_world.grid import grid_from_text
from mapf_world.instances import generate_instance
from mapf_world.validate import SolutionError, validate_solution

GRID = grid_from_text("....\n.#..\n....")
STARTS = [[0, 0], [0, 1]]
GOALS = [[0, 1], [0, 2]]


def check(positions, success=None, starts=STARTS, goals=GOALS, grid=GRID):
    validate_solution(grid, starts, goals, np.array(positions), success=success)


def test_valid_following_run_with_success():
    check([[[0, 0], [0, 1]], [[0, 1], [0, 2]]], success=True)
    check([[[0, 0], [0, 1]], [[0, 0], [0, 1]]], success=False)
    check([[[0, 0], [0, 1]]])  # no step at all


def test_valid_rotation_of_four():
    grid = np.zeros((2, 2), np.uint8)
    ring = [[0, 0], [0, 1], [1, 1], [1, 0]]
    validate_solution(grid, ring, ring[1:] + ring[:1], np.array([ring, ring[1:] + ring[:1]]), success=True)


def test_solution_error_is_a_value_error():
    assert issubclass(SolutionError, ValueError)


@pytest.mark.parametrize(
    "positions, success, pattern",
    [
        ([[0, 0], [0, 1]], None, r"shape \(T\+1, 2, 2\), got \(2, 2\)"),
        ([[[0, 0]]], None, r"shape \(T\+1, 2, 2\), got \(1, 1, 2\)"),
        ([[[0.0, 0.0], [0.0, 1.0]]], None, "integer cells"),
        ([[[0, 1], [0, 0]]], None, r"step 0: agent 0 is at \(0, 1\), its start is \(0, 0\)"),
        ([[[0, 0], [0, 1]], [[0, 0], [0, 3]]], None, r"step 1: agent 1 jumps from \(0, 1\) to \(0, 3\)"),
        ([[[0, 0], [0, 1]], [[1, 1], [0, 1]]], None, r"step 1: agent 0 at \(1, 1\) is on an obstacle"),
        ([[[0, 0], [0, 1]], [[1, 0], [0, 1]], [[1, 0], [0, 2]], [[2, 1], [0, 2]]], None,
         r"step 3: agent 0 jumps from \(1, 0\) to \(2, 1\)"),  # diagonal
        ([[[0, 0], [0, 1]], [[-1, 0], [0, 1]]], None, r"step 1: agent 0 at \(-1, 0\) is off the 3x4 map"),
        ([[[0, 0], [0, 1]], [[0, 0], [0, 4]]], None, r"step 1: agent 1 at \(0, 4\) is off the 3x4 map"),
        ([[[0, 0], [0, 1]], [[1, 0], [0, 1]], [[1, 0], [0, 0]], [[0, 0], [1, 0]]], None,
         r"step 3: agents 0 and 1 swap cells \(1, 0\) <-> \(0, 0\)"),
        ([[[0, 0], [0, 1]], [[0, 1], [0, 0]]], None, r"step 1: agents 0 and 1 swap cells \(0, 0\) <-> \(0, 1\)"),
        ([[[0, 0], [0, 1]], [[0, 0], [0, 2]], [[0, 0], [1, 2]], [[0, 1], [1, 2]]], True,
         r"success claimed but at the last step 3 agent 1 is at \(1, 2\), its goal is \(0, 2\)"),
        ([[[0, 0], [0, 1]], [[0, 1], [0, 2]]], False,
         "failure claimed but all agents are on their goals at the last step 1"),
    ],
)
def test_rejections(positions, success, pattern):
    with pytest.raises(SolutionError, match=pattern):
        check(positions, success=success)


def test_vertex_conflict_names_step_agents_and_cell():
    starts = [[0, 0], [0, 2], [2, 2]]
    goals = [[2, 0], [2, 3], [1, 3]]
    run = [starts, [[0, 1], [0, 1], [2, 2]]]
    with pytest.raises(SolutionError, match=r"step 1: agents \[0, 1\] share cell \(0, 1\) \(vertex conflict\)"):
        validate_solution(GRID, starts, goals, np.array(run))


def test_the_earliest_conflict_is_reported():
    starts = [[0, 0], [0, 2], [2, 0], [2, 2]]
    goals = [[2, 3], [2, 2], [1, 0], [0, 3]]
    run = [starts, [[0, 0], [0, 2], [2, 1], [2, 1]], [[0, 1], [0, 1], [2, 1], [2, 1]]]
    with pytest.raises(SolutionError, match="step 1: agents \\[2, 3\\] share cell \\(2, 1\\)"):
        validate_solution(GRID, starts, goals, np.array(run))


def test_bad_starts_or_goals_are_reported():
    with pytest.raises(ValueError, match="goals: agent 1 cell \\(1, 1\\) is on an obstacle"):
        validate_solution(GRID, STARTS, [[0, 1], [1, 1]], np.array([STARTS]))


def test_random_env_runs_always_validate():
    # The env enforces the rules, so whatever the actions, its trajectories must pass.
    rng = np.random.default_rng(2)
    for k in range(10):
        inst = generate_instance(rng, size=10, density=0.2, n_agents=12)
        env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=60)
        env.reset()
        run = [env.positions]
        done = False
        while not done:
            _, _, term, trunc, info = env.step(rng.integers(0, 5, 12))
            run.append(env.positions)
            done = term or trunc
        validate_solution(inst.grid, inst.starts, inst.goals, np.array(run), success=info["success"])
        assert len(run) == 61 or info["success"]
