"""Prioritized planning in index order (mapf_world.planners.prioritized) and its oracle with the ODrM* fallback."""
import numpy as np
import pytest

from mapf_world.instances import generate_instance
from mapf_world.planners.prioritized import PrioritizedOracle, first_move_costs, plan_prioritized
from mapf_world.rules import resolve_moves
from mapf_world.planners.result import plan_actions


def _plays_out(grid, starts, goals, positions):
    """The plan's actions, stepped through the DHC rules, give the plan's cells and end on the goals."""
    pos = np.asarray(starts)
    for t, acts in enumerate(plan_actions(positions)):
        pos, failed = resolve_moves(grid, pos, acts)
        assert not failed.any(), f"step {t}: moves refused {np.flatnonzero(failed).tolist()}"
        assert np.array_equal(pos, positions[t + 1])
    assert np.array_equal(pos, goals)


def _corridor_with_a_bay():
    """Row 1 is a corridor, (0, 3) a bay above it; agent 0 goes right, agent 1 left (grid, starts, goals)."""
    grid = np.array([[1, 1, 1, 0, 1],
                     [0, 0, 0, 0, 0],
                     [1, 1, 1, 1, 1]], dtype=np.uint8)
    return grid, np.array([[1, 0], [1, 4]]), np.array([[1, 4], [1, 0]])


def test_head_on_in_a_corridor_with_a_bay_the_later_agent_gives_way():
    # Row 1 is a corridor, (0, 3) a bay above it. Agent 0 goes right, agent 1 left: one must wait in the bay.
    grid, starts, goals = _corridor_with_a_bay()
    res = plan_prioritized(grid, starts, goals)
    assert res.solved and res.failed_agent == -1
    path0 = res.positions[:, 0]
    assert len({tuple(c) for c in path0}) == 5 and not (path0 == [0, 3]).all(1).any()  # agent 0 straight through
    assert (res.positions[:, 1] == [0, 3]).all(1).any()  # agent 1 steps into the bay
    _plays_out(grid, starts, goals, res.positions)
    assert res.positions.shape[0] - 1 == 7  # agent 1: bay at t=2, follows agent 0 out at t=4, home at t=7
    # Swapped indices: the agent coming from the right has priority; the other cannot reach the bay before it
    # passes, so in this order there is no plan (prioritized planning is incomplete).
    res2 = plan_prioritized(grid, goals, starts)
    assert not res2.solved and res2.failed_agent == 1


def test_an_earlier_agent_parked_in_the_only_way_makes_the_later_fail():
    grid = np.zeros((2, 4), dtype=np.uint8)
    grid[1, [0, 1, 3]] = 1  # a bay at (1, 2) under a 1x4 corridor
    starts, goals = np.array([[0, 1], [0, 0]]), np.array([[0, 1], [0, 3]])  # agent 0 already on its goal
    res = plan_prioritized(grid, starts, goals)
    assert not res.solved and res.failed_agent == 1
    # In the other order the agent on its goal steps into the bay and back, so both get there.
    res2 = plan_prioritized(grid, starts[::-1], goals[::-1])
    assert res2.solved
    _plays_out(grid, starts[::-1], goals[::-1], res2.positions)


def test_no_swap_and_following_is_allowed():
    grid = np.zeros((1, 3), dtype=np.uint8)
    # Agent 0 moves right and agent 1 follows it: following into a cell being left is legal.
    res = plan_prioritized(grid, np.array([[0, 1], [0, 0]]), np.array([[0, 2], [0, 1]]))
    assert res.solved and res.positions.shape[0] == 2
    # Two agents that must pass each other on a 1x3 line cannot: no swaps, no room.
    assert not plan_prioritized(grid, np.array([[0, 0], [0, 2]]), np.array([[0, 2], [0, 0]])).solved


