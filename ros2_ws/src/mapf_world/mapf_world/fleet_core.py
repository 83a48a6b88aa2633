"""Step synchronisation of the ground station (world node), without ROS.

One grid step of the fleet:
  1. the world publishes every robot's observation for step t (phase COLLECTING);
  2. each robot's action for step t is offered here (`offer_action`); an action for another step
     or another robot is rejected (the robot may still answer correctly before the deadline), an
     action outside 0..4 is rejected and that robot stays;
  3. when every robot has answered or the action deadline passed (`close_step`), robots without a
     valid action stay (TIMEOUT, or REJECTED when they only sent rejected actions) and the grid
     rules (`mapf_world.rules.resolve_moves`) act as the safety interlock: a move they fail becomes
     stay (BLOCKED); the approved moves are returned (phase SETTLING);
  4. when every robot's pose has settled on its target cell (`settle`), the step is done: success
     when every robot stands on its goal, the step limit, or the next step.

Outcome codes equal mapf_msgs/msg/CellMove OUTCOME_*; state codes equal FleetStatus STATE_*.
Grid-to-world frame (docs/FLEET.md): x = col * cell_size, y = -row * cell_size.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np

from mapf_world.grid import ACTION_NAMES, N_ACTIONS, STAY, check_cells, check_grid

OUTCOME_OK, OUTCOME_BLOCKED, OUTCOME_TIMEOUT, OUTCOME_REJECTED = 0, 1, 2, 3
OUTCOME_NAMES = ("ok", "blocked", "timeout", "rejected")


class State(IntEnum):
    WAITING = 0
    RUNNING = 1
    SUCCESS = 2
    MAX_STEPS = 3
    ABORTED = 4


class Phase(IntEnum):
    IDLE = 0        # before the first step / between steps
    COLLECTING = 1  # observations out, waiting for actions
    SETTLING = 2    # moves out, waiting for poses to settle
    DONE = 3


class Deadline:
    """A time limit checked on the ticks of a periodic timer, that does not count a stall of its own process.

    When the limit passes while the process does not run (a gap between two ticks longer than `stall_s`:
    CPU starvation, a blocking call, SIGSTOP), the inputs that arrived in time are still queued, in the
    middleware or behind the tick (rclpy runs a wait's ready timers before its ready subscriptions). So the
    limit then moves to `grace_s` after that tick, once per limit; a process that is slow at every tick
    still enforces it. Times are time.monotonic() seconds.
    """

    def __init__(self, stall_s: float = 0.1, grace_s: float = 0.1):
        self.stall_s, self.grace_s = stall_s, grace_s
        self.at = math.inf
        self._extended = False
        self._last_tick = None

    def set(self, now: float, seconds: float) -> None:
        self.at = now + seconds
        self._extended = False

    def expired(self, now: float) -> bool:
        """Call on every tick, with the tick's time."""
        last, self._last_tick = self._last_tick, now
        if now < self.at:
            return False
        if not self._extended and last is not None and last < self.at and now - last > self.stall_s:
            self.at = now + self.grace_s
            self._extended = True
            return False
        return True


@dataclass(frozen=True)
class Verdict:
    """What happened to one offered action message."""
    accepted: bool
    final: bool          # True when this robot's action for the step is now fixed
    reason: str          # empty when accepted


@dataclass
class StepMoves:
    """The approved moves of one step, index i = robot i."""
    step: int
    requested: np.ndarray   # (N,) int64, 0 where no valid action arrived
    actions: np.ndarray     # (N,) int64 approved (stay unless OK)
    outcomes: np.ndarray    # (N,) int64 OUTCOME_*
    from_cells: np.ndarray  # (N, 2)
    to_cells: np.ndarray    # (N, 2)


def cell_to_xy(cell: Sequence[int], cell_size: float) -> Tuple[float, float]:
    return int(cell[1]) * cell_size, -int(cell[0]) * cell_size


def xy_to_cell(x: float, y: float, cell_size: float) -> Tuple[int, int]:
    return int(round(-y / cell_size)), int(round(x / cell_size))


def wrap_angle(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def pose_error(x: float, y: float, cell: Sequence[int], cell_size: float) -> float:
    """Distance in metres from (x, y) to the centre of cell."""
    cx, cy = cell_to_xy(cell, cell_size)
    return math.hypot(x - cx, y - cy)


def common_drive_start(yaws: Sequence[float], from_cells, to_cells, max_angular: float) -> float:
    """Seconds until every moving robot faces its target: the step's shared drive start.

    Robots that follow each other (allowed by the grid rules) then drive at the same time and keep
    their distance. Robots that stay do not count.
    """
    longest = 0.0
    for yaw, (r0, c0), (r1, c1) in zip(yaws, np.asarray(from_cells).tolist(), np.asarray(to_cells).tolist()):
        if (r0, c0) == (r1, c1):
            continue
        heading = math.atan2(-(r1 - r0), c1 - c0)
        longest = max(longest, abs(wrap_angle(heading - yaw)) / max_angular)
    return longest


class FleetCore:
    """The grid state of the fleet and the per-step protocol (pure; the node feeds it messages)."""

    def __init__(self, grid, starts, goals, max_steps: int,
                 resolve: Optional[Callable] = None, last_action: str = "requested"):
        self.grid = check_grid(grid)
        self.starts = check_cells(self.grid, starts, what="starts")
        self.goals = check_cells(self.grid, goals, what="goals")
        if self.starts.shape != self.goals.shape:
            raise ValueError(f"{len(self.starts)} starts but {len(self.goals)} goals")
        if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}")
        from mapf_world.env import LAST_ACTION_MODES
        if last_action not in LAST_ACTION_MODES:
            raise ValueError(f"last_action must be one of {LAST_ACTION_MODES}, got {last_action!r}")
        self.last_action_mode = last_action
        if resolve is None:
            from mapf_world.rules import resolve_moves as resolve
        self._resolve = resolve
        self.n = int(self.starts.shape[0])
        self.max_steps = int(max_steps)
        self.positions = self.starts.copy()
        self.last_actions = np.zeros(self.n, dtype=np.int64)
        self.step = 0
        self.phase = Phase.IDLE
        self.state = State.WAITING
        self.detail = "waiting for robots"
        self.failed_moves = 0
        self.timeouts = 0
        self.rejected = 0
        self.history: List[np.ndarray] = [self.positions.copy()]  # (T+1) x (N, 2)
        self.moves: List[StepMoves] = []
        self._requested: List[Optional[int]] = [None] * self.n
        self._final = np.zeros(self.n, dtype=bool)
        self._had_rejected = np.zeros(self.n, dtype=bool)
        self._pending: Optional[StepMoves] = None

    # --- queries ---------------------------------------------------------------------------------
    @property
    def on_goal(self) -> np.ndarray:
        return np.all(self.positions == self.goals, axis=1)

    @property
    def done(self) -> bool:
        return self.phase == Phase.DONE

    @property
    def pending(self) -> Optional[StepMoves]:
        return self._pending

    def waiting_for(self) -> List[int]:
        """Robots whose action for the current step is not fixed yet."""
        return [i for i in range(self.n) if not self._final[i]]

    def all_answered(self) -> bool:
        return bool(self._final.all())

    def observe(self, builder, extra=None) -> dict:
        """Every robot's observation of the current step, as MapfEnv.observe builds it for training: fov (the
        paper's six channels, then the optional `extra` ones, an ExtraChannels), last_action, position, and
        `revisits` (MapfEnv's count, from the positions of the steps so far). `builder`: an ObservationBuilder of
        this instance. The heading channel reads each robot's last requested action (stay for a robot that sent
        none), as MapfEnv's does."""
        from mapf_world.env import REVISIT_WINDOW, revisit_counts
        from mapf_world.observation import extra_fov
        obs = builder.build(self.positions, self.last_actions)
        if extra is not None and extra.count:
            last = self.moves[-1] if self.moves else None
            requested = last.requested if last else np.zeros(self.n, dtype=np.int64)
            refused = last.outcomes == OUTCOME_BLOCKED if last else np.zeros(self.n, dtype=bool)
            obs["fov"] = np.concatenate([obs["fov"], extra_fov(builder, extra, self.positions, requested, refused)],
                                        axis=1)
        obs["revisits"] = revisit_counts(self.history[-1 - REVISIT_WINDOW:])
        return obs

    # --- protocol --------------------------------------------------------------------------------
    def begin_step(self) -> int:
        """Start collecting actions for the current step; returns the step number."""
        if self.phase not in (Phase.IDLE,):
            raise RuntimeError(f"begin_step in phase {self.phase.name}")
        self.state = State.RUNNING
        self.detail = "running"
        self.phase = Phase.COLLECTING
        self._requested = [None] * self.n
        self._final[:] = False
        self._had_rejected[:] = False
        return self.step

    def offer_action(self, robot: int, step: int, robot_id: int, action: int) -> Verdict:
        """An AgentAction received on robot `robot`'s own action topic."""
        if not 0 <= robot < self.n:
            raise ValueError(f"robot index {robot} outside 0..{self.n - 1}")
        if robot_id != robot:
            return self._reject(robot, f"robot_id {robot_id} in a message on robot {robot}'s topic", final=False)
        if self.phase != Phase.COLLECTING or step != self.step:
            now = f"step {self.step}" if self.phase == Phase.COLLECTING else f"no step collecting (phase {self.phase.name})"
            return self._reject(robot, f"action for step {step}, but {now}", final=False)
        if self._final[robot]:
            return Verdict(False, True, f"duplicate action for step {step} ignored; the first one counts")
        if not 0 <= action < N_ACTIONS:
            return self._reject(robot, f"action {action} outside 0..4; robot {robot} stays", final=True)
        self._requested[robot] = int(action)
        self._final[robot] = True
        return Verdict(True, True, "")

    def _reject(self, robot: int, reason: str, final: bool) -> Verdict:
        self.rejected += 1
        if self.phase == Phase.COLLECTING:
            self._had_rejected[robot] = True
            if final:
                self._final[robot] = True
        return Verdict(False, final, reason)

    def close_step(self) -> StepMoves:
        """End the collection (all answered or deadline passed) and apply the interlock."""
        if self.phase != Phase.COLLECTING:
            raise RuntimeError(f"close_step in phase {self.phase.name}")
        requested = np.zeros(self.n, dtype=np.int64)
        outcomes = np.full(self.n, OUTCOME_OK, dtype=np.int64)
        for i, a in enumerate(self._requested):
            if a is None:
                outcomes[i] = OUTCOME_REJECTED if self._had_rejected[i] else OUTCOME_TIMEOUT
                self.timeouts += int(outcomes[i] == OUTCOME_TIMEOUT)
            else:
                requested[i] = a
        new_positions, failed = self._resolve(self.grid, self.positions, requested)
        failed = np.asarray(failed, dtype=bool)
        outcomes[failed] = OUTCOME_BLOCKED
        self.failed_moves += int(failed.sum())
        actions = np.where(failed, STAY, requested)
        self._pending = StepMoves(self.step, requested, actions, outcomes,
                                  self.positions.copy(), np.asarray(new_positions, dtype=np.int64))
        self.phase = Phase.SETTLING
        return self._pending

    def settle(self) -> None:
        """Every robot stands on its approved cell: the step is complete."""
        if self.phase != Phase.SETTLING or self._pending is None:
            raise RuntimeError(f"settle in phase {self.phase.name}")
        moves = self._pending
        self._pending = None
        self.positions = moves.to_cells.copy()
        # As in MapfEnv (the training environment), by the model's last_action mode: "requested", the action
        # asked for even when the rules failed it; "executed", the approved one (stay when failed). A robot
        # without a valid action counts as having asked to stay.
        self.last_actions = (moves.actions if self.last_action_mode == "executed" else moves.requested).copy()
        self.moves.append(moves)
        self.history.append(self.positions.copy())
        self.step += 1
        if self.on_goal.all():
            self._finish(State.SUCCESS, f"every robot on its goal after {self.step} steps")
        elif self.step >= self.max_steps:
            self._finish(State.MAX_STEPS, f"step limit {self.max_steps} reached; {int(self.on_goal.sum())}/{self.n} robots on their goals")
        else:
            self.phase = Phase.IDLE

    def abort(self, reason: str) -> None:
        self._finish(State.ABORTED, reason)

    def _finish(self, state: State, detail: str) -> None:
        self.state = state
        self.detail = detail
        self.phase = Phase.DONE

    def summary(self) -> dict:
        """Plain-data summary of the run so far."""
        return {
            "state": self.state.name.lower(),
            "detail": self.detail,
            "success": self.state == State.SUCCESS,
            "steps": self.step,
            "max_steps": self.max_steps,
            "n_robots": self.n,
            "failed_moves": self.failed_moves,
            "timeouts": self.timeouts,
            "rejected": self.rejected,
            "on_goal": self.on_goal.tolist(),
            "starts": self.starts.tolist(),
            "goals": self.goals.tolist(),
            "positions": [p.tolist() for p in self.history],
            "outcomes": [[OUTCOME_NAMES[o] for o in m.outcomes.tolist()] for m in self.moves],
            "actions": [[ACTION_NAMES[a] for a in m.actions.tolist()] for m in self.moves],
        }


def describe_moves(moves: StepMoves) -> str:
    """One line per step for logs: robot -> action (outcome)."""
    parts = []
    for i in range(len(moves.actions)):
        o = int(moves.outcomes[i])
        txt = f"r{i}:{ACTION_NAMES[int(moves.actions[i])]}"
        if o != OUTCOME_OK:
            txt += f"({OUTCOME_NAMES[o]}" + (f" {ACTION_NAMES[int(moves.requested[i])]}" if o == OUTCOME_BLOCKED else "") + ")"
        parts.append(txt)
    return " ".join(parts)


def robot_id_from_namespace(namespace: str, prefix: str = "robot_") -> int:
    """'/robot_3' -> 3 (the last namespace component); ValueError when it does not name a robot."""
    last = namespace.rstrip("/").rsplit("/", 1)[-1]
    if not last.startswith(prefix) or not last[len(prefix):].isdigit():
        raise ValueError(f"namespace {namespace!r} does not end in '{prefix}<i>'; start the node with "
                         f"--ros-args -r __ns:=/{prefix}<i> or set the robot_id parameter")
    return int(last[len(prefix):])


def resolve_robot_id(param_value: int, namespace: str, prefix: str = "robot_") -> int:
    """The robot id of a per-robot node: the robot_id parameter (>= 0) or, when it is -1, the namespace.

    Both given and disagreeing is an error: the node would answer on another robot's topics.
    """
    if isinstance(param_value, bool) or not isinstance(param_value, int) or param_value < -1:
        raise ValueError(f"parameter robot_id must be an integer >= 0 (or -1: take it from the namespace), "
                         f"got {param_value!r}")
    try:
        from_ns = robot_id_from_namespace(namespace, prefix)
    except ValueError:
        from_ns = None
    if param_value == -1:
        if from_ns is None:
            robot_id_from_namespace(namespace, prefix)  # raises with the explanation
        return from_ns
    if from_ns is not None and from_ns != param_value:
        raise ValueError(f"parameter robot_id {param_value} disagrees with namespace {namespace!r}")
    return param_value


INSTANCE_SOURCES = ("random", "map", "npz")


def load_fleet_instance(source: str, *, map_file: str = "", scen_file: str = "", npz_file: str = "",
                        npz_index: int = 0, seed: int = 0, size: int = 10, density: float = 0.3,
                        n_robots: int = 3):
    """The instance the world node runs, from one of INSTANCE_SOURCES; ValueError naming the problem.

    random: generate_instance(seed, size, density, n_robots).
    map:    MovingAI .map + .scen, the first n_robots agents of the scenario.
    npz:    case npz_index of a benchmark .npz; n_robots must equal its agent count or be -1 (all).
    """
    from pathlib import Path

    from mapf_world import instances

    if isinstance(n_robots, bool) or not isinstance(n_robots, int) or not (n_robots >= 1 or (source == "npz" and n_robots == -1)):
        raise ValueError(f"n_robots must be a positive integer (or -1 with instance_source npz), got {n_robots!r}")
    if source == "random":
        inst = instances.generate_instance(int(seed), size=int(size), density=float(density), n_agents=n_robots)
        inst.name = f"random(seed={seed}, size={size}, density={density}, n={n_robots})"
        return inst
    if source == "map":
        for what, value in (("map_file", map_file), ("scen_file", scen_file)):
            if not value:
                raise ValueError(f"instance_source 'map' needs the {what} parameter")
            if not Path(value).is_file():
                raise ValueError(f"{what} {value!r} does not exist")
        grid = instances.load_movingai_map(map_file)
        return instances.load_movingai_scen(scen_file, n_robots, grid=grid)
    if source == "npz":
        if not npz_file:
            raise ValueError("instance_source 'npz' needs the npz_file parameter")
        if not Path(npz_file).is_file():
            raise ValueError(f"npz_file {npz_file!r} does not exist")
        cases = instances.load_npz(npz_file)
        if not 0 <= npz_index < len(cases):
            raise ValueError(f"npz_index {npz_index} is outside 0..{len(cases) - 1} of {npz_file}")
        inst = cases[npz_index]
        if n_robots not in (-1, inst.n_agents):
            raise ValueError(f"{npz_file} case {npz_index} has {inst.n_agents} agents, n_robots is {n_robots} "
                             f"(use -1 to take them all)")
        return inst
    raise ValueError(f"instance_source must be one of {INSTANCE_SOURCES}, got {source!r}")
