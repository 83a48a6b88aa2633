"""The expert behind HSCL labels: ODrM* (paper), prioritized planning in index order falling back to ODrM*
(beyond the paper: a give-way rule the priority channel shows), or a per-agent shortest-path stand-in (tests,
smoke runs).

Two uses:
- `solve(...)`: a whole expert solution of a training instance, positions (T+1, N, 2), for demonstrations;
- `make_oracle(...)`: `.actions(positions) -> (N,)` expert actions on states the actors visit (relabelling).
The stand-in ignores other agents, so it is no MAPF expert: it only keeps the pipeline testable without
the native planner and is never the default.
"""
from __future__ import annotations

import numpy as np

from mapf_policy.config import EXPERT_ORDERS
from mapf_world.env import MapfEnv
from mapf_world.grid import DELTAS, STAY


class ExpertFailed(RuntimeError):
    """The expert gave no solution; the caller skips the instance (or the rest of an episode's labels).

    `reason`: 'timeout', 'unsolvable', 'fallback' (the oracle answered with its shortest-path fallback,
    which is no expert label) or 'error' (the planner raised; counted, so planner bugs stay visible).
    """

    def __init__(self, reason: str, message: str = ""):
        self.reason = reason
        super().__init__(message or reason)


class ShortestPathExpert:
    """Each agent takes the first action (in 0..4 order) that lowers its BFS distance to its goal."""

    def __init__(self, grid: np.ndarray, goals: np.ndarray, dist: np.ndarray):
        self.grid, self.goals, self.dist = grid, goals, dist

    def actions(self, positions: np.ndarray) -> np.ndarray:
        positions = np.asarray(positions, dtype=np.int64)
        h, w = self.grid.shape
        out = np.full(len(positions), STAY, dtype=np.int64)
        for i, (r, c) in enumerate(positions):
            here = self.dist[i, r, c]
            for a in range(1, 5):
                nr, nc = r + DELTAS[a, 0], c + DELTAS[a, 1]
                if 0 <= nr < h and 0 <= nc < w and self.dist[i, nr, nc] < here:
                    out[i] = a
                    break
        return out


class _OdrmOracle:
    """Adapter over mapf_world's ExpertOracle: its shortest-path fallback and its errors become ExpertFailed."""

    def __init__(self, oracle):
        self._oracle = oracle

    def actions(self, positions: np.ndarray) -> np.ndarray:
        try:
            actions = np.asarray(self._oracle.actions(np.asarray(positions)), dtype=np.int64)
        except Exception as exc:  # the states come from MapfEnv, so an error here is the planner's
            raise ExpertFailed("error", f"ODrM* oracle raised: {exc}") from exc
        if self._oracle.last_fallback:
            raise ExpertFailed("fallback", "ODrM* found no plan from these cells")
        return actions


# The order in which the agents are handed to ODrM* (config.EXPERT_ORDERS). Its plans depend on it where
# several joint moves are equally good (operator decomposition expands the agents one by one, in index
# order), so the same cells can get other labels under another order:
#   index     the instance's agent indices (the paper; every run so far);
#   reversed  the indices backwards (a fixed relabelling of the same kind, for comparison);
#   position  sorted by current cell, row first, at every call: an order that each agent can work out from
#             its own view (its position input and the cells of the agents it sees), unlike indices.
def agent_order(order: str, positions: np.ndarray) -> np.ndarray:
    """Permutation p: the planner's agent k is the instance's agent p[k]."""
    n = len(positions)
    if order == "index":
        return np.arange(n)
    if order == "reversed":
        return np.arange(n)[::-1].copy()
    if order == "position":
        return np.lexsort((positions[:, 1], positions[:, 0]))  # row first, then column
    raise ValueError(f"unknown expert order {order!r}; one of {EXPERT_ORDERS}")


class OrderedOracle:
    """ODrM* labels with the agents handed to the planner in `order` (EXPERT_ORDERS); actions come back in
    the instance's agent order. A new order (position: agents changed places) means a new plan."""

    def __init__(self, make, goals: np.ndarray, order: str):
        if order not in EXPERT_ORDERS:
            raise ValueError(f"unknown expert order {order!r}; one of {EXPERT_ORDERS}")
        self._make, self.goals, self.order = make, np.asarray(goals), order
        self._perm, self._oracle = None, None

    def actions(self, positions: np.ndarray) -> np.ndarray:
        positions = np.asarray(positions, dtype=np.int64)
        perm = agent_order(self.order, positions)
        if self._perm is None or not np.array_equal(perm, self._perm):
            self._perm, self._oracle = perm, self._make(self.goals[perm])
        out = np.empty(len(perm), dtype=np.int64)
        out[perm] = self._oracle.actions(positions[perm])
        return out


