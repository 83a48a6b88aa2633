"""Exhaustive joint-state search, the test oracle of the planners (tiny instances only).

Dijkstra over joint states with the planners' rules and costs, written independently of the C++:
a state is, per agent, its cell and whether it has finished (declared that it stays on its goal
for good). Per step every agent picks stay or a move to a free 4-neighbour, or, on its goal, may
finish; a finished agent stays. Two agents in one cell or swapping cells is forbidden; following
and rotations are allowed. Step cost per agent: 0 when finishing or finished, else 1. So an
agent pays one per step until it finishes, which is the sum-of-costs convention (waiting on the
goal at the end is free, waiting there before leaving again is not). Goal: every agent on its goal.
"""
from __future__ import annotations

import heapq
import itertools

import numpy as np


def optimal_sum_of_costs(grid, starts, goals, free_goal_wait: bool = False, leave_cost: int = 1) -> int | None:
    """Optimal cost, or None when no joint plan exists (memoised: several tests ask for the same).
    leave_cost: the cost of a move off one's own goal (2: ODrM*'s goal_keeping objective)."""
    grid = np.asarray(grid, dtype=np.uint8)
    key = (grid.shape, grid.tobytes(), np.asarray(starts).tobytes(), np.asarray(goals).tobytes(), free_goal_wait,
           leave_cost)
    if key not in _MEMO:
        _MEMO[key] = _search(grid, starts, goals, free_goal_wait, leave_cost)
    return _MEMO[key]


_MEMO: dict = {}


def _search(grid, starts, goals, free_goal_wait: bool, leave_cost: int = 1, max_states: int = 2_000_000) -> int | None:
    h, w = grid.shape
    goals = [tuple(int(v) for v in g) for g in goals]
    n = len(goals)

    def options(agent, cell, finished):
        if finished:
            return [(cell, True, 0)]
        at_goal = cell == goals[agent]
        out = [(cell, False, 0 if (free_goal_wait and at_goal) else 1)]
        if at_goal and not free_goal_wait:
            out.append((cell, True, 0))
        r, c = cell
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            rr, cc = r + dr, c + dc
            if 0 <= rr < h and 0 <= cc < w and grid[rr, cc] == 0:
                out.append(((rr, cc), False, leave_cost if at_goal else 1))
        return out

    start = tuple((tuple(int(v) for v in s), False) for s in starts)
    best = {start: 0}
    heap = [(0, start)]
    while heap:
        cost, state = heapq.heappop(heap)
        if cost > best[state]:
            continue
        if all(state[i][0] == goals[i] for i in range(n)):
            return cost
        if len(best) > max_states:
            raise RuntimeError("exhaustive search too large for a unit test")
        for combo in itertools.product(*(options(i, *state[i]) for i in range(n))):
            new_cells = [c[0] for c in combo]
            if len(set(new_cells)) < n:
                continue
            if any(new_cells[i] == state[j][0] and new_cells[j] == state[i][0] and new_cells[i] != state[i][0]
                   for i in range(n) for j in range(i + 1, n)):
                continue
            nxt = tuple((c[0], c[1]) for c in combo)
            nc = cost + sum(c[2] for c in combo)
            if nc < best.get(nxt, 1 << 60):
                best[nxt] = nc
                heapq.heappush(heap, (nc, nxt))
    return None


def plan_sum_of_costs(positions, goals) -> int:
    """Sum of costs of a plan by the plain definition: per agent, the first step from which it
    stays on its goal to the end."""
    pos = np.asarray(positions)
    total = 0
    for i in range(pos.shape[1]):
        on = np.all(pos[:, i] == np.asarray(goals)[i], axis=1)
        off = np.flatnonzero(~on)
        total += 0 if off.size == 0 else int(off[-1]) + 1
    return total


# --- the oracle itself, on cases small enough to count by hand -------------------------------
def test_oracle_single_agent_is_its_distance():
    grid = np.zeros((3, 4), np.uint8)
    assert optimal_sum_of_costs(grid, [[0, 0]], [[2, 3]]) == 5


def test_oracle_swap_in_a_corridor_is_unsolvable():
    grid = np.zeros((1, 3), np.uint8)
    assert optimal_sum_of_costs(grid, [[0, 0], [0, 1]], [[0, 1], [0, 0]]) is None


def test_oracle_waiting_on_the_goal_counts_only_before_leaving_it():
    # Corridor 0-1-2-3 with a pocket below cell 1. Agent 0 sits on its goal (0,1) and must make
    # way for agent 1 going from (0,0) to (0,3): it steps into the pocket and back (2 steps),
    # agent 1 walks 3 steps. Agent 0 leaves its goal at step 1 and is back at step 2 at best.
    grid = np.array([[0, 0, 0, 0], [1, 0, 1, 1]], np.uint8)
    assert optimal_sum_of_costs(grid, [[0, 1], [0, 0]], [[0, 1], [0, 3]]) == 2 + 3
    # Same cost when waits on the goal are free: agent 0 never waits before leaving.
    assert optimal_sum_of_costs(grid, [[0, 1], [0, 0]], [[0, 1], [0, 3]], free_goal_wait=True) == 5


def test_oracle_charges_the_wait_before_leaving_the_goal():
    # Row 0 is a corridor, (1,3) a pocket below it. Agent 0 starts on its goal (0,3), in the way
    # of agent 1 going (0,0) -> (0,4). Best: agent 1 walks 4 steps; agent 0 drops into the pocket
    # as agent 1 enters (0,3) (following) and comes back behind it, at step 4. Exactly: agent 0
    # pays its 3 waits on the goal too, 4 + 4 = 8; with free waits on the goal only 2 + 4 = 6.
    grid = np.array([[0, 0, 0, 0, 0], [1, 1, 1, 0, 1]], np.uint8)
    starts, goals = [[0, 3], [0, 0]], [[0, 3], [0, 4]]
    assert optimal_sum_of_costs(grid, starts, goals) == 8
    assert optimal_sum_of_costs(grid, starts, goals, free_goal_wait=True) == 6
    plan = [[[0, 3], [0, 0]], [[0, 3], [0, 1]], [[0, 3], [0, 2]], [[1, 3], [0, 3]], [[0, 3], [0, 4]]]
    assert plan_sum_of_costs(plan, goals) == 8


def tiny_cases(seed: int, count: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """`count` random solvable-or-not tiny cases: 3x3..4x5 maps, 20 % obstacles, 2-3 agents,
    every goal reachable from its start (like MapfEnv requires)."""
    from mapf_world.heuristics import connected_components

    rng = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        h, w = int(rng.integers(3, 5)), int(rng.integers(3, 6))
        grid = (rng.random((h, w)) < 0.2).astype(np.uint8)
        free = np.argwhere(grid == 0)
        n = int(rng.integers(2, 4))
        if len(free) < 2 * n:
            continue
        idx = rng.permutation(len(free))[: 2 * n]
        starts, goals = free[idx[:n]], free[idx[n:]]
        labels = connected_components(grid)
        if np.any(labels[tuple(starts.T)] != labels[tuple(goals.T)]):
            continue
        out.append((grid, starts, goals))
    return out
