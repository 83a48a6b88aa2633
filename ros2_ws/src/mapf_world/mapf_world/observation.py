"""Per-agent observations (paper section III-B, heuristic channels as in DHC).

fov (6, l, l) float32 centred on the agent, channels in this order:
  0 static obstacles (cells outside the map count as obstacles)
  1 other agents (the agent's own cell is 0)
  2..5 heuristic up, down, left, right: 1 at a cell when the move in that direction from that cell
       reaches a cell strictly closer (4-connected BFS distance) to THIS agent's goal. Obstacles,
       cells that cannot reach the goal and cells outside the map are 0.
last_action (5,) float32 one-hot; position (2,) float32 raw (row, col).

Beyond the paper, optional (`headings`, MapfEnv(heading=True) appends it to fov as channel 6): the cell in
front of each other agent, that is its cell plus its last requested move (nothing for a stay, nor off the
map), 1 where at least one other agent faces that cell. A differential-drive robot turns towards the cell it
asks for, so a motion-capture ground station sees this without any robot telling another; a parked agent that
a neighbour keeps pushing into sees its own cell marked.

Beyond the paper, optional (`priorities`, MapfEnv(priority=True) appends it after the heading channel, if any):
1 at the cells of the other agents that come before this one in the instance's agent order (lower index). The
expert (ODrM*, agents taken in index order) settles ties over who gives way by that order; a fleet's ground
station knows each robot's number, so the order is observable without any robot telling another.

Beyond the paper, optional (`goal_directions`, MapfEnv(goal_dirs=True) appends them last): four channels, at the cell
of each other agent the bits of ITS heuristic channels there (which of up, down, left, right bring it closer to its
own goal). Who gives way in the expert's plan depends on where the others are going; the ground station assigns
every goal, so it can show each robot which way its neighbours' goals lie without any robot telling another.

Everything that depends only on the map and the goals is precomputed once, padded by l // 2, so a
step only gathers windows: row r, col c of the map is row r + l//2, col c + l//2 of the padded
arrays, and the window of an agent at (r, c) starts at padded (r, c).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from mapf_world.grid import DELTAS, N_ACTIONS, STAY, check_actions, check_cells, check_grid
from mapf_world.heuristics import distance_maps

N_CHANNELS = 6


@dataclass(frozen=True)
class ExtraChannels:
    """Which of the optional fov channels (all beyond the paper; module docstring) follow the paper's six, in this
    order: heading (1 channel; with heading_refused it marks only refused moves), priority (1), goal_dirs (4).
    MapfEnv builds them for training; the world node builds them for the robots (the ground station sees every
    robot, so no robot tells another anything); AgentObservation names them (`names`)."""
    heading: bool = False
    heading_refused: bool = False
    priority: bool = False
    goal_dirs: bool = False

    # name -> channels it takes; the names are what AgentObservation.extra_channels carries
    WIDTHS = {"heading": 1, "heading_refused": 1, "priority": 1, "goal_dirs": 4}

    def __post_init__(self):
        for name in ("heading", "heading_refused", "priority", "goal_dirs"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"ExtraChannels.{name} must be a bool, got {getattr(self, name)!r}")
        if self.heading_refused and not self.heading:
            raise ValueError("heading_refused=True needs heading=True (it says what the heading channel marks)")

    @property
    def names(self) -> tuple:
        """The optional channels present, in fov order, e.g. ('heading', 'priority', 'goal_dirs')."""
        return ((("heading_refused" if self.heading_refused else "heading",) if self.heading else ())
                + (("priority",) if self.priority else ()) + (("goal_dirs",) if self.goal_dirs else ()))

    @property
    def count(self) -> int:
        """Channels they add to the paper's six."""
        return sum(self.WIDTHS[n] for n in self.names)

    @classmethod
    def from_names(cls, names) -> "ExtraChannels":
        """The inverse of `names`; ValueError naming an unknown, repeated or misplaced name."""
        names = tuple(str(n) for n in names)
        unknown = [n for n in names if n not in cls.WIDTHS]
        if unknown:
            raise ValueError(f"unknown extra channels {unknown}; known: {sorted(cls.WIDTHS)}")
        out = cls(heading="heading" in names or "heading_refused" in names, heading_refused="heading_refused" in names,
                  priority="priority" in names, goal_dirs="goal_dirs" in names)
        if out.names != names:
            raise ValueError(f"extra channels {list(names)} are not a valid set in fov order; expected a subset of "
                             f"['heading' or 'heading_refused', 'priority', 'goal_dirs'] in that order")
        return out


