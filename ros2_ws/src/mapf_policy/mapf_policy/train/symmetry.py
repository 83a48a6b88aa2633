"""The eight symmetries of the square grid (the dihedral group D4), for data augmentation in training.

Beyond the paper (dqn_hscl Args.augment). Turning or mirroring a whole instance (map, starts, goals) changes
nothing that matters: the step rules break ties by agent index, never by direction (rules.py), the rewards
do not look at directions, and the shortest paths turn with the map. So a transition seen in one orientation
is a valid transition in all eight, and its expert label, turned, is a label of the turned state. The network
sees each training row in a random one of the eight orientations: eight times the distinct rows for the
same episodes. (The issue-20 capacity check found held-out agreement limited by distinct rows, about half a
point per doubling, not by the network's capacity.)

A symmetry g = (transpose, flip_rows, flip_cols) acts on (row, col) arrays in that order: first swap rows and
columns, then reverse the rows, then reverse the columns. The eight combinations are the whole group; index 0
is the identity. Actions are grid.DELTAS's: 0 stay, 1 up, 2 down, 3 left, 4 right. What turns with g:
- every fov channel as a picture (a centred window turns about its centre);
- the channels that hold one bit per direction (the four heuristic channels, and the four goal-direction
  channels when the network reads them) are also permuted as the actions are;
- actions, expert labels and the one-hot last action, by `action_map`;
- the raw (row, col) position, which needs the map's (height, width) (rows keep it as "map_shape").
"""
from __future__ import annotations

import itertools

import numpy as np
import torch

SYMMETRIES = tuple(itertools.product((False, True), repeat=3))
"""The eight symmetries (transpose, flip_rows, flip_cols); SYMMETRIES[0] is the identity."""

_TRANSPOSE = np.array([0, 3, 4, 1, 2])  # up <-> left, down <-> right
_FLIP_ROWS = np.array([0, 2, 1, 3, 4])  # up <-> down
_FLIP_COLS = np.array([0, 1, 2, 4, 3])  # left <-> right


def action_map(g: tuple) -> np.ndarray:
    """(5,) int: the action under symmetry g of each action 0..4."""
    transpose, flip_rows, flip_cols = g
    perm = np.arange(5)
    if transpose:
        perm = _TRANSPOSE[perm]
    if flip_rows:
        perm = _FLIP_ROWS[perm]
    if flip_cols:
        perm = _FLIP_COLS[perm]
    return perm


def transform_plane(a: np.ndarray, g: tuple) -> np.ndarray:
    """The picture(s) a (..., H, W) under symmetry g (a view where numpy allows)."""
    transpose, flip_rows, flip_cols = g
    if transpose:
        a = np.swapaxes(a, -1, -2)
    if flip_rows:
        a = a[..., ::-1, :]
    if flip_cols:
        a = a[..., :, ::-1]
    return a


def transform_cells(cells: np.ndarray, shape: tuple, g: tuple) -> tuple[np.ndarray, tuple]:
    """Cells (..., 2) (row, col) of a map of `shape` (H, W) under symmetry g: (cells, the turned map's shape)."""
    transpose, flip_rows, flip_cols = g
    cells = np.asarray(cells)
    r, c = cells[..., 0], cells[..., 1]
    h, w = shape
    if transpose:
        r, c, h, w = c, r, w, h
    if flip_rows:
        r = h - 1 - r
    if flip_cols:
        c = w - 1 - c
    return np.stack([r, c], axis=-1), (h, w)


def channel_sources(channels: int, direction_blocks: tuple, g: tuple) -> np.ndarray:
    """(channels,) int: which channel of the original fov each channel of the turned fov reads. A direction block
    starting at s holds the bits for up, down, left, right at s..s+3; the bit for direction d becomes the bit for d
    turned."""
    perm = action_map(g)
    src = np.arange(channels)
    for s in direction_blocks:
        if s < 0 or s + 4 > channels:
            raise ValueError(f"direction block at channel {s} does not fit in {channels} channels")
        for d in range(4):
            src[s + perm[d + 1] - 1] = s + d
    return src


def direction_blocks(cfg) -> tuple:
    """The first channels of the fov's direction blocks for network config `cfg` (NetworkConfig): the heuristic
    channels 2..5 (observation.py), and the goal-direction channels, last, when the network reads them."""
    return (2,) + ((cfg.fov_channels - 4,) if cfg.goal_dirs else ())


class Augmenter:
    """Turns a training batch (dqn_hscl.Replay rows as tensors) by one symmetry per row.

    Precomputes, for the eight symmetries, where each turned fov cell and channel comes from and how actions map,
    so one batch is a few gathers."""

    def __init__(self, fov_size: int, channels: int, blocks: tuple):
        self.fov_size, self.channels = fov_size, channels
        cells = np.arange(fov_size * fov_size).reshape(fov_size, fov_size)
        self.cell_src = torch.from_numpy(np.stack([transform_plane(cells, g).reshape(-1) for g in SYMMETRIES]))
        self.channel_src = torch.from_numpy(np.stack([channel_sources(channels, blocks, g) for g in SYMMETRIES]))
        self.action = torch.from_numpy(np.stack([action_map(g) for g in SYMMETRIES]))
        self.action_src = torch.argsort(self.action, dim=1)  # new one-hot column j reads old column action_src[j]
        self.flags = torch.tensor(SYMMETRIES, dtype=torch.bool)  # (8, 3)

    def fov(self, x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        b, c, l, _ = x.shape
        if c != self.channels or l != self.fov_size:
            raise ValueError(f"fov of shape {tuple(x.shape[1:])}, the augmenter was built for "
                             f"{(self.channels, self.fov_size, self.fov_size)}")
        flat = x.reshape(b, c, l * l)
        rows = torch.arange(b)[:, None, None]
        out = flat[rows, self.channel_src[g][:, :, None], self.cell_src[g][:, None, :]]
        return out.reshape(b, c, l, l).contiguous(memory_format=torch.channels_last)

    def position(self, pos: torch.Tensor, shape: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """pos (B, 2) float (row, col); shape (B, 2) the rows' map (H, W)."""
        if bool((shape <= 0).any()):
            raise ValueError("augmenting a position needs its map's shape; rows without one (map_shape 0) cannot "
                             "be turned (episode_rows(map_shape=...))")
        t, fr, fc = (self.flags[g, k] for k in range(3))
        r = torch.where(t, pos[:, 1], pos[:, 0])
        c = torch.where(t, pos[:, 0], pos[:, 1])
        h = torch.where(t, shape[:, 1], shape[:, 0]).to(pos.dtype)
        w = torch.where(t, shape[:, 0], shape[:, 1]).to(pos.dtype)
        r = torch.where(fr, h - 1 - r, r)
        c = torch.where(fc, w - 1 - c, c)
        return torch.stack([r, c], dim=1)

    def __call__(self, batch: dict, g: torch.Tensor) -> dict:
        """The batch with row i turned by SYMMETRIES[g[i]]; keys that do not turn are passed on as they are."""
        out = dict(batch)
        for pre in ("", "next_"):
            out[pre + "fov"] = self.fov(batch[pre + "fov"], g)
            out[pre + "last_action"] = batch[pre + "last_action"].gather(1, self.action_src[g])
            out[pre + "position"] = self.position(batch[pre + "position"], batch["map_shape"], g)
        out["action"] = self.action[g, batch["action"]]
        expert = batch["expert"]
        out["expert"] = torch.where(expert >= 0, self.action[g, expert.clamp(min=0)], expert)
        return out
