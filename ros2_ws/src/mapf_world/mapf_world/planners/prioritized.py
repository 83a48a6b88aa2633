"""Prioritized planning in agent-index order: a MAPF expert whose give-way rule the agents can observe.

Beyond the paper (its expert is ODrM*). ODrM* settles who gives way by whatever joint plan it finds first,
so two agents in mirror-image situations often get labels that both push; a memoryless learner cannot
copy that. Here the agents plan one after the other in index order (agent 0 first), each by space-time
A* around the paths already planned, and ignoring the agents after it. So an agent never yields to a
later one, and always makes way for an earlier one: the give-way rule is the index order, which the
priority channel of the observation shows (mapf_world.observation, `priority=True`).

The search respects the DHC step rules (mapf_world.rules): no two agents in one cell at one step, no
swaps; following into a cell that its occupant leaves is allowed. An agent that has arrived for good
stays on its goal, so a later agent may not cross that cell afterwards. Prioritized planning is
incomplete: an agent may find no path around the earlier ones (for example an earlier agent parked in
the only corridor); `plan_prioritized` then reports which agent failed.

Time steps are counted from the cells given (t = 0); cells are flat indices row * W + col inside.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from mapf_world.grid import DELTAS, check_cells, check_grid
from mapf_world.heuristics import UNREACHABLE, distance_maps
from mapf_world.planners.result import follow_plan, plan_actions

# Expansions per agent before the search gives up (a 20x20 map has 400 cells; a free path needs ~40).
DEFAULT_MAX_EXPANSIONS = 20_000


@dataclass
class PrioritizedResult:
    """positions: (T+1, N, 2) joint plan (every agent padded on its goal to the longest path), or None;
    failed_agent: the first agent (index) that found no path, or -1; expansions: A* pops, all agents."""
    positions: np.ndarray | None
    failed_agent: int
    expansions: int

    @property
    def solved(self) -> bool:
        return self.positions is not None


class _Reservations:
    """Cells and moves taken by the agents planned so far."""

    def __init__(self):
        self.cells: set[tuple[int, int]] = set()  # (cell, t)
        self.moves: set[tuple[int, int, int]] = set()  # (from, to, t): from at t-1, to at t
        self.parked: dict[int, int] = {}  # cell -> first step of an agent staying there for good
        self.last: dict[int, int] = {}  # cell -> last step at which it is reserved (parked: parked step)

    def add(self, path: list[int]) -> None:
        for t, c in enumerate(path):
            self.cells.add((c, t))
            self.last[c] = max(self.last.get(c, -1), t)
            if t:
                self.moves.add((path[t - 1], c, t))
        self.parked[path[-1]] = len(path) - 1

    def free(self, frm: int, to: int, t: int) -> bool:
        """May an agent at `frm` (step t-1) be at `to` at step t?"""
        if (to, t) in self.cells or self.parked.get(to, t + 1) <= t:
            return False
        return frm == to or (to, frm, t) not in self.moves  # a swap with an earlier agent

    def can_stop(self, cell: int, t: int) -> bool:
        """May an agent stay on `cell` from step t on for good? Nobody earlier passes it later."""
        return cell not in self.parked and self.last.get(cell, -1) < t


def _neighbours(grid: np.ndarray) -> list[list[int]]:
    """Per flat cell: the flat cells reachable in one step, in action order (stay first)."""
    h, w = grid.shape
    out = []
    for r in range(h):
        for c in range(w):
            nb = []
            if not grid[r, c]:
                for dr, dc in DELTAS:
                    nr, nc = r + dr, c + dc
                    if 0 <= nr < h and 0 <= nc < w and not grid[nr, nc]:
                        nb.append(nr * w + nc)
            out.append(nb)
    return out


def _space_time_astar(start: int, goal: int, dist: np.ndarray, nbrs: list[list[int]], res: _Reservations,
                      max_expansions: int, t0: int = 0) -> tuple[list[int] | None, int]:
    """Shortest path (flat cells per step, the first at step t0) from start at t0 to staying on goal for good,
    around `res`."""
    if dist[start] >= UNREACHABLE or goal in res.parked:
        return None, 0
    # After `horizon` only parked cells are taken, so the world stands still: states from then on are
    # keyed by cell alone (t clamped to horizon), which keeps a search that cannot succeed finite.
    horizon = max(res.last.values(), default=0) + 1
    # Heap entries (f, -t, tie, cell, t): f = t + distance; deeper first among equal f; then insertion order,
    # which follows the action order (stay, up, down, left, right), so equal plans break ties the same way.
    heap = [(t0 + int(dist[start]), -t0, 0, start, t0)]
    parent: dict[tuple[int, int], tuple[int, int] | None] = {(start, min(t0, horizon)): None}
    tie, expansions = 1, 0
    while heap:
        _, _, _, cell, t = heapq.heappop(heap)
        expansions += 1
        if cell == goal and res.can_stop(cell, t):
            path, node = [], (cell, min(t, horizon))
            while node is not None:
                path.append(node[0])
                node = parent[node]
            return path[::-1], expansions
        if expansions >= max_expansions:
            return None, expansions
        nt = t + 1
        for nxt in nbrs[cell]:
            key = (nxt, min(nt, horizon))
            if key in parent or dist[nxt] >= UNREACHABLE or not res.free(cell, nxt, nt):
                continue
            parent[key] = (cell, min(t, horizon))
            heapq.heappush(heap, (nt + int(dist[nxt]), -nt, tie, nxt, nt))
            tie += 1
    return None, expansions


def plan_prioritized(grid, starts, goals, dist: np.ndarray | None = None,
                     max_expansions: int = DEFAULT_MAX_EXPANSIONS, nbrs: list[list[int]] | None = None
                     ) -> PrioritizedResult:
    """Plan the agents in index order; `dist` (N, H, W) BFS distances to the goals and `nbrs` (the grid's
    moves per flat cell) if already known (an oracle plans many times on one map)."""
    grid = check_grid(grid)
    starts = check_cells(grid, starts, what="starts")
    goals = check_cells(grid, goals, what="goals")
    if starts.shape != goals.shape:
        raise ValueError(f"starts has {starts.shape[0]} agents, goals {goals.shape[0]}")
    if max_expansions < 1:
        raise ValueError(f"max_expansions must be >= 1, got {max_expansions}")
    if dist is None:
        dist = distance_maps(grid, goals)
    w = grid.shape[1]
    flat_dist = np.asarray(dist).reshape(len(goals), -1)
    nbrs = _neighbours(grid) if nbrs is None else nbrs
    res, paths, total = _Reservations(), [], 0
    for i, (s, g) in enumerate(zip(starts, goals)):
        path, n = _space_time_astar(int(s[0] * w + s[1]), int(g[0] * w + g[1]), flat_dist[i], nbrs, res,
                                    max_expansions)
        total += n
        if path is None:
            return PrioritizedResult(None, i, total)
        res.add(path)
        paths.append(path)
    length = max(len(p) for p in paths)
    flat = np.array([p + [p[-1]] * (length - len(p)) for p in paths], dtype=np.int64).T  # (T+1, N)
    return PrioritizedResult(np.stack([flat // w, flat % w], axis=-1), -1, total)


def first_move_costs(grid, positions, goals, dist: np.ndarray | None = None,
                     max_expansions: int = DEFAULT_MAX_EXPANSIONS, nbrs: list[list[int]] | None = None) -> np.ndarray:
    """(N, 5) int: for each agent and first action (stay, up, down, left, right), the length of its shortest
    plan that starts with that action (steps until it stays on its goal for good), planned as plan_prioritized
    plans: in index order, around the plans of the earlier agents and ignoring the later ones; -1 where the
    action is illegal (a wall, off the map, a cell or swap taken by an earlier agent) or leaves no plan.

    Its minimum over actions is the agent's cost in the prioritized plan, and the actions at that minimum are
    the moves the expert ranks equal: its label is one of them, picked by the search's fixed direction order.
    An agent with no plan at all (row of -1) stops the planning: the later agents' rows are -1 too."""
    grid = check_grid(grid)
    positions = check_cells(grid, positions, what="positions")
    goals = check_cells(grid, goals, what="goals")
    if positions.shape != goals.shape:
        raise ValueError(f"positions has {positions.shape[0]} agents, goals {goals.shape[0]}")
    if dist is None:
        dist = distance_maps(grid, goals)
    h, w = grid.shape
    flat_dist = np.asarray(dist).reshape(len(goals), -1)
    nbrs = _neighbours(grid) if nbrs is None else nbrs
    costs = np.full((len(goals), len(DELTAS)), -1, dtype=np.int64)
    res = _Reservations()
    for i, (s, g) in enumerate(zip(positions, goals)):
        start, goal = int(s[0] * w + s[1]), int(g[0] * w + g[1])
        for a, (dr, dc) in enumerate(DELTAS):
            r, c = int(s[0] + dr), int(s[1] + dc)
            if not (0 <= r < h and 0 <= c < w) or grid[r, c] or not res.free(start, r * w + c, 1):
                continue
            if a == 0 and start == goal and res.can_stop(start, 0):
                path = [start]  # already there for good: the plan's cost is 0, staying keeps it
            else:
                tail, _ = _space_time_astar(r * w + c, goal, flat_dist[i], nbrs, res, max_expansions, t0=1)
                path = None if tail is None else [start] + tail
            if path is not None:
                costs[i, a] = len(path) - 1
        # The later agents plan around the path plan_prioritized picks among the equal ones (its tie order).
        chosen, _ = _space_time_astar(start, goal, flat_dist[i], nbrs, res, max_expansions)
        if chosen is None:
            break
        res.add(chosen)
    return costs


