"""The floor every solver must beat: each agent follows its own shortest path, ignoring the others.

At each step an agent takes the action whose next cell has the smallest BFS distance to its goal
(stay included, ties broken by action order 0 stay, 1 up, 2 down, 3 left, 4 right), so it stays
once on its goal. It never waits for others: blocked moves simply fail under the grid rules.
"""
from __future__ import annotations

import numpy as np

from mapf_world.grid import DELTAS
from mapf_world.heuristics import UNREACHABLE
from mapf_world.solvers import check_options


class GreedySolver:
    name = "greedy"

    def __init__(self):
        self._padded: np.ndarray | None = None

    def reset(self, env) -> None:
        # Distance maps padded by one UNREACHABLE cell, so moves off the map are never chosen.
        self._padded = np.pad(env.dist, ((0, 0), (1, 1), (1, 1)), constant_values=UNREACHABLE)

    def act(self, obs: dict) -> np.ndarray:
        if self._padded is None:
            raise ValueError("greedy: act() called before reset(env)")
        pos = np.asarray(obs["position"]).astype(np.int64) + 1  # padded coordinates
        n = pos.shape[0]
        nxt = pos[:, None, :] + DELTAS[None, :, :]  # (N, 5, 2)
        d = self._padded[np.arange(n)[:, None], nxt[..., 0], nxt[..., 1]]  # (N, 5)
        return np.argmin(d, axis=1)  # first minimum = lowest action number


def make_greedy(**options) -> GreedySolver:
    check_options("greedy", options)
    return GreedySolver()
