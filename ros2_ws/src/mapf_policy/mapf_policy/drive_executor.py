"""Drive executor: one per robot (namespace /robot_<i>). Turns approved cell moves into motion.

Subscribes: cell_move (mapf_msgs/CellMove), initialpose (geometry_msgs/PoseWithCovarianceStamped,
latched: the simulated robot's start pose, sent by the world node).
Publishes at a fixed rate: cmd_vel (geometry_msgs/Twist) and odom (nav_msgs/Odometry, the
integration of the commanded twist; frame `frame_id`, child `<ns>/base_link`).

Idle odometry (`idle_rate_hz`, simulated Hz; 0 = off, the default): while the robot stands still, odom and
cmd_vel go out at this lower rate instead of rate_hz. The first standstill tick after a move is always sent
(it is what tells the world the robot has settled), so nothing waits longer; a fleet of 64 robots, most
standing on their goals, then sends a fraction of the messages (docs/FLEET.md, "64 robots").

Time: the node keeps a simulated clock that advances one control period (1 / rate_hz) per tick;
ticks run every 1 / (rate_hz * real_time_factor) wall seconds. Odometry stamps are that simulated
clock and the velocities are the physical ones, so a run at real_time_factor 10 logs the same
motion as one at 1, only sooner. The kinematics are in drive.py (pure).
"""
from __future__ import annotations

import math
import time
from collections import deque

import rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped, Twist
from mapf_msgs.msg import CellMove
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.time import Time

from mapf_policy.drive import (DriveLimits, Pose2D, cell_to_xy, integrate, plan_cell_move,
                               quaternion_from_yaw, xy_to_cell, yaw_from_quaternion)
from mapf_world.fleet_core import resolve_robot_id
from mapf_world.fleet_qos import DEFAULT_DEPTH, LATCHED, history_depth
from mapf_world.node_main import run_node


def positive(node: Node, name: str) -> float:
    value = node.get_parameter(name).value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"parameter {name} must be a positive number, got {value!r}")
    return float(value)


