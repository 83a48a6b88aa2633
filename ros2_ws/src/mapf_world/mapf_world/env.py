"""MapfEnv: the DHC grid world with a gymnasium-style reset/step (no gymnasium dependency).

Rewards per agent and step (DHC, paper section III-D): move -0.075; stay on own goal 0; stay off
goal -0.075; a failed move -0.5 instead. When all agents stand on their goals at the same step the
episode ends (terminated) and the reward of that step is set to 3 for every agent, as in DHC and
the paper ("the reward value is set to 3"). An episode has at most `max_steps` steps; reaching it
without success ends it with truncated=True.

The observation's last action (`last_action`): "requested" (the action the agent asked for, also when the
grid rules refused the move; every model before the second design) or "executed" (what the agent did:
stay when its move was refused). The paper says "the action performed by the agent at the last moment".
With "requested", an agent whose move was refused often sees exactly the observation it saw before.

The observation also counts, per agent, the steps it has stood on the same cell (`still`: 0 at the start
and after a move, +1 for each step that leaves it where it was, refused moves included). Only networks
built with NetworkConfig.still_bins > 0 read it, or one of two other counts: `refused_run`, its consecutive
refused moves (0 after a move or a stay), and `contact_run`, the consecutive steps in which it stood still
with the same non-empty set of cells next to it (4-neighbourhood) held by agents (0 when it moved, when that
set changed or is empty). An agent can count all three from its own requests, positions and fields of view.
A fourth count, `revisits` (beyond the paper, issue 20's thirty-third session), is how many of the agent's
last REVISIT_WINDOW positions before the current step equal its current cell: 0 on a first visit, rising in a
loop of any period up to the window (waiting on one cell counts too). A network that reads it can tell a loop
from a first visit, which a memoryless network cannot (its observations repeat with the joint state). With
`revisit_cap` > 0 the joint state (joint_state) includes the counts capped there, as such a network sees them.

`heading=True` (beyond the paper; off everywhere by default) appends a seventh fov channel: the cells the
other agents face, each one's cell plus its last requested move (ObservationBuilder.headings); with
`heading_refused=True` as well, only the moves that were refused (the cells another agent tried and failed to enter).
`priority=True` (beyond the paper; off by default) appends one more channel after those: the other agents ahead of
this one in the instance's agent order (ObservationBuilder.priorities).
`goal_dirs=True` (beyond the paper; off by default) appends four channels last: which way each other agent's goal
lies from its cell (ObservationBuilder.goal_directions).
"""
from __future__ import annotations

import copy

import numpy as np

from mapf_world.grid import STAY, check_actions
from mapf_world.heuristics import UNREACHABLE, distance_maps
from mapf_world.instances import check_instance
from mapf_world.observation import ExtraChannels, ObservationBuilder, check_fov_size, extra_fov
from mapf_world.rules import resolve_moves

REWARD_MOVE = -0.075
REWARD_STAY_ON_GOAL = 0.0
REWARD_STAY_OFF_GOAL = -0.075
REWARD_FAILED_MOVE = -0.5
REWARD_FINISH = 3.0
LAST_ACTION_MODES = ("requested", "executed")
REVISIT_WINDOW = 16  # steps of each agent's own past positions that the revisits count looks back over


