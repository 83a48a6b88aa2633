"""The one strict solution validator, used by the tests and by every evaluation.

A solution is `positions` (T+1, N, 2): the (row, col) of every agent at steps 0..T. It is valid when
row 0 is the starts, every agent stays on free map cells, moves at most one 4-neighbour step per
step, no two agents share a cell (vertex conflict) and no two agents swap cells (edge conflict).
Following and rotations are allowed. A claimed outcome is checked too: success=True requires all
agents on their goals at the last step, success=False requires them not to be.
Checks run in this order: shape, starts, off-map, obstacles, jumps, vertex conflicts, swaps, claimed
outcome; the first failing check reports its earliest step (lowest agent) with agents and cells.
"""
from __future__ import annotations

import numpy as np

from mapf_world.grid import check_cells, check_grid


class SolutionError(ValueError):
    """A solution breaks the grid rules or misreports its outcome."""


def _cell(c) -> str:
    return f"({int(c[0])}, {int(c[1])})"


def validate_solution(grid, starts, goals, positions, success: bool | None = None) -> None:
    grid = check_grid(grid)
    starts = check_cells(grid, starts, what="starts")
    goals = check_cells(grid, goals, what="goals")
    n = starts.shape[0]
    pos = np.asarray(positions)
    if pos.ndim != 3 or pos.shape[0] < 1 or pos.shape[1:] != (n, 2):
        raise SolutionError(f"positions must have shape (T+1, {n}, 2), got {pos.shape}")
    if not np.issubdtype(pos.dtype, np.integer):
        raise SolutionError(f"positions must be integer cells, got dtype {pos.dtype}")
    pos = pos.astype(np.int64)
    h, w = grid.shape

    wrong = np.flatnonzero(np.any(pos[0] != starts, axis=1))
    if wrong.size:
        i = int(wrong[0])
        raise SolutionError(f"step 0: agent {i} is at {_cell(pos[0, i])}, its start is {_cell(starts[i])}")

    # Per-cell checks; report the earliest (step, agent).
    off = (pos[..., 0] < 0) | (pos[..., 0] >= h) | (pos[..., 1] < 0) | (pos[..., 1] >= w)
    if off.any():
        t, i = np.argwhere(off)[0]
        raise SolutionError(f"step {t}: agent {i} at {_cell(pos[t, i])} is off the {h}x{w} map")
    blocked = grid[pos[..., 0], pos[..., 1]] == 1
    if blocked.any():
        t, i = np.argwhere(blocked)[0]
        raise SolutionError(f"step {t}: agent {i} at {_cell(pos[t, i])} is on an obstacle")

    if pos.shape[0] > 1:
        step_len = np.abs(np.diff(pos, axis=0)).sum(axis=2)  # (T, N)
        if (step_len > 1).any():
            t, i = np.argwhere(step_len > 1)[0]
            raise SolutionError(
                f"step {t + 1}: agent {i} jumps from {_cell(pos[t, i])} to {_cell(pos[t + 1, i])} "
                "(more than one 4-neighbour step)"
            )

    lin = pos[..., 0] * w + pos[..., 1]  # (T+1, N) flat cells
    srt = np.sort(lin, axis=1)
    dup_rows = np.flatnonzero(np.any(srt[:, 1:] == srt[:, :-1], axis=1))
    if dup_rows.size:
        t = int(dup_rows[0])
        uniq, counts = np.unique(lin[t], return_counts=True)
        cell = int(uniq[counts > 1][0])
        agents = np.flatnonzero(lin[t] == cell).tolist()
        raise SolutionError(f"step {t}: agents {agents} share cell ({cell // w}, {cell % w}) (vertex conflict)")

    if pos.shape[0] > 1:
        # Without vertex conflicts, two agents crossing the same undirected edge in one step must
        # cross it in opposite directions: a swap. Key each move by (step, edge) and look for twins.
        prev, cur = lin[:-1], lin[1:]
        t_idx, i_idx = np.nonzero(prev != cur)
        if t_idx.size > 1:
            lo = np.minimum(prev[t_idx, i_idx], cur[t_idx, i_idx])
            hi = np.maximum(prev[t_idx, i_idx], cur[t_idx, i_idx])
            hw = h * w
            key = (t_idx * hw + lo) * hw + hi
            order = np.argsort(key, kind="stable")
            twin = np.flatnonzero(key[order][1:] == key[order][:-1])
            if twin.size:
                k1, k2 = order[twin[0]], order[twin[0] + 1]
                t = int(t_idx[k1]) + 1
                a, b = sorted((int(i_idx[k1]), int(i_idx[k2])))
                raise SolutionError(
                    f"step {t}: agents {a} and {b} swap cells {_cell(pos[t - 1, a])} <-> {_cell(pos[t - 1, b])} "
                    "(edge conflict)"
                )

    if success is not None:
        all_on_goal = bool(np.all(pos[-1] == goals))
        if success and not all_on_goal:
            i = int(np.flatnonzero(np.any(pos[-1] != goals, axis=1))[0])
            raise SolutionError(
                f"success claimed but at the last step {pos.shape[0] - 1} agent {i} is at {_cell(pos[-1, i])}, "
                f"its goal is {_cell(goals[i])}"
            )
        if not success and all_on_goal:
            raise SolutionError(
                f"failure claimed but all agents are on their goals at the last step {pos.shape[0] - 1}"
            )
