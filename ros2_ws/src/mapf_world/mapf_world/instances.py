"""Instances: the seeded DHC-style generator, the benchmark `.npz` format and MovingAI files.

Benchmark `.npz` (../shared/benchmarks/dhc_40x40_d0.3/README.md): maps (K, H, W) uint8 1 = obstacle,
starts and goals (K, N, 2) int16 as (row, col); loaded with allow_pickle=False.
MovingAI (movingai.com/benchmarks): `.map` = "type octile / height H / width W / map" then H rows;
`.scen` = "version 1" then rows "bucket map width height start_x start_y goal_x goal_y optimal"
with x = column and y = row (converted to (row, col) here).
Every loader validates everything and names file, line / case and agent in its errors.
"""
from __future__ import annotations

import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapf_world.grid import check_cells, check_grid
from mapf_world.heuristics import connected_components

MOVINGAI_FREE = frozenset(".GS")
MOVINGAI_OBSTACLE = frozenset("@OTW")


def check_instance(grid, starts, goals) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Checked (grid, starts, goals): cells on the map, free, distinct per set, equal counts, and
    every goal in its start's connected component. ValueError naming the agent otherwise."""
    grid = check_grid(grid)
    starts = check_cells(grid, starts, what="starts")
    goals = check_cells(grid, goals, what="goals")
    if starts.shape != goals.shape:
        raise ValueError(f"{len(starts)} starts but {len(goals)} goals")
    labels = connected_components(grid)
    bad = labels[starts[:, 0], starts[:, 1]] != labels[goals[:, 0], goals[:, 1]]
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"agent {i}: goal {goals[i].tolist()} is unreachable from start {starts[i].tolist()}")
    return grid, starts, goals


@dataclass
class Instance:
    """One MAPF case. grid (H, W) uint8 1 = obstacle; starts, goals (N, 2) int64 (row, col)."""

    grid: np.ndarray
    starts: np.ndarray
    goals: np.ndarray
    name: str = ""

    def __post_init__(self):
        self.grid, self.starts, self.goals = check_instance(self.grid, self.starts, self.goals)

    @property
    def n_agents(self) -> int:
        return int(self.starts.shape[0])


def _rng(rng_or_seed) -> np.random.Generator:
    if isinstance(rng_or_seed, np.random.Generator):
        return rng_or_seed
    if isinstance(rng_or_seed, (int, np.integer)) and not isinstance(rng_or_seed, bool):
        return np.random.default_rng(int(rng_or_seed))
    raise ValueError(f"expected an int seed or a numpy Generator, got {rng_or_seed!r}")


def generate_instance(rng_or_seed, size: int = 40, density: float = 0.3, n_agents: int = 4,
                      height: int | None = None, max_tries: int = 100) -> Instance:
    """A random case in the DHC manner.

    Each cell is an obstacle with probability `density`. Agents are placed one after another: a
    connected component is drawn with probability proportional to its number of unused cells
    (among components with at least two), then the start and the goal are two distinct unused cells
    of it, so every goal is reachable and all 2N cells are distinct. A map without room for all
    agents is redrawn (at most `max_tries` times). `size` is the width; `height` defaults to it.
    """
    rng = _rng(rng_or_seed)
    height = size if height is None else height
    for value, what in ((size, "size"), (height, "height"), (n_agents, "n_agents"), (max_tries, "max_tries")):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{what} must be a positive integer, got {value!r}")
    if not 0.0 <= float(density) < 1.0:
        raise ValueError(f"density must be in [0, 1), got {density!r}")
    if 2 * n_agents > size * height:
        raise ValueError(f"{n_agents} agents need {2 * n_agents} cells; the {height}x{size} map has {size * height}")
    for _ in range(max_tries):
        grid = (rng.random((height, size)) < density).astype(np.uint8)
        placed = _place_agents(rng, grid, n_agents)
        if placed is not None:
            return Instance(grid, placed[0], placed[1])
    raise ValueError(f"no {height}x{size} map at density {density} fitted {n_agents} agents in {max_tries} tries")


