"""ExpertOracle: plan reuse while the agents follow it, replanning when they leave it, the
shortest-path fallback when planning fails, and input checks."""
from __future__ import annotations

import numpy as np
import pytest
from mapf_world.grid import grid_from_text as parse_map

from mapf_world.env import MapfEnv
from mapf_world.grid import LEFT, RIGHT, STAY
from mapf_world.instances import generate_instance
from mapf_world.planners import ExpertOracle


def test_follows_its_plan_to_the_goals_with_one_plan():
    inst = generate_instance(7, size=40, density=0.3, n_agents=8)
    env = MapfEnv(inst.grid, inst.starts, inst.goals)
    env.reset()
    oracle = ExpertOracle(inst.grid, inst.goals)
    done = False
    while not done:
        actions = oracle.actions(env.positions)
        assert np.array_equal(actions, oracle.actions(env.positions))  # asked twice: same answer
        _, _, terminated, truncated, info = env.step(actions)
        assert not info["failed"].any()
        done = terminated or truncated
    assert info["success"]
    assert (oracle.plans, oracle.replans, oracle.fallbacks) == (1, 0, 0)
    assert env.step_count == oracle.plan.shape[0] - 1
    # On the goals: everyone stays.
    np.testing.assert_array_equal(oracle.actions(env.positions), np.zeros(8, dtype=np.int64))


def test_replans_when_the_agents_leave_the_plan():
    inst = generate_instance(8, size=40, density=0.3, n_agents=6)
    env = MapfEnv(inst.grid, inst.starts, inst.goals)
    env.reset()
    oracle = ExpertOracle(inst.grid, inst.goals)
    for _ in range(3):
        env.step(oracle.actions(env.positions))
    first_plan = oracle.plan
    actions = oracle.actions(env.positions)
    movers = np.flatnonzero(actions != STAY)
    assert movers.size >= 2
    # Everyone waiting keeps the agents on the plan (its cells at the current step): reused.
    env.step(np.zeros(6, dtype=np.int64))
    assert np.array_equal(oracle.actions(env.positions), actions) and oracle.plans == 1
    # One mover waiting while the others move puts the cells on no step of the plan: replan.
    actions[movers[0]] = STAY
    env.step(actions)
    assert oracle.plans == 1
    oracle.actions(env.positions)
    assert (oracle.plans, oracle.replans) == (2, 1)
    assert oracle.plan is not first_plan
    np.testing.assert_array_equal(oracle.plan[0], env.positions)  # the new plan starts here
    # ... and is followed to the end without failed moves.
    done = False
    while not done:
        _, _, terminated, truncated, info = env.step(oracle.actions(env.positions))
        assert not info["failed"].any()
        done = terminated or truncated
    assert info["success"] and oracle.replans == 1


def test_fallback_when_no_plan_exists():
    corridor = parse_map(". . .")
    oracle = ExpertOracle(corridor, [[0, 1], [0, 0]])
    actions = oracle.actions([[0, 0], [0, 1]])  # swapping in a corridor: unsolvable
    assert oracle.last_fallback and oracle.fallbacks == 1 and oracle.plan is None
    assert oracle.last_result.status == "unsolvable"
    np.testing.assert_array_equal(actions, [RIGHT, LEFT])  # each agent's shortest-path move
    # It tries again on the next call, and on goals the fallback stays.
    oracle.actions([[0, 1], [0, 0]])
    assert not oracle.last_fallback and oracle.plans == 1


def test_fallback_on_timeout():
    inst = generate_instance(5, size=12, density=0.0, n_agents=40)
    oracle = ExpertOracle(inst.grid, inst.goals, epsilon=1.0, time_limit=0.05)
    actions = oracle.actions(inst.starts)
    assert oracle.last_fallback and oracle.last_result.status == "timeout"
    assert actions.shape == (40,) and actions.dtype == np.int64


def test_bad_input():
    grid = parse_map(". . .\n. # .")
    with pytest.raises(ValueError, match="goals: agent 0 cell \\(1, 1\\) is on an obstacle"):
        ExpertOracle(grid, [[1, 1]])
    with pytest.raises(ValueError, match="epsilon"):
        ExpertOracle(grid, [[0, 0]], epsilon=0.9)
    with pytest.raises(ValueError, match="time_limit"):
        ExpertOracle(grid, [[0, 0]], time_limit=0)
    with pytest.raises(ValueError, match="objective"):
        ExpertOracle(grid, [[0, 0]], objective="fast")
    oracle = ExpertOracle(grid, [[0, 0], [0, 2]])
    with pytest.raises(ValueError, match="positions: agent 0 cell \\(1, 1\\) is on an obstacle"):
        oracle.actions([[1, 1], [0, 1]])
    with pytest.raises(ValueError, match="positions has 1 agents, the oracle 2"):
        oracle.actions([[0, 1]])