class _PrioritizedThenOdrm:
    """Beyond the paper: prioritized planning in index order (mapf_world.planners.prioritized), whose give-way
    rule the priority channel shows; where it finds no plan (an earlier agent parked in the only way), the
    ODrM* oracle labels that state. `pp_states` / `odrm_states` count the states each answered."""

    def __init__(self, pp, odrm):
        self._pp, self._odrm = pp, odrm
        self.pp_states = self.odrm_states = 0

    def actions(self, positions: np.ndarray) -> np.ndarray:
        actions = self._pp.actions(positions)
        if actions is not None:
            self.pp_states += 1
            return actions
        self.odrm_states += 1
        return self._odrm.actions(positions)


def make_oracle(kind: str, grid: np.ndarray, goals: np.ndarray, dist: np.ndarray, epsilon: float, time_limit: float,
                order: str = "index", objective: str = "free_goal_wait"):
    """An oracle with `.actions(positions)`; `order` and `objective` (odrmstar only): see EXPERT_ORDERS and
    mapf_world.planners.odrmstar.OBJECTIVES."""
    if kind == "shortest_path":
        return ShortestPathExpert(grid, goals, dist)
    if kind == "odrmstar":
        from mapf_world.planners.expert import ExpertOracle  # native planner: imported only when used

        def make(goals_in_order):
            return _OdrmOracle(ExpertOracle(grid, goals_in_order, epsilon=epsilon, time_limit=time_limit,
                                            objective=objective))

        return make(goals) if order == "index" else OrderedOracle(make, goals, order)
    if kind == "prioritized":
        from mapf_world.planners.expert import ExpertOracle
        from mapf_world.planners.prioritized import PrioritizedOracle

        if order != "index":
            raise ValueError(f"the prioritized expert plans in index order only, got order {order!r}")
        odrm = _OdrmOracle(ExpertOracle(grid, goals, epsilon=epsilon, time_limit=time_limit, objective=objective))
        return _PrioritizedThenOdrm(PrioritizedOracle(grid, goals, dist), odrm)
    raise ValueError(f"unknown expert {kind!r} (odrmstar, prioritized or shortest_path)")


def solve(kind: str, env: MapfEnv, epsilon: float, time_limit: float) -> np.ndarray:
    """Expert joint plan positions (T+1, N, 2) from the env's starts; ExpertFailed if there is none."""
    if kind == "odrmstar":
        from mapf_world.planners.odrmstar import plan_odrmstar

        try:
            result = plan_odrmstar(env.grid, env.starts, env.goals, epsilon=epsilon, time_limit=time_limit)
        except Exception as exc:  # the instance passed MapfEnv's checks, so an error here is the planner's
            raise ExpertFailed("error", f"ODrM* raised: {exc}") from exc
        if result.positions is None:
            raise ExpertFailed(result.status, f"ODrM* returned status {result.status!r}")
        return np.asarray(result.positions, dtype=np.int64)
    if kind == "shortest_path":
        expert = ShortestPathExpert(env.grid, env.goals, env.dist)
        env.reset()
        trajectory = [env.positions]
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step(expert.actions(env.positions))
            trajectory.append(env.positions)
            done = terminated or truncated
        if not terminated:
            raise ExpertFailed("timeout", "shortest-path stand-in did not finish within the step limit")
        return np.stack(trajectory)
    raise ValueError(f"unknown expert {kind!r} (odrmstar or shortest_path)")


def plan_actions(positions: np.ndarray) -> np.ndarray:
    """(T, N) actions that move a joint plan from step t to t+1; ValueError if a move is not a unit step."""
    delta = np.diff(positions, axis=0)  # (T, N, 2)
    actions = np.full(delta.shape[:2], -1, dtype=np.int64)
    for a, d in enumerate(DELTAS):
        actions[np.all(delta == d, axis=2)] = a
    if np.any(actions < 0):
        t, i = np.argwhere(actions < 0)[0]
        raise ValueError(f"plan step {t}: agent {i} moves by {delta[t, i].tolist()}, not a unit move")
    return actions