def _place_agents(rng: np.random.Generator, grid: np.ndarray, n_agents: int):
    labels = connected_components(grid).reshape(-1)
    free = np.flatnonzero(labels >= 0)
    order = np.argsort(labels[free], kind="stable")
    _, starts_at = np.unique(labels[free][order], return_index=True)
    # pools[k] = unused flat cells of component k, shuffled once; popping from the end is uniform.
    pools = [list(rng.permutation(part)) for part in np.split(free[order], starts_at[1:])]
    w = grid.shape[1]
    cells = np.empty((2, n_agents, 2), dtype=np.int64)
    for i in range(n_agents):
        sizes = np.array([len(p) if len(p) >= 2 else 0 for p in pools], dtype=float)
        if sizes.sum() == 0:
            return None
        k = rng.choice(len(pools), p=sizes / sizes.sum())
        for j in range(2):
            flat = pools[k].pop()
            cells[j, i] = divmod(int(flat), w)
    return cells[0], cells[1]


# --- benchmark .npz ---------------------------------------------------------------------------
def load_npz(path) -> list[Instance]:
    """Every case of a benchmark `.npz` as Instances named '<file stem>#<case>'."""
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable .npz file ({exc})") from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise ValueError(f"{path}: expected an .npz archive of maps, starts, goals; got a single array")
    with data:
        missing = {"maps", "starts", "goals"} - set(data.files)
        if missing:
            raise ValueError(f"{path}: missing arrays {sorted(missing)} (has {sorted(data.files)})")
        try:
            maps, starts, goals = data["maps"], data["starts"], data["goals"]
        except (zipfile.BadZipFile, EOFError, OSError, ValueError) as exc:
            raise ValueError(f"{path}: unreadable array ({exc})") from None
    if maps.ndim != 3:
        raise ValueError(f"{path}: maps must be (K, H, W), got shape {maps.shape}")
    for name, arr in (("starts", starts), ("goals", goals)):
        if arr.ndim != 3 or arr.shape[2] != 2 or arr.shape[0] != maps.shape[0]:
            raise ValueError(f"{path}: {name} must be ({maps.shape[0]}, N, 2), got shape {arr.shape}")
        if not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"{path}: {name} must be integers, got dtype {arr.dtype}")
    if starts.shape != goals.shape:
        raise ValueError(f"{path}: starts {starts.shape} and goals {goals.shape} differ in shape")
    out = []
    for k in range(maps.shape[0]):
        try:
            out.append(Instance(maps[k], starts[k], goals[k], name=f"{path.stem}#{k}"))
        except ValueError as exc:
            raise ValueError(f"{path}: case {k}: {exc}") from None
    return out


def save_npz(path, instances) -> None:
    """Write instances (same map shape and agent count) in the benchmark format."""
    instances = list(instances)
    if not instances:
        raise ValueError(f"{path}: no instances to save")
    shape, n = instances[0].grid.shape, instances[0].n_agents
    for k, inst in enumerate(instances):
        if inst.grid.shape != shape or inst.n_agents != n:
            raise ValueError(
                f"{path}: case {k} has a {inst.grid.shape} map and {inst.n_agents} agents; "
                f"case 0 has {shape} and {n} (one file holds one shape and one team size)"
            )
    if max(shape) > np.iinfo(np.int16).max:
        raise ValueError(f"{path}: a {shape} map does not fit the int16 cells of the format")
    np.savez_compressed(
        path,
        maps=np.stack([inst.grid for inst in instances]).astype(np.uint8),
        starts=np.stack([inst.starts for inst in instances]).astype(np.int16),
        goals=np.stack([inst.goals for inst in instances]).astype(np.int16),
    )


# --- MovingAI ---------------------------------------------------------------------------------
def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="ascii").splitlines()
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not an ASCII text file ({exc})") from None


