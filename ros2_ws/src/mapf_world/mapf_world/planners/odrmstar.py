"""ODrM* (Ferner, Wagner & Choset 2013): recursive M* with operator decomposition and an
inflated heuristic, the expert of the paper (epsilon = 10). The search runs in C++
(csrc/odrmstar.cpp): in Python the per-node overhead made 64-agent cases far slower than the
0.5 s target.

Objectives (what the search minimises; the sum_of_costs it reports is always the plain
definition of planners/result.py):
- "sum_of_costs": that definition exactly. An agent resting on its goal that must later make way
  pays for all its waiting there, so an inflated search tends to send the others on detours.
- "free_goal_wait": every wait on one's own goal is free, the cost model of the M* reference
  implementation (Wagner's, used by PRIMAL) behind the paper's ODrM* figures. The default: with
  epsilon = 10 it gives the short plans the expert should teach (see the closing note of issue 3).
- "goal_keeping": "free_goal_wait", and a move off one's own goal costs 2 (beyond the paper). Where an
  agent on its goal stepping aside and another going round it cost the same, the one on its goal
  keeps it: the labels then teach a rule each agent can follow from what it sees (go round an agent
  that stands still), instead of one that depends on where the other agent is going.
"""
from __future__ import annotations

import time

import numpy as np

from mapf_world.instances import check_instance
from mapf_world.planners import native
from mapf_world.planners.result import PlanResult, check_epsilon, check_time_limit, finish

MAX_AGENTS = 64  # agent sets are 64-bit masks in the C++ core
OBJECTIVES = {"sum_of_costs": native.ODRMSTAR, "free_goal_wait": native.ODRMSTAR_FREE_GOAL_WAIT,
              "goal_keeping": native.ODRMSTAR_GOAL_KEEPING}


def check_objective(objective) -> str:
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {sorted(OBJECTIVES)}, got {objective!r}")
    return objective


def plan_odrmstar(grid, starts, goals, epsilon: float = 10.0, time_limit: float = 10.0,
                  objective: str = "free_goal_wait", cancel: np.ndarray | None = None) -> PlanResult:
    """Joint plan from `starts` to `goals`; epsilon = 1 gives a plan optimal for `objective`,
    larger values one within epsilon times that optimum, found faster. `cancel`: see native.run."""
    t0 = time.perf_counter()
    epsilon = check_epsilon(epsilon)
    time_limit = check_time_limit(time_limit)
    objective = check_objective(objective)
    grid, starts, goals = check_instance(grid, starts, goals)
    if starts.shape[0] > MAX_AGENTS:
        raise ValueError(f"ODrM* supports at most {MAX_AGENTS} agents, got {starts.shape[0]}")
    result = native.run(OBJECTIVES[objective], grid, starts, goals, epsilon, time_limit, cancel)
    return finish(result, grid, starts, goals, t0)
