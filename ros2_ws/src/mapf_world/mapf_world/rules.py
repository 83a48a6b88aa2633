"""The DHC step rules (../shared/benchmarks/dhc_40x40_d0.3/README.md), as one pure function.

1. A move off the map or into an obstacle fails: the agent stays.
2. Two agents that would swap cells both stay.
3. Several agents moving into one cell: if the cell ends the step occupied by an agent that stays
   there (by choice or because its move failed) every mover into it fails; otherwise the lowest
   agent index gets the cell and the other movers fail.
4. Failed moves turn agents into stayers, which can block further movers: repeat 3 to a fixpoint.
Following (moving into a cell that its occupant leaves) and rotations of >= 3 agents are allowed.

Failing is monotone (a failed agent never moves again and only ever blocks more cells), so the
fixpoint does not depend on the order in which conflicts are found. The movers' targets never
change, so the lowest-index tie-break needs one pass; after it only "blocked by an agent that
stays" can fail further movers, which the loop propagates round by round (cascades).
"""
from __future__ import annotations

import numpy as np

from mapf_world.grid import DELTAS, check_actions

_DROW = np.ascontiguousarray(DELTAS[:, 0])
_DCOL = np.ascontiguousarray(DELTAS[:, 1])


def resolve_moves(grid: np.ndarray, positions: np.ndarray, actions) -> tuple[np.ndarray, np.ndarray]:
    """Apply one joint step.

    grid: (H, W) uint8, 1 = obstacle. positions: (N, 2) distinct free cells (not re-checked here:
    the caller owns the state). actions: (N,) ints 0..4 (checked).
    Returns (new_positions (N, 2) int64, failed (N,) bool); failed[i] is True only when agent i
    asked to move (action != 0) and stayed.
    """
    positions = np.asarray(positions, dtype=np.int64)
    n = positions.shape[0]
    acts = check_actions(actions, n)
    h, w = grid.shape
    rows, cols = positions[:, 0], positions[:, 1]
    tr = rows + _DROW[acts]
    tc = cols + _DCOL[acts]
    cur = rows * w + cols  # flat cells
    # Rule 1: off the map or into an obstacle.
    ok = (acts != 0) & (tr >= 0) & (tr < h) & (tc >= 0) & (tc < w)
    tgt = cur.copy()
    tgt[ok] = tr[ok] * w + tc[ok]
    ok &= grid.reshape(-1)[tgt] == 0
    tgt[~ok] = cur[~ok]

    if ok.any():
        # Rule 2: swaps. occupant[cell] = agent standing there at the start of the step, else -1.
        occupant = np.full(h * w, -1, dtype=np.int64)
        occupant[cur] = np.arange(n)
        movers = np.flatnonzero(ok)
        other = occupant[tgt[movers]]
        swap = other >= 0
        swap[swap] = tgt[other[swap]] == cur[movers[swap]]
        ok[movers[swap]] = False
        movers = movers[~swap]

        # Rule 3: a cell of a staying agent blocks every mover into it; among movers into a free
        # cell the lowest index wins (stable sort keeps ascending agent order within a cell).
        blocked = np.zeros(h * w, dtype=bool)
        blocked[cur[~ok]] = True
        mt = tgt[movers]
        fail = blocked[mt]
        order = np.argsort(mt, kind="stable")
        st = mt[order]
        fail[order[1:][st[1:] == st[:-1]]] = True
        newly = movers[fail]
        movers = movers[~fail]
        # Rule 4: cascades. Each failed mover now stays and blocks its own cell.
        while newly.size:
            ok[newly] = False
            blocked[cur[newly]] = True
            hit = blocked[tgt[movers]]
            newly = movers[hit]
            movers = movers[~hit]
        tgt[~ok] = cur[~ok]

    new_positions = np.empty((n, 2), dtype=np.int64)
    np.divmod(tgt, w, out=(new_positions[:, 0], new_positions[:, 1]))
    return new_positions, (acts != 0) & ~ok
