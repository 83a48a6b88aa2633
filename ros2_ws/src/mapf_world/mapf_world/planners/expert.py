"""ExpertOracle: the ODrM* actions that supervise the learned policy (the paper's expert).

Given the current cells of all agents it returns every agent's next action. It plans from the
current cells and then reuses that plan for as long as the agents are on it: a call whose cells
equal the plan's cells at the next step (the agents did what the plan said) or at the current
step (asked again, or everyone waited) costs a comparison; the rest of a plan from any of its
steps is a valid plan from there. When the cells are anywhere else the agents have left the
plan and it replans from there.

Fallback: when planning fails (timeout, or no joint plan exists from these cells) every agent
takes its own shortest-path action (the move to the neighbour closest to its goal by BFS
distance, stay when on its goal; ties by action order), `last_fallback` is True and `fallbacks`
counts such calls. The next call tries to plan again.
"""
from __future__ import annotations

import numpy as np

from mapf_world.grid import DELTAS, check_cells, check_grid
from mapf_world.heuristics import UNREACHABLE, distance_maps
from mapf_world.planners.odrmstar import MAX_AGENTS, check_objective, plan_odrmstar
from mapf_world.planners.result import PlanResult, check_epsilon, check_time_limit, follow_plan, plan_actions


class ExpertOracle:
    """ODrM* expert for one map and goal set. time_limit is per (re)plan, in seconds (a failed plan
    costs that much every call until one succeeds, hence the short default); objective: see
    planners/odrmstar.py."""

    def __init__(self, grid, goals, epsilon: float = 10.0, time_limit: float = 2.0,
                 objective: str = "free_goal_wait"):
        self.grid = check_grid(grid)
        self.goals = check_cells(self.grid, goals, what="goals")
        if self.goals.shape[0] > MAX_AGENTS:
            raise ValueError(f"ODrM* supports at most {MAX_AGENTS} agents, got {self.goals.shape[0]}")
        self.epsilon = check_epsilon(epsilon)
        self.time_limit = check_time_limit(time_limit)
        self.objective = check_objective(objective)
        self.plans = 0  # successful plans (the first one included)
        self.replans = 0  # plans made because the agents had left the previous plan
        self.fallbacks = 0  # calls answered by the shortest-path fallback
        self.last_fallback = False
        self.last_result: PlanResult | None = None
        self._positions: np.ndarray | None = None  # (T+1, N, 2) current plan
        self._actions: np.ndarray | None = None  # (T, N)
        self._step = 0  # plan step the agents were last seen at
        self._padded_dist: np.ndarray | None = None

    @property
    def plan(self) -> np.ndarray | None:
        """The plan in use, (T+1, N, 2), or None."""
        return self._positions

    def actions(self, positions) -> np.ndarray:
        """(N,) int64 next actions from `positions` (N, 2)."""
        pos = np.asarray(positions)
        on = follow_plan(self._positions, self._step, pos)
        if on is not None:
            self._step = on
            return self._action_at(on)
        pos = check_cells(self.grid, pos, what="positions")
        if pos.shape != self.goals.shape:
            raise ValueError(f"positions has {pos.shape[0]} agents, the oracle {self.goals.shape[0]}")
        had_plan = self._positions is not None
        result = plan_odrmstar(self.grid, pos, self.goals, self.epsilon, self.time_limit, self.objective)
        self.last_result = result
        if not result.solved:
            self._positions = self._actions = None
            self.fallbacks += 1
            self.last_fallback = True
            return self._fallback(pos)
        self.plans += 1
        self.replans += had_plan
        self.last_fallback = False
        self._positions = result.positions
        self._actions = plan_actions(result.positions)
        self._step = 0
        return self._action_at(0)

    def _action_at(self, step: int) -> np.ndarray:
        if step >= self._actions.shape[0]:  # end of the plan: everyone is on its goal
            return np.zeros(self.goals.shape[0], dtype=np.int64)
        return self._actions[step].astype(np.int64)

    def _fallback(self, pos: np.ndarray) -> np.ndarray:
        if self._padded_dist is None:
            self._padded_dist = np.pad(distance_maps(self.grid, self.goals), ((0, 0), (1, 1), (1, 1)),
                                       constant_values=UNREACHABLE)
        nxt = pos[:, None, :] + 1 + DELTAS[None]  # (N, 5, 2) in padded coordinates
        n = pos.shape[0]
        d = self._padded_dist[np.arange(n)[:, None], nxt[..., 0], nxt[..., 1]]
        return np.argmin(d, axis=1).astype(np.int64)  # first minimum: stay wins on the goal