class DriveExecutor(Node):
    """`node_options` (namespace, parameter_overrides, ...) go to rclpy's Node (robot_container.py)."""

    def __init__(self, **node_options):
        super().__init__("drive_executor", **node_options)
        self.declare_parameter("robot_id", -1)
        self.declare_parameter("cell_size", 0.3)
        self.declare_parameter("max_linear_speed", 0.2)
        self.declare_parameter("max_angular_speed", 1.57)
        self.declare_parameter("rate_hz", 20.0)
        self.declare_parameter("real_time_factor", 1.0)
        self.declare_parameter("frame_id", "map")
        self.declare_parameter("idle_rate_hz", 0.0)
        self.robot_id = resolve_robot_id(self.get_parameter("robot_id").value, self.get_namespace())
        self.cell_size = positive(self, "cell_size")
        self.limits = DriveLimits(positive(self, "max_linear_speed"), positive(self, "max_angular_speed"))
        rate = positive(self, "rate_hz")
        self.rtf = positive(self, "real_time_factor")
        self.dt = 1.0 / rate
        self.frame_id = str(self.get_parameter("frame_id").value)
        idle = self.get_parameter("idle_rate_hz").value
        if isinstance(idle, bool) or not isinstance(idle, (int, float)) or not math.isfinite(idle) or idle < 0:
            raise ValueError(f"parameter idle_rate_hz must be a number >= 0 (0: odometry at rate_hz always), got {idle!r}")
        # Ticks between two idle publications (1: every tick).
        self.idle_every = max(1, round(rate / idle)) if 0 < idle < rate else 1
        self.idle_ticks = 0              # ticks since the last publication while standing still
        self.child_frame_id = f"{self.get_namespace().strip('/') or 'robot_%d' % self.robot_id}/base_link"

        self.pose = None                 # Pose2D once the initial pose is known
        self.plan = deque()              # commands of the move in progress
        self.queue = deque()             # CellMoves waiting for the move in progress
        self.last_step = -1
        self.sim_ns = time.time_ns()     # simulated clock, advanced dt per tick
        # One tick per dt / rtf wall seconds: keep fleet_qos.REPAIR_WINDOW_S of ticks for the reliable protocol.
        depth = history_depth(rate * self.rtf)
        self.odom_pub = self.create_publisher(Odometry, "odom", depth)
        self.cmd_pub = self.create_publisher(Twist, "cmd_vel", depth)
        self.create_subscription(CellMove, "cell_move", self.on_cell_move, DEFAULT_DEPTH)
        self.create_subscription(PoseWithCovarianceStamped, "initialpose", self.on_initial_pose, LATCHED)
        self.create_timer(self.dt / self.rtf, self.tick)
        self.get_logger().info(f"robot {self.robot_id}: cell {self.cell_size} m, limits {self.limits.max_linear} m/s "
                               f"{self.limits.max_angular} rad/s, {rate} Hz, real_time_factor {self.rtf}")

    def on_initial_pose(self, msg: PoseWithCovarianceStamped) -> None:
        p = msg.pose.pose
        self.pose = Pose2D(p.position.x, p.position.y, yaw_from_quaternion(p.orientation.z, p.orientation.w))
        self.plan.clear()
        self.queue.clear()
        self.last_step = -1
        self.idle_ticks = 0  # the next tick publishes the new pose
        cell = xy_to_cell(self.pose.x, self.pose.y, self.cell_size)
        self.get_logger().info(f"initial pose ({self.pose.x:.3f}, {self.pose.y:.3f}, {self.pose.yaw:.3f}) = cell {cell}")

    def on_cell_move(self, msg: CellMove) -> None:
        log = self.get_logger()
        if msg.robot_id != self.robot_id:
            log.error(f"cell_move for robot {msg.robot_id} on robot {self.robot_id}'s topic: ignored")
            return
        if abs(msg.cell_size - self.cell_size) > 1e-9:
            log.error(f"cell_move step {msg.step}: cell_size {msg.cell_size} m differs from this robot's "
                      f"{self.cell_size} m: ignored (set the same cell_size on world and robots)")
            return
        if self.pose is None:
            log.error(f"cell_move step {msg.step} before the initial pose is known: ignored")
            return
        if msg.step <= self.last_step:
            log.warning(f"cell_move step {msg.step} again (last was {self.last_step}): ignored")
            return
        self.last_step = msg.step
        self.queue.append(msg)

    def _start_next_move(self) -> None:
        msg = self.queue.popleft()
        here = xy_to_cell(self.pose.x, self.pose.y, self.cell_size)
        if here != tuple(msg.from_cell):
            self.get_logger().warning(f"step {msg.step}: move from {tuple(msg.from_cell)} but the robot is at {here}")
        target = cell_to_xy(msg.to_cell, self.cell_size)
        self.plan.extend(plan_cell_move(self.pose, target, self.limits, self.dt, drive_start_s=msg.drive_start_s,
                                        min_distance=1e-3 * self.cell_size))

    def tick(self) -> None:
        if self.pose is None:
            return
        if not self.plan and self.queue:
            self._start_next_move()
        moving = bool(self.plan)
        v, w = self.plan.popleft() if self.plan else (0.0, 0.0)
        # Standing still: publish every idle_every-th tick only; a move's first standstill tick always goes out.
        self.idle_ticks = 0 if moving else self.idle_ticks + 1
        if not moving and self.idle_ticks != 1 and (self.idle_ticks - 1) % self.idle_every:
            self.sim_ns += int(round(self.dt * 1e9))
            return
        stamp = Time(nanoseconds=self.sim_ns).to_msg()
        odom = Odometry()
        odom.header.stamp = stamp
        odom.header.frame_id = self.frame_id
        odom.child_frame_id = self.child_frame_id
        odom.pose.pose.position.x = self.pose.x
        odom.pose.pose.position.y = self.pose.y
        _, _, qz, qw = quaternion_from_yaw(self.pose.yaw)
        odom.pose.pose.orientation.z = qz
        odom.pose.pose.orientation.w = qw
        odom.twist.twist.linear.x = v
        odom.twist.twist.angular.z = w
        cmd = Twist()
        cmd.linear.x = v
        cmd.angular.z = w
        self.cmd_pub.publish(cmd)
        self.odom_pub.publish(odom)
        self.pose = integrate(self.pose, v, w, self.dt)
        self.sim_ns += int(round(self.dt * 1e9))


def main(args=None):
    run_node("drive_executor", DriveExecutor, args)


if __name__ == "__main__":
    main()