class MapfEnv:
    """One instance (map, starts, goals). Arrays follow docs/ARCHITECTURE.md: cells are (row, col)."""

    def __init__(self, grid, starts, goals, fov_size: int = 9, max_steps: int = 256, last_action: str = "requested",
                 heading: bool = False, heading_refused: bool = False, priority: bool = False,
                 goal_dirs: bool = False, revisit_cap: int = 0):
        # Cells on the map, free, distinct, goals reachable (cheap component labels; the BFS waits for reset()).
        self._grid, self._starts, self._goals = check_instance(grid, starts, goals)
        if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}")
        self.fov_size = check_fov_size(fov_size)
        self.max_steps = int(max_steps)
        if last_action not in LAST_ACTION_MODES:
            raise ValueError(f"last_action must be one of {LAST_ACTION_MODES}, got {last_action!r}")
        self.last_action_mode = last_action
        self.heading = bool(heading)
        self.heading_refused = bool(heading_refused)
        self.priority = bool(priority)
        self.goal_dirs = bool(goal_dirs)
        if isinstance(revisit_cap, bool) or not isinstance(revisit_cap, (int, np.integer)) or revisit_cap < 0:
            raise ValueError(f"revisit_cap must be an integer >= 0, got {revisit_cap!r}")
        self.revisit_cap = int(revisit_cap)
        # The optional channels, in fov order (ValueError for heading_refused without heading).
        self.extra = ExtraChannels(self.heading, self.heading_refused, self.priority, self.goal_dirs)
        self._dist: np.ndarray | None = None
        self._builder: ObservationBuilder | None = None
        self._positions = self._starts.copy()
        self._last_actions = np.zeros(len(self._starts), dtype=np.int64)
        self._requested = np.zeros(len(self._starts), dtype=np.int64)
        self._still = np.zeros(len(self._starts), dtype=np.int64)
        self._refused_run = np.zeros(len(self._starts), dtype=np.int64)
        self._contact_run = np.zeros(len(self._starts), dtype=np.int64)
        self._reset_trail()
        self._step = 0
        self._done = True  # until reset()

    def _reset_trail(self) -> None:
        # _trail[k % REVISIT_WINDOW] is every agent's position before step k + 1; (-1, -1) where no step was taken.
        self._trail = np.full((REVISIT_WINDOW, len(self._starts), 2), -1, dtype=self._starts.dtype)
        self._revisits = np.zeros(len(self._starts), dtype=np.int64)

    # The instance's fixed parts, built once and never written after: a copy of the env shares them.
    _SHARED = ("_grid", "_starts", "_goals", "_dist", "_builder")

    def __deepcopy__(self, memo):
        """A copy that plays on independently of this env: the per-step state is copied, the fixed parts (map,
        starts, goals, distance maps, observation builder) are shared. The rollout search (dqn_hscl.best_deviation)
        copies an episode for every candidate deviation, and a deep copy of the builder costs 4-12 ms at 16
        agents on 40x40 (before ObservationBuilder.__deepcopy__, it also showed the copy no other agent). The
        builder's scratch map is written and cleared within each build, so copies stepped one after another in one
        thread may share it."""
        new = object.__new__(type(self))
        memo[id(self)] = new
        for name, value in self.__dict__.items():
            new.__dict__[name] = value if name in self._SHARED else copy.deepcopy(value, memo)
        return new

    # --- read-only views of the state -----------------------------------------------------------
    @property
    def grid(self) -> np.ndarray:
        return self._grid

    @property
    def starts(self) -> np.ndarray:
        return self._starts.copy()

    @property
    def goals(self) -> np.ndarray:
        return self._goals.copy()

    @property
    def n_agents(self) -> int:
        return int(self._starts.shape[0])

    @property
    def positions(self) -> np.ndarray:
        return self._positions.copy()

    @property
    def last_actions(self) -> np.ndarray:
        return self._last_actions.copy()

    @property
    def step_count(self) -> int:
        return self._step

    @property
    def dist(self) -> np.ndarray:
        """(N, H, W) BFS distance maps to each agent's goal (computed once, on first use)."""
        if self._dist is None:
            self._dist = distance_maps(self._grid, self._goals)
            if np.any(self._dist[np.arange(self.n_agents), self._starts[:, 0], self._starts[:, 1]] >= UNREACHABLE):
                raise AssertionError("component check and BFS disagree on reachability")
        return self._dist

    @property
    def observation_builder(self) -> ObservationBuilder:
        if self._builder is None:
            self._builder = ObservationBuilder(self._grid, self._goals, self.fov_size, dist=self.dist)
        return self._builder

    def joint_state(self) -> bytes:
        """Everything the next observations are built from (positions, executed and requested last actions; the
        still counts aside; the revisits counts capped at revisit_cap when it is > 0), as a hashable key: a
        deterministic policy that reads no more than that and sees a joint state again loops for ever. With
        revisit_cap the key is a close reading, not an exact one: the next counts depend on the last REVISIT_WINDOW
        positions, which the key does not hold, so a repeat before the loop has filled the window may be followed
        by other counts (a greedy stretch then ends a few steps early; once a loop has gone round for REVISIT_WINDOW
        steps, its counts repeat with it, for ever)."""
        key = self._positions.tobytes() + self._last_actions.tobytes() + self._requested.tobytes()
        if self.revisit_cap:
            key += np.minimum(self._revisits, self.revisit_cap).tobytes()
        return key

    def on_goal(self) -> np.ndarray:
        return np.all(self._positions == self._goals, axis=1)

    def observe(self) -> dict:
        """fov, last_action, position (ObservationBuilder.build); still, refused_run, contact_run and revisits: (N,)
        counts (module docstring)."""
        obs = self.observation_builder.build(self._positions, self._last_actions)
        if self.extra.count:
            more = extra_fov(self.observation_builder, self.extra, self._positions, self._requested, self._refused_run > 0)
            obs["fov"] = np.concatenate([obs["fov"], more], axis=1)
        return obs | {
            "still": self._still.copy(), "refused_run": self._refused_run.copy(), "contact_run": self._contact_run.copy(),
            "revisits": self._revisits.copy()}

    # --- gymnasium-style API --------------------------------------------------------------------
    def reset(self) -> tuple[dict, dict]:
        """Back to the starts. The BFS runs on the first reset only (cached per instance)."""
        self._positions = self._starts.copy()
        self._last_actions = np.zeros(self.n_agents, dtype=np.int64)
        self._requested = np.zeros(self.n_agents, dtype=np.int64)
        self._still = np.zeros(self.n_agents, dtype=np.int64)
        self._refused_run = np.zeros(self.n_agents, dtype=np.int64)
        self._contact_run = np.zeros(self.n_agents, dtype=np.int64)
        self._reset_trail()
        self._step = 0
        on_goal = self.on_goal()
        # If every agent starts on its goal the case is solved in 0 steps: info["success"] is True
        # and the episode is already over (step() raises). Generated and benchmark cases never do this.
        success = bool(on_goal.all())
        self._done = success
        obs = self.observe()
        info = {"failed": np.zeros(self.n_agents, dtype=bool), "on_goal": on_goal, "step": 0, "success": success}
        return obs, info

    def step(self, actions):
        if self._done:
            raise ValueError("the episode has ended (or reset() was never called): call reset() first")
        acts = check_actions(actions, self.n_agents)
        stayed_on_goal = (acts == STAY) & self.on_goal()
        new_pos, failed = resolve_moves(self._grid, self._positions, acts)
        moved = np.any(new_pos != self._positions, axis=1)
        self._still = np.where(moved, 0, self._still + 1)
        self._refused_run = np.where(failed, self._refused_run + 1, 0)
        before, after = _contacts(self._positions), _contacts(new_pos)
        same = ~moved & np.all(before == after, axis=1) & after.any(axis=1)
        self._contact_run = np.where(same, self._contact_run + 1, 0)
        self._trail[self._step % REVISIT_WINDOW] = self._positions
        self._revisits = np.all(self._trail == new_pos[None], axis=2).sum(axis=0)
        self._positions = new_pos
        self._last_actions = np.where(failed, STAY, acts) if self.last_action_mode == "executed" else acts
        self._requested = acts.copy()
        self._step += 1
        rewards = np.full(self.n_agents, REWARD_MOVE, dtype=np.float32)
        rewards[acts == STAY] = REWARD_STAY_OFF_GOAL
        rewards[stayed_on_goal] = REWARD_STAY_ON_GOAL
        rewards[failed] = REWARD_FAILED_MOVE
        on_goal = self.on_goal()
        success = bool(on_goal.all())
        terminated = success
        truncated = (not success) and self._step >= self.max_steps
        if success:
            rewards[:] = REWARD_FINISH
        self._done = terminated or truncated
        info = {"failed": failed, "on_goal": on_goal, "step": self._step, "success": success}
        return self.observe(), rewards, terminated, truncated, info


def revisit_counts(history) -> np.ndarray:
    """(N,) the `revisits` counts of MapfEnv's observation from the positions of an episode so far: history[0] the
    starts, history[-1] the current cells ((T+1, N, 2), or a list of (N, 2)). The world node counts them so (its
    FleetCore keeps the positions of every step) for a robot whose network reads them."""
    h = np.asarray(history)
    if h.ndim != 3 or h.shape[0] < 1 or h.shape[2] != 2:
        raise ValueError(f"history must have shape (T+1, N, 2), got {h.shape}")
    return np.all(h[-1 - REVISIT_WINDOW:-1] == h[-1][None], axis=2).sum(axis=0).astype(np.int64)


def _contacts(positions: np.ndarray) -> np.ndarray:
    """(N, 4) bool: which of each agent's four neighbour cells (up, down, left, right) another agent holds."""
    offsets = np.array([[-1, 0], [1, 0], [0, -1], [0, 1]])
    around = positions[:, None, :] + offsets[None]  # (N, 4, 2)
    held = np.all(around[:, :, None, :] == positions[None, None, :, :], axis=3)  # (N, 4, N)
    return held.any(axis=2)