def extra_fov(builder: "ObservationBuilder", extra: ExtraChannels, positions, requested, refused) -> np.ndarray:
    """(N, extra.count, l, l) float32: the optional channels of every agent, to append to the paper's six.
    `requested`: each agent's last requested action (0 before the first step and for an agent that sent none);
    `refused`: (N,) bool, whether that request was refused by the grid rules (read only with heading_refused)."""
    parts = []
    if extra.heading:
        req = check_actions(requested, builder.n_agents)
        if extra.heading_refused:
            refused = np.asarray(refused, dtype=bool)
            if refused.shape != (builder.n_agents,):
                raise ValueError(f"refused must have shape ({builder.n_agents},), got {refused.shape}")
            req = np.where(refused, req, STAY)
        parts.append(builder.headings(positions, req)[:, None])
    if extra.priority:
        parts.append(builder.priorities(positions)[:, None])
    if extra.goal_dirs:
        parts.append(builder.goal_directions(positions))
    size = builder.fov_size
    return np.concatenate(parts, axis=1) if parts else np.zeros((builder.n_agents, 0, size, size), np.float32)


def heuristic_bits(grid: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(N, 4, H, W) uint8: bit a is 1 where the move UP/DOWN/LEFT/RIGHT (a+1) gets strictly closer."""
    n, h, w = dist.shape
    bits = np.zeros((n, 4, h, w), dtype=np.uint8)
    free = grid == 0
    for a in range(4):
        dr, dc = DELTAS[a + 1]
        # Source cells (rows/cols that have a neighbour on the map in this direction) and neighbours.
        src = (slice(max(0, -dr), h - max(0, dr)), slice(max(0, -dc), w - max(0, dc)))
        dst = (slice(max(0, dr), h + min(0, dr)), slice(max(0, dc), w + min(0, dc)))
        closer = dist[(slice(None),) + dst] < dist[(slice(None),) + src]
        bits[(slice(None), a) + src] = closer & free[src]
    return bits


def check_fov_size(fov_size) -> int:
    """The field of view is centred on the agent, so l must be odd; l >= 3 to see any neighbour."""
    if isinstance(fov_size, bool) or not isinstance(fov_size, (int, np.integer)) or fov_size < 3 or fov_size % 2 == 0:
        raise ValueError(f"fov_size must be an odd integer >= 3, got {fov_size!r}")
    return int(fov_size)


class ObservationBuilder:
    """Builds the observations of all agents of one instance (fixed map and goals)."""

    def __init__(self, grid, goals, fov_size: int = 9, dist: np.ndarray | None = None):
        self.fov_size = check_fov_size(fov_size)
        self.grid = check_grid(grid)
        self.goals = check_cells(self.grid, goals, what="goals")
        self.n_agents = self.goals.shape[0]
        h, w = self.grid.shape
        if dist is None:
            dist = distance_maps(self.grid, self.goals)
        dist = np.asarray(dist)
        if dist.shape != (self.n_agents, h, w):
            raise ValueError(f"dist must have shape {(self.n_agents, h, w)}, got {dist.shape}")
        r = self.fov_size // 2
        self._radius = r
        self._obstacles = np.pad(self.grid, r, constant_values=1).astype(np.float32)
        self._heuristic = np.pad(heuristic_bits(self.grid, dist), ((0, 0), (0, 0), (r, r), (r, r))).astype(
            np.float32
        )
        # Scratch map of agent cells: marked and cleared again inside each build (one builder per thread).
        self._agents = np.zeros_like(self._obstacles)
        self._rows = np.arange(self.n_agents)
        self._view_windows()

    def _view_windows(self) -> None:
        """Windows as strided views of the padded maps: [row, col] of these is the l x l window of an agent at
        (row, col). A view must look at this builder's own maps: the agent windows see what each build marks."""
        win = (self.fov_size, self.fov_size)
        self._obstacle_windows = sliding_window_view(self._obstacles, win)
        self._heuristic_windows = sliding_window_view(self._heuristic, win, axis=(2, 3))
        self._agent_windows = sliding_window_view(self._agents, win)

    def __deepcopy__(self, memo):
        """The maps copied and the windows made anew over the copies. numpy deep-copies a strided view as a new,
        frozen array: a plain deep copy's agent windows never saw its marks, and it showed no other agent."""
        new = object.__new__(type(self))
        memo[id(self)] = new
        for name, value in self.__dict__.items():
            if not name.endswith("_windows"):
                new.__dict__[name] = copy.deepcopy(value, memo)
        new._view_windows()
        return new

    def _check_positions(self, positions) -> np.ndarray:
        pos = np.asarray(positions)
        if pos.shape != (self.n_agents, 2):
            raise ValueError(f"positions must have shape {(self.n_agents, 2)}, got {pos.shape}")
        if not np.issubdtype(pos.dtype, np.integer) and not np.all(pos == np.round(pos)):
            raise ValueError(f"positions must be integer cells, got {pos.tolist()}")
        pos = pos.astype(np.int64, copy=False)
        h, w = self.grid.shape
        if pos.min() < 0 or pos[:, 0].max() >= h or pos[:, 1].max() >= w:
            bad = int(np.flatnonzero((pos < 0).any(1) | (pos[:, 0] >= h) | (pos[:, 1] >= w))[0])
            raise ValueError(f"agent {bad}: position {pos[bad].tolist()} is off the {h}x{w} map")
        return pos

    def _mark_agents(self, pos: np.ndarray) -> None:
        r = self._radius
        self._agents[r + pos[:, 0], r + pos[:, 1]] = 1.0

    def _unmark_agents(self, pos: np.ndarray) -> None:
        r = self._radius
        self._agents[r + pos[:, 0], r + pos[:, 1]] = 0.0

    def build(self, positions, last_actions) -> dict:
        """Observations of all agents: fov (N, 6, l, l), last_action (N, 5), position (N, 2)."""
        pos = self._check_positions(positions)
        acts = check_actions(last_actions, self.n_agents)
        rr, cc = pos[:, 0], pos[:, 1]
        n, size, r = self.n_agents, self.fov_size, self._radius
        fov = np.empty((n, N_CHANNELS, size, size), dtype=np.float32)
        fov[:, 0] = self._obstacle_windows[rr, cc]
        self._mark_agents(pos)
        fov[:, 1] = self._agent_windows[rr, cc]
        self._unmark_agents(pos)
        fov[:, 1, r, r] = 0.0
        fov[:, 2:] = self._heuristic_windows[self._rows, :, rr, cc]
        one_hot = np.zeros((n, N_ACTIONS), dtype=np.float32)
        one_hot[self._rows, acts] = 1.0
        return {"fov": fov, "last_action": one_hot, "position": pos.astype(np.float32)}

    def headings(self, positions, requested) -> np.ndarray:
        """(N, l, l) float32: in each agent's window, 1 at the cells that other agents face (their cell plus
        their last requested move; a stay faces nothing). The agent's own facing cell is not marked."""
        pos = self._check_positions(positions)
        acts = check_actions(requested, self.n_agents)
        r = self._radius
        counts = np.zeros_like(self._obstacles)  # padded map
        target = pos + DELTAS[acts]
        movers = np.flatnonzero(acts != STAY)
        h, w = self.grid.shape
        on_map = movers[(target[movers] >= 0).all(1) & (target[movers, 0] < h) & (target[movers, 1] < w)]
        np.add.at(counts, (r + target[on_map, 0], r + target[on_map, 1]), 1.0)  # a cell off the map is not marked
        out = sliding_window_view(counts, (self.fov_size, self.fov_size))[pos[:, 0], pos[:, 1]].copy()
        out[on_map, r + DELTAS[acts[on_map], 0], r + DELTAS[acts[on_map], 1]] -= 1.0  # not one's own
        return np.minimum(out, 1.0)

    def priorities(self, positions) -> np.ndarray:
        """(N, l, l) float32: in each agent's window, 1 at the cells of the agents with a lower index (ahead of it in
        the instance's order); its own cell and the cells of agents behind it are 0."""
        pos = self._check_positions(positions)
        r = self._radius
        ids = np.zeros(self._obstacles.shape, dtype=np.int64)  # padded map of agent index + 1 (0: no agent)
        ids[r + pos[:, 0], r + pos[:, 1]] = self._rows + 1
        windows = sliding_window_view(ids, (self.fov_size, self.fov_size))[pos[:, 0], pos[:, 1]]  # (N, l, l)
        return ((windows > 0) & (windows <= self._rows[:, None, None])).astype(np.float32)

    def goal_directions(self, positions) -> np.ndarray:
        """(N, 4, l, l) float32: in each agent's window, at the cell of every other agent j the four heuristic bits
        of agent j at that cell (up, down, left, right: the moves that bring j closer to its goal); 0 elsewhere,
        and at the agent's own cell."""
        pos = self._check_positions(positions)
        r = self._radius
        bits = np.zeros((4,) + self._obstacles.shape, dtype=np.float32)  # padded maps
        bits[:, r + pos[:, 0], r + pos[:, 1]] = self._heuristic[self._rows, :, r + pos[:, 0], r + pos[:, 1]].T
        out = sliding_window_view(bits, (self.fov_size, self.fov_size), axis=(1, 2))[:, pos[:, 0], pos[:, 1]]
        out = np.ascontiguousarray(out.transpose(1, 0, 2, 3))  # (N, 4, l, l)
        out[:, :, r, r] = 0.0  # not one's own (its own bits are channels 2-5)
        return out

    def build_one(self, i: int, positions, last_action) -> dict:
        """Observation of agent i alone (no batch dimension); positions are all agents' cells."""
        if not 0 <= int(i) < self.n_agents:
            raise ValueError(f"agent index {i} is outside 0..{self.n_agents - 1}")
        i = int(i)
        pos = self._check_positions(positions)
        act = int(check_actions(np.atleast_1d(last_action), 1)[0])
        row, col = int(pos[i, 0]), int(pos[i, 1])
        size, r = self.fov_size, self._radius
        fov = np.empty((N_CHANNELS, size, size), dtype=np.float32)
        fov[0] = self._obstacle_windows[row, col]
        self._mark_agents(pos)
        fov[1] = self._agent_windows[row, col]
        self._unmark_agents(pos)
        fov[1, r, r] = 0.0
        fov[2:] = self._heuristic_windows[i, :, row, col]
        one_hot = np.zeros(N_ACTIONS, dtype=np.float32)
        one_hot[act] = 1.0
        return {"fov": fov, "last_action": one_hot, "position": pos[i].astype(np.float32)}
