"""PlanResult, the input checks every planner shares, and plan <-> actions conversions.

Cost convention of every planner here: sum of costs, where agent i pays one per step up to the
step from which it stays on its goal to the end (waiting on the goal at the end is free; an agent
that leaves its goal again pays for all its waiting before).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from mapf_world.grid import DELTAS
from mapf_world.validate import validate_solution

STATUSES = ("solved", "unsolvable", "timeout")


@dataclass
class PlanResult:
    """Outcome of one planner call.

    status: 'solved', 'unsolvable' (the search space was exhausted: no joint plan exists) or
    'timeout' (out of time or memory budget, nothing proven). positions: (T+1, N, 2) int64 cells
    of every agent at steps 0..T when solved, else None. makespan = T; sum_of_costs as in the
    module docstring. seconds: wall time of the call; expansions: search nodes expanded.
    """

    status: str
    positions: np.ndarray | None
    sum_of_costs: int | None
    makespan: int | None
    seconds: float
    expansions: int
    message: str = field(default="")

    @property
    def solved(self) -> bool:
        return self.status == "solved"


def check_time_limit(time_limit) -> float:
    if isinstance(time_limit, bool) or not isinstance(time_limit, (int, float, np.integer, np.floating)):
        raise ValueError(f"time_limit must be a number of seconds > 0, got {time_limit!r}")
    if not math.isfinite(time_limit) or time_limit <= 0:
        raise ValueError(f"time_limit must be a finite number of seconds > 0, got {time_limit!r}")
    return float(time_limit)


def check_epsilon(epsilon) -> float:
    if isinstance(epsilon, bool) or not isinstance(epsilon, (int, float, np.integer, np.floating)):
        raise ValueError(f"epsilon must be a number >= 1, got {epsilon!r}")
    if not math.isfinite(epsilon) or epsilon < 1:
        raise ValueError(f"epsilon must be a finite number >= 1, got {epsilon!r}")
    return float(epsilon)


def finish(native, grid: np.ndarray, starts: np.ndarray, goals: np.ndarray, t0: float) -> PlanResult:
    """PlanResult from a native result; a solved plan is validated first (a bug raises here)."""
    positions = makespan = None
    if native.status == "solved":
        w = grid.shape[1]
        cells = native.cells.astype(np.int64)
        positions = np.stack((cells // w, cells % w), axis=-1)
        validate_solution(grid, starts, goals, positions, success=True)
        makespan = positions.shape[0] - 1
    return PlanResult(native.status, positions, native.sum_of_costs, makespan, time.perf_counter() - t0,
                      native.expansions, native.message)


def plan_actions(positions: np.ndarray) -> np.ndarray:
    """(T, N) actions 0..4 that move a plan's agents from step t to t+1 (ValueError on a jump)."""
    pos = np.asarray(positions, dtype=np.int64)
    delta = pos[1:] - pos[:-1]  # (T, N, 2)
    match = np.all(delta[:, :, None, :] == DELTAS[None, None, :, :], axis=-1)  # (T, N, 5)
    if not match.any(axis=-1).all():
        t, i = np.argwhere(~match.any(axis=-1))[0]
        raise ValueError(f"plan step {t + 1}: agent {i} moves by {delta[t, i].tolist()}, not one 4-neighbour step")
    return np.argmax(match, axis=-1)


def follow_plan(plan: np.ndarray | None, step: int, positions: np.ndarray) -> int | None:
    """The step of `plan` (T+1, N, 2) the agents stand at, for oracles that reuse a plan while the agents keep to it:
    step + 1 when they did what the plan said, `step` when they are where they were (asked again, or everyone
    waited); None when they left the plan, or there is none. The rest of a plan from any of its steps is a valid
    plan from there."""
    if plan is None or positions.shape != plan.shape[1:]:
        return None
    nxt = min(step + 1, plan.shape[0] - 1)
    if np.array_equal(positions, plan[nxt]):
        return nxt
    if np.array_equal(positions, plan[step]):
        return step
    return None