def load_movingai_map(path) -> np.ndarray:
    """(H, W) uint8 grid of a MovingAI `.map`: '.', 'G', 'S' free; '@', 'O', 'T', 'W' obstacles."""
    path = Path(path)
    lines = _read_lines(path)
    header = {}
    for lineno, key in enumerate(("type", "height", "width"), start=1):
        if len(lines) < lineno:
            raise ValueError(f"{path}: line {lineno}: file ends before the '{key}' header line")
        parts = lines[lineno - 1].split()
        if len(parts) != 2 or parts[0] != key:
            raise ValueError(f"{path}: line {lineno}: expected '{key} <value>', got {lines[lineno - 1]!r}")
        header[key] = parts[1]
    if header["type"] != "octile":
        raise ValueError(f"{path}: line 1: unsupported map type {header['type']!r} (expected 'octile')")
    dims = {}
    for lineno, key in ((2, "height"), (3, "width")):
        if not header[key].isdigit() or int(header[key]) < 1:
            raise ValueError(f"{path}: line {lineno}: {key} must be a positive integer, got {header[key]!r}")
        dims[key] = int(header[key])
    if len(lines) < 4 or lines[3].strip() != "map":
        raise ValueError(f"{path}: line 4: expected 'map'")
    h, w = dims["height"], dims["width"]
    rows = lines[4:]
    while rows and not rows[-1].strip():
        rows.pop()
    if len(rows) != h:
        raise ValueError(f"{path}: line {4 + len(rows) + (len(rows) < h)}: expected {h} map rows, found {len(rows)}")
    grid = np.zeros((h, w), dtype=np.uint8)
    for r, row in enumerate(rows):
        lineno = 5 + r
        row = row.rstrip("\r")
        if len(row) != w:
            raise ValueError(f"{path}: line {lineno}: expected {w} characters, got {len(row)}")
        for c, ch in enumerate(row):
            if ch in MOVINGAI_OBSTACLE:
                grid[r, c] = 1
            elif ch not in MOVINGAI_FREE:
                raise ValueError(f"{path}: line {lineno}, column {c + 1}: unknown map character {ch!r}")
    return grid


def load_movingai_scen(path, n_agents: int, grid: np.ndarray | None = None) -> Instance:
    """The first `n_agents` agents of a MovingAI `version 1` scenario.

    Without `grid`, the map named in the scenario's first agent row is loaded from the scenario's
    directory. Width and height in each row must match the map.
    """
    path = Path(path)
    if isinstance(n_agents, bool) or not isinstance(n_agents, (int, np.integer)) or n_agents < 1:
        raise ValueError(f"n_agents must be a positive integer, got {n_agents!r}")
    lines = _read_lines(path)
    if not lines or lines[0].split() not in (["version", "1"], ["version", "1.0"]):
        raise ValueError(f"{path}: line 1: expected 'version 1', got {lines[0] if lines else ''!r}")
    rows = [(k + 2, line) for k, line in enumerate(lines[1:]) if line.strip()]
    if len(rows) < n_agents:
        raise ValueError(f"{path}: has {len(rows)} agents, {n_agents} requested")
    starts, goals = [], []
    for lineno, line in rows[:n_agents]:
        parts = [p.strip() for p in (line.split("\t") if "\t" in line else line.split())]
        if len(parts) != 9:
            raise ValueError(f"{path}: line {lineno}: expected 9 columns, got {len(parts)}")
        try:
            width, height, sx, sy, gx, gy = (int(v) for v in parts[2:8])
            float(parts[8])
        except ValueError:
            raise ValueError(f"{path}: line {lineno}: sizes and coordinates must be integers: {line!r}") from None
        if grid is None:
            map_path = path.parent / parts[1]
            if not map_path.is_file():
                raise ValueError(f"{path}: line {lineno}: map file {map_path} not found (pass grid=)")
            grid = load_movingai_map(map_path)
        grid = check_grid(grid)
        if (height, width) != grid.shape:
            raise ValueError(f"{path}: line {lineno}: the scenario's map is {width} wide, {height} high; "
                             f"the grid is {grid.shape[1]} wide, {grid.shape[0]} high")
        starts.append((sy, sx))  # x = column, y = row
        goals.append((gy, gx))
    try:
        return Instance(grid, np.array(starts), np.array(goals), name=f"{path.stem}[:{n_agents}]")
    except ValueError as exc:
        msg = str(exc)
        # Point at the scenario line of the agent the message names (the later one of a duplicate).
        m = re.search(r"agent (\d+)|agents \[([\d, ]+)\]", msg)
        if m:
            i = int(m.group(1)) if m.group(1) else int(m.group(2).split(",")[-1])
            raise ValueError(f"{path}: line {rows[i][0]}: {msg}") from None
        raise ValueError(f"{path}: {msg}") from None
