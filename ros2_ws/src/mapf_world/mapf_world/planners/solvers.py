"""Harness adapters (mapf_world.solvers protocol): plan once in reset(env), then replay.

reset(env) plans from env.positions to env.goals on env.grid and raises PlanFailed('unsolvable'
| 'timeout') when the planner gives up; act(obs) returns the plan's actions for the current step
and stay after the plan's end. The harness runs the plan through MapfEnv, so a planner's figures
mean the same as a learned policy's.
"""
from __future__ import annotations

import numpy as np

from mapf_world.planners.cbs import plan_cbs
from mapf_world.planners.odrmstar import check_objective, plan_odrmstar
from mapf_world.planners.result import PlanResult, check_epsilon, check_time_limit, plan_actions
from mapf_world.solvers import PlanFailed, check_options


class PlannerSolver:
    def __init__(self, name: str, plan, **options):
        self.name = name
        self._plan = plan
        self._options = options
        self.last_result: PlanResult | None = None
        self._positions: np.ndarray | None = None
        self._actions: np.ndarray | None = None
        self._step = 0

    def reset(self, env) -> None:
        self._positions = self._actions = None
        result = self._plan(env.grid, env.positions, env.goals, **self._options)
        self.last_result = result
        if not result.solved:
            raise PlanFailed(result.status, f"{self.name}: {result.status} after {result.seconds:.2f} s {result.message}".rstrip())
        self._positions = result.positions
        self._actions = plan_actions(result.positions)
        self._step = 0

    def act(self, obs: dict) -> np.ndarray:
        if self._actions is None:
            raise ValueError(f"{self.name}: act() called before a successful reset(env)")
        t = self._step
        expected = self._positions[min(t, len(self._positions) - 1)]
        if not np.array_equal(np.asarray(obs["position"]).astype(np.int64), expected):
            raise RuntimeError(f"{self.name}: at step {t} the agents are not where the plan put them")
        self._step += 1
        if t >= self._actions.shape[0]:
            return np.zeros(self._positions.shape[1], dtype=np.int64)
        return self._actions[t].astype(np.int64)


def make_odrmstar(**options) -> PlannerSolver:
    """Options: epsilon (default 10), time_limit (seconds, default 10), objective (default
    "free_goal_wait", see planners/odrmstar.py)."""
    check_options("odrmstar", options, ("epsilon", "time_limit", "objective"))
    epsilon = check_epsilon(options.get("epsilon", 10.0))
    time_limit = check_time_limit(options.get("time_limit", 10.0))
    objective = check_objective(options.get("objective", "free_goal_wait"))
    return PlannerSolver("odrmstar", plan_odrmstar, epsilon=epsilon, time_limit=time_limit, objective=objective)


def make_cbs(**options) -> PlannerSolver:
    """Options: time_limit (seconds, default 10)."""
    check_options("cbs", options, ("time_limit",))
    time_limit = check_time_limit(options.get("time_limit", 10.0))
    return PlannerSolver("cbs", plan_cbs, time_limit=time_limit)
