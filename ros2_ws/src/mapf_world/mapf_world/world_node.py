"""World node: the ground station of the fleet, standing in for the motion-capture computer.

It loads an instance, tracks every robot's pose (simulated odometry `/robot_<i>/odom`, or a pose
topic per robot for real robots), and runs the grid steps of mapf_world.fleet_core: observations
to each robot's own namespace only, actions collected with a timeout, the grid rules as a safety
interlock, approved cell moves out, wait until every robot has settled on its cell, advance.

Publishes per robot: observation (AgentObservation), cell_move (CellMove), initialpose (latched,
pose_source odom only: the simulated start pose). Fleet-wide: fleet/status (FleetStatus), map
(nav_msgs/OccupancyGrid, latched) and fleet/markers (visualization_msgs/MarkerArray) for viewers.
Grid-to-world frame: x = col * cell_size, y = -row * cell_size (docs/FLEET.md).
Exit status: 0 when the run ended (success or step limit), 1 when it was aborted, 2 on bad input.
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from mapf_msgs.msg import AgentAction, AgentObservation, CellMove, FleetStatus
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from visualization_msgs.msg import MarkerArray

from mapf_world import fleet_msgs
from mapf_world.fleet_core import (INSTANCE_SOURCES, Deadline, FleetCore, Phase, State, common_drive_start,
                                   describe_moves, load_fleet_instance, pose_error)
from mapf_world.fleet_qos import DEFAULT_DEPTH, LATCHED, STATUS_DEPTH, history_depth
from mapf_world.node_main import create_node
from mapf_world.observation import ExtraChannels, ObservationBuilder


class RobotTrack:
    """Latest pose of one robot as seen by the ground station."""

    def __init__(self):
        self.x = self.y = self.yaw = None
        self.speed = 0.0           # |v| + |w| from odometry (0 for pose topics)
        self.in_tolerance_since = None

    @property
    def known(self) -> bool:
        return self.x is not None


class WorldNode(Node):
    def __init__(self):
        super().__init__("world")
        p = self._declare_parameters()
        self.params = p
        inst = load_fleet_instance(
            p["instance_source"], map_file=p["map_file"], scen_file=p["scen_file"], npz_file=p["npz_file"],
            npz_index=p["npz_index"], seed=p["seed"], size=p["size"], density=p["density"], n_robots=p["n_robots"])
        self.instance = inst
        self.core = FleetCore(inst.grid, inst.starts, inst.goals, p["max_steps"], last_action=p["last_action"])
        self.builder = ObservationBuilder(inst.grid, inst.goals, fov_size=p["fov_size"])
        self.extra = ExtraChannels.from_names(p["extra_channels"])  # checked in _declare_parameters
        self.n = self.core.n
        self.cell_size = p["cell_size"]
        self.tracks = [RobotTrack() for _ in range(self.n)]
        self.step_started = None
        self.deadline = Deadline()   # of the current phase: actions in, or robots settled
        self.step_walls = []      # wall s per step: observations out -> every robot settled
        self.action_walls = []    # wall s per step: observations out -> actions closed (all in, or timeout)
        self.t_start = time.monotonic()
        self.t_running = None
        self.finished = False
        self.exit_code = 0
        self._last_wait_log = 0.0
        self._ready_since = None

        ns = [f"{p['robot_namespace_prefix']}{i}" for i in range(self.n)]
        self.obs_pubs = [self.create_publisher(AgentObservation, f"{n}/observation", DEFAULT_DEPTH) for n in ns]
        self.move_pubs = [self.create_publisher(CellMove, f"{n}/cell_move", DEFAULT_DEPTH) for n in ns]
        self.action_topics = [f"{n}/action" for n in ns]
        for i, n in enumerate(ns):
            self.create_subscription(AgentAction, f"{n}/action", lambda m, i=i: self.on_action(i, m), 10)
            if p["pose_source"] == "odom":
                self.create_subscription(Odometry, f"{n}/odom", lambda m, i=i: self.on_odom(i, m), 10)
            else:
                self.create_subscription(PoseStamped, f"{n}/{p['pose_topic']}", lambda m, i=i: self.on_pose(i, m), 10)
        self.status_pub = self.create_publisher(FleetStatus, "fleet/status", STATUS_DEPTH)
        self.map_pub = self.create_publisher(OccupancyGrid, "map", LATCHED)
        self.marker_pub = self.create_publisher(MarkerArray, "fleet/markers",
                                               history_depth(1.0 / p["marker_period_s"]))
        self.map_pub.publish(fleet_msgs.occupancy_grid(inst.grid, self.cell_size, self.header()))
        if p["pose_source"] == "odom":
            self.initial_pubs = [self.create_publisher(PoseWithCovarianceStamped, f"{n}/initialpose", LATCHED) for n in ns]
            for i in range(self.n):
                self.initial_pubs[i].publish(fleet_msgs.initial_pose(inst.starts[i], self.cell_size, self.header()))
        self.create_timer(0.01, self.tick)
        self.create_timer(p["marker_period_s"], self.publish_markers)
        self.get_logger().info(
            f"instance {inst.name}: {inst.grid.shape[0]}x{inst.grid.shape[1]} map, {self.n} robots, "
            f"starts {inst.starts.tolist()}, goals {inst.goals.tolist()}; cell {self.cell_size} m, "
            f"max_steps {p['max_steps']}, pose_source {p['pose_source']}; observations: the paper's six channels"
            + (f" + {list(self.extra.names)}" if self.extra.names else "") + f", last action {p['last_action']}")

    # --- parameters ------------------------------------------------------------------------------
    def _declare_parameters(self) -> dict:
        defaults = dict(
            instance_source="random", map_file="", scen_file="", npz_file="", npz_index=0,
            seed=0, size=10, density=0.3, n_robots=3,
            fov_size=9, max_steps=64, cell_size=0.3,
            pose_source="odom", pose_topic="pose",
            action_timeout_s=2.0, settle_timeout_s=30.0, startup_timeout_s=60.0,
            settle_tolerance_m=0.03, settle_speed_eps=1e-3, settle_hold_s=0.3,
            lockstep_drive=True, max_angular_speed=1.57,
            robot_namespace_prefix="robot_", frame_id="map",
            summary_path="", marker_period_s=0.2, linger_s=1.0, ready_grace_s=1.0, wait_for_recorder="",
            last_action="requested", extra_channels=[""],
        )
        p = {k: self.declare_parameter(k, v).value for k, v in defaults.items()}
        if p["instance_source"] not in INSTANCE_SOURCES:
            raise ValueError(f"parameter instance_source must be one of {INSTANCE_SOURCES}, got {p['instance_source']!r}")
        if p["pose_source"] not in ("odom", "pose_topic"):
            raise ValueError(f"parameter pose_source must be 'odom' or 'pose_topic', got {p['pose_source']!r}")
        for k in ("cell_size", "action_timeout_s", "settle_timeout_s", "startup_timeout_s", "settle_tolerance_m",
                  "settle_speed_eps", "max_angular_speed", "marker_period_s"):
            if not (math.isfinite(p[k]) and p[k] > 0):
                raise ValueError(f"parameter {k} must be a positive number, got {p[k]!r}")
        for k in ("settle_hold_s", "linger_s", "ready_grace_s"):
            if not (math.isfinite(p[k]) and p[k] >= 0):
                raise ValueError(f"parameter {k} must be a number >= 0, got {p[k]!r}")
        if p["settle_tolerance_m"] >= p["cell_size"] / 2:
            raise ValueError(f"parameter settle_tolerance_m ({p['settle_tolerance_m']}) must be below half a cell "
                             f"({p['cell_size'] / 2})")
        if p["max_steps"] < 1:
            raise ValueError(f"parameter max_steps must be >= 1, got {p['max_steps']}")
        if p["fov_size"] < 3 or p["fov_size"] % 2 == 0:
            raise ValueError(f"parameter fov_size must be an odd integer >= 3, got {p['fov_size']}")
        try:
            p["extra_channels"] = list(ExtraChannels.from_names([n for n in p["extra_channels"] if n]).names)
        except ValueError as exc:
            raise ValueError(f"parameter extra_channels: {exc}") from exc
        return p

    # --- inputs ----------------------------------------------------------------------------------
    def on_action(self, i: int, msg: AgentAction) -> None:
        verdict = self.core.offer_action(i, int(msg.step), int(msg.robot_id), int(msg.action))
        if not verdict.accepted:
            if verdict.reason.startswith("duplicate"):
                self.get_logger().debug(f"robot {i}: {verdict.reason}")
            else:
                self.get_logger().warning(f"robot {i}: rejected action: {verdict.reason}")
        self.update()

    def on_odom(self, i: int, msg: Odometry) -> None:
        t = self.tracks[i]
        pose = msg.pose.pose
        t.x, t.y = pose.position.x, pose.position.y
        t.yaw = 2.0 * math.atan2(pose.orientation.z, pose.orientation.w)
        tw = msg.twist.twist
        t.speed = abs(tw.linear.x) + abs(tw.linear.y) + abs(tw.angular.z)
        if self.core.phase == Phase.SETTLING:
            self.update()

    def on_pose(self, i: int, msg: PoseStamped) -> None:
        t = self.tracks[i]
        t.x, t.y = msg.pose.position.x, msg.pose.position.y
        t.yaw = 2.0 * math.atan2(msg.pose.orientation.z, msg.pose.orientation.w)
        t.speed = 0.0

    # --- the step machine ------------------------------------------------------------------------
    def _settled(self, i: int, cell, now: float) -> bool:
        t = self.tracks[i]
        if not t.known or pose_error(t.x, t.y, cell, self.cell_size) > self.params["settle_tolerance_m"]:
            t.in_tolerance_since = None
            return False
        if self.params["pose_source"] == "odom":
            return t.speed <= self.params["settle_speed_eps"]
        if t.in_tolerance_since is None:
            t.in_tolerance_since = now
        return now - t.in_tolerance_since >= self.params["settle_hold_s"]

    def tick(self) -> None:
        """The periodic timer: the only place where deadlines are enforced (see fleet_core.Deadline)."""
        self.update(expired=self.deadline.expired(time.monotonic()))

    def update(self, expired: bool = False) -> None:
        if self.finished:
            return
        now = time.monotonic()
        core = self.core
        if core.state == State.WAITING:
            self._wait_for_robots(now)
        elif core.phase == Phase.COLLECTING:
            if core.all_answered() or expired:
                self._send_moves(now)
        elif core.phase == Phase.SETTLING:
            moves = core.pending
            if all(self._settled(i, moves.to_cells[i], now) for i in range(self.n)):
                self._complete_step(now)
            elif expired:
                late = [i for i in range(self.n) if not self._settled(i, moves.to_cells[i], now)]
                where = "; ".join(self._where(i, moves.to_cells[i]) for i in late)
                self._finish(f"settle timeout: robots {late} not settled on their cells within "
                             f"{self.params['settle_timeout_s']} s ({where})", aborted=True)

    def _where(self, i: int, cell) -> str:
        t = self.tracks[i]
        if not t.known:
            return f"robot {i}: no pose received"
        return f"robot {i} at ({t.x:.3f}, {t.y:.3f}), {pose_error(t.x, t.y, cell, self.cell_size):.3f} m from cell {tuple(int(v) for v in cell)}"

    def _wait_for_robots(self, now: float) -> None:
        not_placed = [i for i in range(self.n) if not self._settled(i, self.core.starts[i], now)]
        no_policy = [i for i in range(self.n) if self.count_publishers(self.action_topics[i]) == 0]
        unrecorded = self._unrecorded_topics() if not not_placed and not no_policy else []
        waited = now - self.t_start
        if not not_placed and not no_policy and not unrecorded:
            # A short grace lets passive subscribers (recorder, viewers) discover the new publishers.
            if self._ready_since is None:
                self._ready_since = now
            if now - self._ready_since >= self.params["ready_grace_s"]:
                self._begin(now)
            return
        self._ready_since = None
        if waited >= self.params["startup_timeout_s"]:
            if not_placed:
                where = "; ".join(self._where(i, self.core.starts[i]) for i in not_placed)
                self._finish(f"startup timeout: robots {not_placed} not on their start cells after "
                             f"{waited:.1f} s ({where})", aborted=True)
            elif no_policy:
                self.get_logger().warning(f"startup timeout: no policy node publishes the action of robots {no_policy}; "
                                          f"starting anyway (they stay until one answers)")
                self._begin(now)
            else:
                self.get_logger().warning(f"startup timeout: {self.params['wait_for_recorder']!r} does not subscribe "
                                          f"to {unrecorded[:4]} ({len(unrecorded)} topics); starting anyway "
                                          f"(its log will lack the first messages there)")
                self._begin(now)
        elif now - self._last_wait_log >= 5.0:
            self._last_wait_log = now
            self.get_logger().info(f"waiting for robots: not on start cell {not_placed}, no policy node {no_policy}"
                                   + (f", {len(unrecorded)} topics not yet recorded" if unrecorded else ""))
            self.publish_status()

    def _unrecorded_topics(self) -> list:
        """Topics of the grid steps (every robot's observation, action and cell_move, and fleet/status) that the
        node named by wait_for_recorder does not subscribe to yet ([] when the parameter is empty). Waiting for
        them keeps a fast start-up from running steps before the recorder sees them."""
        name = self.params["wait_for_recorder"]
        if not name:
            return []
        topics = ["/fleet/status"] + [f"/{t}" for t in self.action_topics]
        topics += [f"/{p.topic_name.lstrip('/')}" for p in self.obs_pubs + self.move_pubs]
        return [t for t in topics if not any(info.node_name == name for info in self.get_subscriptions_info_by_topic(t))]

    def _begin(self, now: float) -> None:
        self.t_running = now
        self.get_logger().info(f"all robots ready after {now - self.t_start:.2f} s: running")
        self.publish_status()
        self._start_step(now)

    def _start_step(self, now: float) -> None:
        core = self.core
        step = core.begin_step()
        self.step_started = now
        obs = core.observe(self.builder, self.extra)
        for i, msg in enumerate(fleet_msgs.observations(obs, core, self.header(), self.extra.names)):
            self.obs_pubs[i].publish(msg)
        # The robots' time starts when the last observation is out, not before a slow publish.
        self.deadline.set(time.monotonic(), self.params["action_timeout_s"])

    def _send_moves(self, now: float) -> None:
        core = self.core
        waiting = core.waiting_for()
        moves = core.close_step()
        self.action_walls.append(now - self.step_started)
        if waiting:
            self.get_logger().warning(f"step {moves.step}: no valid action from robots {waiting} within "
                                      f"{self.params['action_timeout_s']} s: they stay")
        drive_start = 0.0
        if self.params["lockstep_drive"]:
            yaws = [t.yaw if t.yaw is not None else 0.0 for t in self.tracks]
            drive_start = common_drive_start(yaws, moves.from_cells, moves.to_cells, self.params["max_angular_speed"])
        for i, msg in enumerate(fleet_msgs.cell_moves(moves, self.cell_size, drive_start, self.header())):
            self.move_pubs[i].publish(msg)
        self.deadline.set(time.monotonic(), self.params["settle_timeout_s"])

    def _complete_step(self, now: float) -> None:
        moves = self.core.pending
        self.core.settle()
        wall = now - self.step_started
        self.step_walls.append(wall)
        self.get_logger().info(f"step {moves.step} done in {wall:.3f} s: {describe_moves(moves)}")
        self.publish_status(moves, wall)
        if self.core.done:
            self._finish(self.core.detail, aborted=False)
        else:
            self._start_step(now)

    def _finish(self, detail: str, aborted: bool) -> None:
        if aborted:
            self.core.abort(detail)
            self.exit_code = 1
            self.get_logger().error(detail)
        self.finished = True
        self.publish_status(done=True)
        summary = self.summary()
        self.get_logger().info(
            f"run over: {summary['state']} ({summary['detail']}); steps {summary['steps']}, failed moves "
            f"{summary['failed_moves']}, timeouts {summary['timeouts']}, rejected {summary['rejected']}, "
            f"wall {summary['wall_s']:.2f} s, mean step {summary['mean_step_wall_s']:.3f} s")
        self.write_summary()

    def interrupted(self) -> None:
        """SIGINT/SIGTERM: record the run as aborted unless it had already ended."""
        if not self.finished:
            self.finished = True
            self.core.abort("interrupted (SIGINT/SIGTERM)")
            self.exit_code = 0
            self.write_summary()
            # print, not the ROS logger: the context (and /rosout) is already shut down.
            print(f"[world] interrupted at step {self.core.step}; summary: {self.params['summary_path'] or 'not written'}",
                  file=sys.stderr, flush=True)

    # --- outputs ---------------------------------------------------------------------------------
    def summary(self) -> dict:
        s = self.core.summary()
        s["instance"] = self.instance.name
        s["grid"] = self.instance.grid.tolist()
        s["step_wall_s"] = [round(w, 4) for w in self.step_walls]
        s["mean_step_wall_s"] = float(np.mean(self.step_walls)) if self.step_walls else 0.0
        s["action_wall_s"] = [round(w, 4) for w in self.action_walls]
        s["mean_action_wall_s"] = float(np.mean(self.action_walls)) if self.action_walls else 0.0
        s["wall_s"] = time.monotonic() - (self.t_running or self.t_start)
        s["startup_s"] = (self.t_running - self.t_start) if self.t_running else None
        s["parameters"] = self.params
        return s

    def write_summary(self) -> None:
        path = self.params["summary_path"]
        if path:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            Path(path).write_text(json.dumps(self.summary(), indent=1) + "\n")

    def header(self):
        return fleet_msgs.stamp_header(self.get_clock().now().to_msg(), self.params["frame_id"])

    def publish_status(self, moves=None, wall: float = 0.0, done: bool = False) -> None:
        self.status_pub.publish(fleet_msgs.fleet_status(self.core, self.instance.name, self.cell_size, self.header(),
                                                        moves, wall, done))

    def publish_markers(self) -> None:
        poses = [(t.x, t.y, t.yaw) if t.known else None for t in self.tracks]
        self.marker_pub.publish(fleet_msgs.markers(self.core, poses, self.cell_size, self.header()))


def main(args=None):
    rclpy.init(args=args)
    node = create_node("world_node", WorldNode)
    if node is None:
        return
    code = 0
    # EventsExecutor: the default executor rebuilds a wait set of all the node's entities (a few per robot) for
    # every callback, which at 64 robots and their odometry took more CPU than the callbacks themselves.
    from rclpy.experimental import EventsExecutor
    executor = EventsExecutor()
    executor.add_node(node)
    try:
        while rclpy.ok() and not node.finished:
            executor.spin_once(timeout_sec=0.1)
        if not node.finished:  # the context was shut down (SIGINT/SIGTERM) between two spins
            node.interrupted()
        # Let the last status and moves reach their subscribers (the recorder) before leaving.
        end = time.monotonic() + node.params["linger_s"]
        while rclpy.ok() and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        code = node.exit_code
    except (KeyboardInterrupt, ExternalShutdownException):
        node.interrupted()
    except Exception:
        if rclpy.ok():
            raise
        node.interrupted()  # a signal shut the context down while a callback ran (an rclpy race)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    raise SystemExit(code)


if __name__ == "__main__":
    main()