class PrioritizedOracle:
    """Next actions of the prioritized plan from the cells given; like ExpertOracle it follows its plan while
    the agents keep to it and replans when they leave it. `last_failed` says the last call found no plan
    (actions() then returns None); `plans` and `failures` count."""

    def __init__(self, grid, goals, dist: np.ndarray | None = None, max_expansions: int = DEFAULT_MAX_EXPANSIONS):
        self.grid = check_grid(grid)
        self.goals = check_cells(self.grid, goals, what="goals")
        self.dist = distance_maps(self.grid, self.goals) if dist is None else np.asarray(dist)
        self.max_expansions = max_expansions
        self._nbrs = _neighbours(self.grid)
        self.plans = self.failures = 0
        self.last_failed = False
        self._positions: np.ndarray | None = None
        self._actions: np.ndarray | None = None
        self._step = 0

    def actions(self, positions) -> np.ndarray | None:
        pos = np.asarray(positions, dtype=np.int64)
        on = follow_plan(self._positions, self._step, pos)
        if on is not None:
            self._step = on
            return self._action_at(on)
        result = plan_prioritized(self.grid, pos, self.goals, self.dist, self.max_expansions, self._nbrs)
        self.last_failed = not result.solved
        if not result.solved:
            self.failures += 1
            self._positions = self._actions = None
            return None
        self.plans += 1
        self._positions, self._actions, self._step = result.positions, plan_actions(result.positions), 0
        return self._action_at(0)

    def _action_at(self, step: int) -> np.ndarray:
        if step >= self._actions.shape[0]:
            return np.zeros(self.goals.shape[0], dtype=np.int64)
        return self._actions[step].astype(np.int64)