def test_generated_plans_are_legal_and_the_first_agent_takes_its_shortest_path():
    from mapf_world.heuristics import distance_maps

    solved = 0
    for seed in range(8):
        inst = generate_instance(np.random.default_rng(seed), size=20, density=0.3, n_agents=8)
        res = plan_prioritized(inst.grid, inst.starts, inst.goals)
        if not res.solved:  # prioritized planning is incomplete
            assert 0 < res.failed_agent < 8
            continue
        solved += 1
        _plays_out(inst.grid, inst.starts, inst.goals, res.positions)
        d0 = distance_maps(inst.grid, inst.goals[:1])[0][tuple(inst.starts[0])]
        off_goal = np.flatnonzero(~(res.positions[:, 0] == inst.goals[0]).all(1))
        assert (off_goal.max() + 1 if off_goal.size else 0) == d0  # agent 0 ignores the rest
    assert solved >= 6


def test_oracle_follows_its_plan_and_replans_off_it():
    inst = generate_instance(np.random.default_rng(3), size=12, density=0.2, n_agents=3)
    oracle = PrioritizedOracle(inst.grid, inst.goals)
    first = oracle.actions(inst.starts)
    assert first is not None and oracle.plans == 1
    nxt, _ = resolve_moves(inst.grid, inst.starts, first)
    oracle.actions(nxt)
    assert oracle.plans == 1  # on the plan: no new search
    oracle.actions(inst.starts)  # back at the start: neither the plan's current nor its next cells
    assert oracle.plans == 2


def test_expert_prioritized_falls_back_to_odrmstar_where_it_finds_no_plan():
    from mapf_policy.train.expert import make_oracle
    from mapf_world.heuristics import distance_maps

    grid = np.zeros((2, 4), dtype=np.uint8)
    grid[1, [0, 1, 3]] = 1  # a bay at (1, 2) under a 1x4 corridor
    starts, goals = np.array([[0, 1], [0, 0]]), np.array([[0, 1], [0, 3]])
    oracle = make_oracle("prioritized", grid, goals, distance_maps(grid, goals), 10.0, 2.0)
    a = oracle.actions(starts)
    assert oracle.odrm_states == 1 and oracle.pp_states == 0 and a.shape == (2,)
    with pytest.raises(ValueError, match="index order"):
        make_oracle("prioritized", grid, goals, distance_maps(grid, goals), 10.0, 2.0, order="position")


def test_first_move_costs_in_a_corridor_with_a_bay():
    grid, starts, goals = _corridor_with_a_bay()
    costs = first_move_costs(grid, starts, goals)
    # Agent 0 (first) ignores agent 1: right is its 4-step path, stay costs one more, the rest are walls.
    assert costs[0].tolist() == [5, -1, -1, -1, 4]
    # Agent 1 plans around agent 0 going right and must wait in the bay (0, 3) while it passes. Going left first
    # and waiting once first tie: both reach the bay before agent 0 takes (1, 3) at t=3 (following it in is
    # legal), leave it behind agent 0 at t=4 and are home at t=7. The label is one of the two.
    assert costs[1].tolist() == [7, -1, -1, 7, -1]
    assert costs.min(axis=1, where=costs >= 0, initial=10**9).tolist() == [4, 7]  # the plan's own lengths


def test_first_move_costs_agree_with_the_plan_and_its_label_on_generated_cases():
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(20):
        inst = generate_instance(rng, size=12, density=0.3, n_agents=6)
        res = plan_prioritized(inst.grid, inst.starts, inst.goals)
        costs = first_move_costs(inst.grid, inst.starts, inst.goals)
        if not res.solved:
            continue
        checked += 1
        label = plan_actions(res.positions)[0]
        moved = res.positions[:, :, None, :] != res.positions[-1][None, :, None, :]
        lengths = np.array([np.flatnonzero(moved[:, i, 0].any(-1)).max(initial=-1) + 1 for i in range(6)])
        for i in range(6):
            legal = costs[i] >= 0
            assert costs[i, label[i]] == costs[i][legal].min() == lengths[i]  # the label is among the cheapest
    assert checked >= 10


def test_first_move_costs_of_an_agent_on_its_goal_and_of_walls_and_bad_input():
    grid = np.zeros((3, 3), dtype=np.uint8)
    grid[1, 1] = 1
    costs = first_move_costs(grid, np.array([[0, 0]]), np.array([[0, 0]]))
    assert costs.tolist() == [[0, -1, 2, -1, 2]]  # staying keeps it there; a step out and back costs 2
    with pytest.raises(ValueError, match="agents"):
        first_move_costs(grid, np.array([[0, 0], [2, 2]]), np.array([[0, 0]]))
