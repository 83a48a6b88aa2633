"""ROS messages of the ground station built from fleet_core data (no node, no publishing).

Frame convention (docs/FLEET.md): x = col * cell_size, y = -row * cell_size, yaw 0 faces +x.
"""
from __future__ import annotations

import array
import math
from typing import Optional, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, PoseWithCovarianceStamped
from mapf_msgs.msg import AgentObservation, CellMove, FleetStatus
from nav_msgs.msg import OccupancyGrid
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from mapf_world.fleet_core import FleetCore, StepMoves, cell_to_xy

COLORS = [(0.85, 0.1, 0.1), (0.1, 0.65, 0.1), (0.1, 0.25, 0.9), (0.9, 0.6, 0.0), (0.6, 0.1, 0.8),
          (0.0, 0.7, 0.7), (0.5, 0.3, 0.1), (0.9, 0.3, 0.6)]


def observations(obs: dict, core: FleetCore, header: Header, extra_channels: Sequence[str] = ()) -> list:
    """One AgentObservation per robot from FleetCore.observe output; `extra_channels`: the names of the channels
    after the paper's six (ExtraChannels.names) that obs["fov"] holds."""
    out = []
    on_goal = core.on_goal
    names = [str(n) for n in extra_channels]
    for i in range(core.n):
        msg = AgentObservation(header=header, step=core.step, robot_id=i, fov_size=obs["fov"].shape[-1],
                               fov_channels=obs["fov"].shape[1], extra_channels=names,
                               last_action_mode=core.last_action_mode, revisits=int(obs["revisits"][i]))
        msg.fov = array.array("f", obs["fov"][i].tobytes())
        msg.last_action = obs["last_action"][i]
        msg.position = core.positions[i].astype(np.int32)
        msg.on_goal = bool(on_goal[i])
        out.append(msg)
    return out


def cell_moves(moves: StepMoves, cell_size: float, drive_start_s: float, header: Header) -> list:
    """One CellMove per robot."""
    out = []
    for i in range(len(moves.actions)):
        msg = CellMove(header=header, step=moves.step, robot_id=i, action=int(moves.actions[i]),
                       requested_action=int(moves.requested[i]), outcome=int(moves.outcomes[i]),
                       cell_size=float(cell_size), drive_start_s=float(drive_start_s))
        msg.from_cell = moves.from_cells[i].astype(np.int32)
        msg.to_cell = moves.to_cells[i].astype(np.int32)
        out.append(msg)
    return out


def fleet_status(core: FleetCore, instance: str, cell_size: float, header: Header,
                 moves: Optional[StepMoves] = None, wall: float = 0.0, done: bool = False) -> FleetStatus:
    """The state after the step `moves` (None: before any step); arrays are per robot."""
    def per_robot(values) -> array.array:
        return array.array("B", [int(v) for v in values] if values is not None else [0] * core.n)

    msg = FleetStatus(header=header, instance=instance, state=int(core.state), detail=core.detail, step=core.step,
                      max_steps=core.max_steps, n_robots=core.n, cell_size=float(cell_size),
                      failed_moves=core.failed_moves, timeouts=core.timeouts, rejected=core.rejected,
                      step_wall_s=float(wall), done=bool(done))
    msg.positions = array.array("i", core.positions.astype(np.int32).ravel().tobytes())
    msg.goals = array.array("i", core.goals.astype(np.int32).ravel().tobytes())
    msg.requested_actions = per_robot(moves.requested if moves else None)
    msg.actions = per_robot(moves.actions if moves else None)
    msg.outcomes = per_robot(moves.outcomes if moves else None)
    msg.on_goal = [bool(v) for v in core.on_goal]
    return msg


def occupancy_grid(grid: np.ndarray, cell_size: float, header: Header) -> OccupancyGrid:
    """The map for viewers: 100 = obstacle. OccupancyGrid rows grow along +y, grid rows along -y."""
    h, w = grid.shape
    msg = OccupancyGrid(header=header)
    msg.info.resolution = float(cell_size)
    msg.info.width, msg.info.height = w, h
    msg.info.origin.position.x = -cell_size / 2
    msg.info.origin.position.y = -(h - 1) * cell_size - cell_size / 2
    msg.info.origin.orientation.w = 1.0
    msg.data = array.array("b", (np.flipud(grid).astype(np.int8) * 100).ravel().tobytes())
    return msg


def initial_pose(cell: Sequence[int], cell_size: float, header: Header) -> PoseWithCovarianceStamped:
    """A simulated robot's start pose: centre of its start cell, facing +x (right)."""
    msg = PoseWithCovarianceStamped(header=header)
    msg.pose.pose.position.x, msg.pose.pose.position.y = cell_to_xy(cell, cell_size)
    msg.pose.pose.orientation.w = 1.0
    return msg


def markers(core: FleetCore, poses: Sequence[Optional[tuple]], cell_size: float, header: Header) -> MarkerArray:
    """Goals (flat cubes), robots (arrows at their live poses (x, y, yaw)) and the cells visited (lines)."""
    out = MarkerArray()

    def marker(ns: str, mid: int, mtype: int, color, alpha=1.0) -> Marker:
        m = Marker(header=header, ns=ns, id=mid, type=mtype, action=Marker.ADD)
        m.pose.orientation.w = 1.0
        m.color = ColorRGBA(r=color[0], g=color[1], b=color[2], a=alpha)
        return m

    for i in range(core.n):
        color = COLORS[i % len(COLORS)]
        goal = marker("goals", i, Marker.CUBE, color, 0.5)
        goal.pose.position.x, goal.pose.position.y = cell_to_xy(core.goals[i], cell_size)
        goal.scale.x = goal.scale.y = 0.6 * cell_size
        goal.scale.z = 0.02
        out.markers.append(goal)
        if poses[i] is not None:
            x, y, yaw = poses[i]
            body = marker("robots", i, Marker.ARROW, color)
            body.pose.position.x, body.pose.position.y = x, y
            body.pose.orientation.z, body.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
            body.scale.x, body.scale.y, body.scale.z = 0.6 * cell_size, 0.3 * cell_size, 0.3 * cell_size
            out.markers.append(body)
        path = marker("paths", i, Marker.LINE_STRIP, color, 0.8)
        path.scale.x = 0.05 * cell_size
        for cells in core.history:
            px, py = cell_to_xy(cells[i], cell_size)
            path.points.append(Point(x=px, y=py, z=0.0))
        out.markers.append(path)
    return out


def stamp_header(stamp: Time, frame_id: str) -> Header:
    return Header(stamp=stamp, frame_id=frame_id)
