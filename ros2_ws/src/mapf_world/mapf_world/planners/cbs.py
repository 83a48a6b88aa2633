"""Conflict-Based Search (Sharon et al. 2015), optimal for the sum of costs: the paper's CBS
baseline. C++ core (csrc/cbs.cpp); rules and costs as ODrM* (planners/result.py).
CBS cannot prove a case unsolvable unless every branch runs out of paths; an unsolvable case
normally ends in 'timeout'.
"""
from __future__ import annotations

import time

import numpy as np

from mapf_world.instances import check_instance
from mapf_world.planners import native
from mapf_world.planners.result import PlanResult, check_time_limit, finish


def plan_cbs(grid, starts, goals, time_limit: float = 10.0, cancel: np.ndarray | None = None) -> PlanResult:
    t0 = time.perf_counter()
    time_limit = check_time_limit(time_limit)
    grid, starts, goals = check_instance(grid, starts, goals)
    result = native.run(native.CBS, grid, starts, goals, 1.0, time_limit, cancel)
    return finish(result, grid, starts, goals, t0)
