"""Shortest-path distances on the 4-connected grid, vectorised with numpy.

`distance_maps` runs one breadth-first search per goal, all goals at once: the frontiers of every
goal are dilated together, one numpy pass per BFS level, so the cost is (levels x N x H x W)
vectorised work instead of N Python searches.
"""
from __future__ import annotations

import numpy as np

from mapf_world.grid import check_cells, check_grid

# Distance of obstacles and of cells that cannot reach the goal. Far below the int32 limit so
# that `dist + small` never overflows.
UNREACHABLE = 1 << 30


def distance_maps(grid, goals) -> np.ndarray:
    """(N, H, W) int32: 4-connected BFS distance from every cell to goal i, UNREACHABLE where none."""
    grid = check_grid(grid)
    goals = check_cells(grid, goals, what="goals")
    n = goals.shape[0]
    h, w = grid.shape
    # Work on a map padded by one obstacle cell, flattened, so the four neighbours of flat index k
    # are k-1, k+1, k-(w+2), k+(w+2) and shifts never wrap into the other side of a row.
    hp, wp = h + 2, w + 2
    free = np.zeros((hp, wp), dtype=bool)
    free[1:-1, 1:-1] = grid == 0
    free = free.reshape(-1)
    size = hp * wp
    dist = np.full((n, size), UNREACHABLE, dtype=np.int32)
    frontier = np.zeros((n, size), dtype=bool)
    frontier[np.arange(n), (goals[:, 0] + 1) * wp + goals[:, 1] + 1] = True
    unseen = np.broadcast_to(free, (n, size)).copy()
    unseen &= ~frontier
    grown = np.empty_like(frontier)
    level = 0
    while True:
        np.copyto(dist, level, where=frontier)
        grown[:] = False
        np.logical_or(grown[:, 1:], frontier[:, :-1], out=grown[:, 1:])
        np.logical_or(grown[:, :-1], frontier[:, 1:], out=grown[:, :-1])
        np.logical_or(grown[:, wp:], frontier[:, :-wp], out=grown[:, wp:])
        np.logical_or(grown[:, :-wp], frontier[:, wp:], out=grown[:, :-wp])
        np.logical_and(grown, unseen, out=frontier)
        if not frontier.any():
            break
        unseen &= ~frontier
        level += 1
    return dist.reshape(n, hp, wp)[:, 1:-1, 1:-1].copy()


def connected_components(grid) -> np.ndarray:
    """(H, W) int64 component label per free cell (4-connected), -1 on obstacles.

    Labels are the smallest flat index (row * W + col) of the component, so they are stable.
    Vectorised hooking and pointer jumping (a union-find over all edges at once): a few rounds.
    """
    grid = check_grid(grid)
    h, w = grid.shape
    free = (grid == 0).reshape(-1)
    idx = np.arange(h * w)
    flat = free.reshape(h, w)
    right = (flat[:, :-1] & flat[:, 1:]).reshape(-1)
    down = (flat[:-1, :] & flat[1:, :]).reshape(-1)
    ra = idx.reshape(h, w)[:, :-1].reshape(-1)[right]
    da = idx.reshape(h, w)[:-1, :].reshape(-1)[down]
    ea = np.concatenate((ra, da))
    eb = np.concatenate((ra + 1, da + w))
    parent = idx.copy()
    while True:
        pa, pb = parent[ea], parent[eb]
        diff = pa != pb
        if not diff.any():
            break
        hi = np.maximum(pa[diff], pb[diff])
        lo = np.minimum(pa[diff], pb[diff])
        # Roots only (parent is fully compressed below), so any of several writes to one root is a
        # valid smaller parent; the loop repeats until every edge joins equal labels.
        parent[hi] = np.minimum(parent[hi], lo)
        while True:
            nxt = parent[parent]
            if np.array_equal(nxt, parent):
                break
            parent = nxt
    labels = np.where(free, parent, -1)
    return labels.reshape(h, w)
