"""Grid-world conventions and the input checks every module shares.

Conventions (docs/ARCHITECTURE.md):
- a map (`Grid`) is an (H, W) uint8 array, 1 = obstacle, 0 = free;
- a cell is (row, col); an array of cells (`Cells`) is (N, 2) int64, row first;
- actions are 0 stay, 1 up (row-1), 2 down (row+1), 3 left (col-1), 4 right (col+1).

The checks raise ValueError naming the problem and the agent; they never clip or repair input.
"""
from __future__ import annotations

import numpy as np

Grid = np.ndarray  # (H, W) uint8, 1 = obstacle
Cells = np.ndarray  # (N, 2) int64, (row, col)

STAY, UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3, 4
N_ACTIONS = 5
ACTION_NAMES = ("stay", "up", "down", "left", "right")
# (drow, dcol) per action, indexed by the action number.
DELTAS = np.array([[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]], dtype=np.int64)
DELTAS.setflags(write=False)


def _is_integer_valued(arr: np.ndarray) -> bool:
    """True for integer arrays and for float arrays whose values are all whole numbers."""
    if arr.dtype == bool:
        return False
    if np.issubdtype(arr.dtype, np.integer):
        return True
    if np.issubdtype(arr.dtype, np.floating):
        return bool(np.all(np.isfinite(arr)) and np.all(arr == np.round(arr)))
    return False


def check_grid(grid) -> np.ndarray:
    """Return the map as a C-contiguous (H, W) uint8 array of 0/1; ValueError otherwise."""
    arr = np.asarray(grid)
    if arr.ndim != 2:
        raise ValueError(f"grid must be a 2-D (H, W) array, got shape {arr.shape}")
    if arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"grid must not be empty, got shape {arr.shape}")
    if arr.dtype != bool and not _is_integer_valued(arr):
        raise ValueError(f"grid must hold 0 (free) and 1 (obstacle), got dtype {arr.dtype}")
    bad = (arr != 0) & (arr != 1)
    if np.any(bad):
        r, c = np.argwhere(bad)[0]
        raise ValueError(f"grid must hold only 0 (free) and 1 (obstacle); cell ({r}, {c}) is {arr[r, c].item()!r}")
    return np.ascontiguousarray(arr, dtype=np.uint8)


def check_cells(grid, cells, what: str = "starts") -> np.ndarray:
    """Return `cells` as (N, 2) int64 after checking they are on the map, free and distinct.

    `what` names the cells in messages ("starts", "goals", ...). `grid` must already be checked.
    """
    arr = np.asarray(cells)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{what} must be an (N, 2) array of (row, col) cells, got shape {arr.shape}")
    if arr.shape[0] == 0:
        raise ValueError(f"{what} must hold at least one agent")
    if not _is_integer_valued(arr):
        raise ValueError(f"{what} must be integer (row, col) cells, got dtype {arr.dtype}")
    arr = arr.astype(np.int64)
    h, w = grid.shape
    for i, (r, c) in enumerate(arr.tolist()):
        if not (0 <= r < h and 0 <= c < w):
            raise ValueError(f"{what}: agent {i} cell ({r}, {c}) is off the {h}x{w} map")
        if grid[r, c]:
            raise ValueError(f"{what}: agent {i} cell ({r}, {c}) is on an obstacle")
    lin = arr[:, 0] * w + arr[:, 1]
    uniq, first, counts = np.unique(lin, return_index=True, return_counts=True)
    if np.any(counts > 1):
        cell = uniq[counts > 1][0]
        agents = np.flatnonzero(lin == cell).tolist()
        raise ValueError(f"{what}: agents {agents} share cell ({cell // w}, {cell % w}); cells must be distinct")
    return arr


def check_actions(actions, n_agents: int) -> np.ndarray:
    """Return actions as (N,) int64 after checking count, integrality and the range 0..4."""
    arr = np.asarray(actions)
    if arr.dtype.kind in "iu" and arr.shape == (n_agents,) and n_agents:
        # Fast path for the per-step call: integer arrays need only the range check.
        if arr.min() >= 0 and arr.max() < N_ACTIONS:
            return arr.astype(np.int64, copy=False)
    if arr.ndim != 1 or arr.shape[0] != n_agents:
        raise ValueError(f"expected {n_agents} actions (one per agent), got shape {arr.shape}")
    if arr.dtype == bool or not np.issubdtype(arr.dtype, np.integer):
        if not _is_integer_valued(arr):
            raise ValueError(f"actions must be integers 0..4, got dtype {arr.dtype}: {arr.tolist()}")
    arr = arr.astype(np.int64, copy=False)
    bad = (arr < 0) | (arr >= N_ACTIONS)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"agent {i}: action {arr[i]} is outside 0..4 (0 stay, 1 up, 2 down, 3 left, 4 right)")
    return arr


def grid_from_text(text: str) -> np.ndarray:
    """A map from rows of '.' (free) and '#' (obstacle); spaces are ignored. For tests and docs:
    grid_from_text("..#\\n...") is the 2x3 map with an obstacle at (0, 2)."""
    rows = [line.replace(" ", "") for line in text.strip().splitlines()]
    for r, row in enumerate(rows):
        if len(row) != len(rows[0]):
            raise ValueError(f"grid text row {r} has {len(row)} cells, row 0 has {len(rows[0])}")
        bad = set(row) - {".", "#"}
        if bad:
            raise ValueError(f"grid text row {r}: unknown characters {sorted(bad)} (use '.' and '#')")
    return check_grid([[ch == "#" for ch in row] for row in rows])
