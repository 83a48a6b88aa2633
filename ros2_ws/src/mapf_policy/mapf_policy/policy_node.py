"""Policy node: one per robot (namespace /robot_<i>), its own copy of the learned grid policy.

Subscribes to its own relative `observation` topic only and publishes its own relative `action`
(mapf_msgs/AgentObservation -> mapf_msgs/AgentAction). It never names another robot's topic: the
robots do not communicate (paper section V-B); the namespace it is started in decides its topics.
It runs the exported model (.npz, scripts/export_model) with numpy (runtime_policy.py): it imports neither
torch nor the training code. It refuses to start (exit 2) when the model file is missing, is not an export,
fails its checks, or was exported from another model file than `source_sha256` names.

Parameters: robot_id, model_path (the exported .npz), source_sha256 (SHA-256 of the .pt file the export must
come from; empty: not checked); the action rule (mapf_policy/action_selection.py,
defaults those of ActionRule): action_temperature (softmax sampling of the action, 0 = greedy argmax),
backtrack_penalty (Q-value penalty on moving back to the previous step's cell, 0 = off; the node keeps
its robot's previous cell) and mask_obstacle_moves; the paper's rule is action_temperature:=0
backtrack_penalty:=0 mask_obstacle_moves:=false. seed: of this robot's own sampling generator; -1, the
default, uses the robot id, so that no two robots draw the same noise and a run is repeatable.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

# One BLAS thread: a robot's forward pass is a few small matrix products, and the robots of one machine
# (or one process) would only contend for the cores. Set before numpy is imported, which reads it then.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from mapf_msgs.msg import AgentAction, AgentObservation  # noqa: E402
from rcl_interfaces.msg import ParameterDescriptor  # noqa: E402
from rclpy.node import Node  # noqa: E402

from mapf_policy.action_selection import ActionRule  # noqa: E402
from mapf_policy.runtime_policy import RuntimePolicy  # noqa: E402
from mapf_world.fleet_core import resolve_robot_id  # noqa: E402
from mapf_world.fleet_qos import DEFAULT_DEPTH  # noqa: E402
from mapf_world.node_main import run_node  # noqa: E402

DEFAULT_MODEL = "models/hscl.npz"
# The ActionRule fields a robot can set (settled_greedy is an ablation of scripts/compare_models only).
RULE_PARAMETERS = ("action_temperature", "backtrack_penalty", "mask_obstacle_moves")


def resolve_model_path(value: str) -> Path:
    """An absolute path as is; a relative one against the working directory, then $MAPF_ROOT."""
    if not value:
        raise ValueError("parameter model_path is empty; name a model file (default models/hscl.pt)")
    path = Path(value).expanduser()
    if path.is_absolute():
        candidates = [path]
    else:
        candidates = [Path.cwd() / path]
        if os.environ.get("MAPF_ROOT"):
            candidates.append(Path(os.environ["MAPF_ROOT"]) / path)
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    tried = ", ".join(str(c) for c in candidates)
    raise FileNotFoundError(f"model file {value!r} not found (looked at {tried}); export one with "
                            f"scripts/export_model MODEL.pt or pass -p model_path:=/path/to/model.npz")


class PolicyNode(Node):
    """`node_options` (namespace, parameter_overrides, ...) go to rclpy's Node: a robot container
    (robot_container.py) starts several robots' nodes in one process this way."""

    def __init__(self, **node_options):
        super().__init__("policy_node", **node_options)
        self.declare_parameter("robot_id", -1)
        self.declare_parameter("model_path", DEFAULT_MODEL)
        self.declare_parameter("source_sha256", "")
        # Dynamic typing: `-p action_temperature:=0` arrives as an integer and is still a valid temperature.
        default_rule = ActionRule()
        for name in RULE_PARAMETERS:
            typing = ParameterDescriptor(dynamic_typing=not isinstance(getattr(default_rule, name), bool))
            self.declare_parameter(name, getattr(default_rule, name), typing)
        self.declare_parameter("seed", -1)
        self.robot_id = resolve_robot_id(self.get_parameter("robot_id").value, self.get_namespace())
        rule = ActionRule(**{name: self.get_parameter(name).value for name in RULE_PARAMETERS})
        seed = self.get_parameter("seed").value
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < -1:
            raise ValueError(f"parameter seed must be an integer >= 0, or -1 for the robot id; got {seed!r}")
        seed = self.robot_id if seed == -1 else seed
        model_path = resolve_model_path(str(self.get_parameter("model_path").value))
        if model_path.suffix == ".pt":
            raise ValueError(f"model_path {model_path} is a torch model file; a robot runs its export: "
                             f"scripts/export_model {model_path}, then -p model_path:={model_path.with_suffix('.npz')}")

        t0 = time.perf_counter()
        self.policy = RuntimePolicy(model_path, rule=rule, seed=seed)
        self.policy.check_servable()
        source = self.policy.header["source"]
        expected = str(self.get_parameter("source_sha256").value)
        if expected and source.get("sha256") != expected:
            raise ValueError(f"model_path {model_path} was exported from {source.get('file')!r} with SHA-256 "
                             f"{str(source.get('sha256'))[:12]}..., not from the model file with SHA-256 {expected[:12]}... "
                             f"that source_sha256 names; export that model again (scripts/export_model)")
        self.fov_size = int(self.policy.cfg.fov_size)
        l = self.fov_size
        # Warm-up: the first forward pass is slower; do it before announcing the action publisher.
        cfg = self.policy.cfg
        self.policy.act(np.zeros((1, cfg.fov_channels, l, l), np.float32), np.eye(5, dtype=np.float32)[:1],
                        np.zeros((1, 2), np.float32), np.eye(cfg.still_bins, dtype=np.float32)[:1] if cfg.still_bins else None)
        self.policy.reset(seed)  # the warm-up must not shift this robot's draws nor leave a previous cell
        self.get_logger().info(f"robot {self.robot_id}: model {model_path} (from {source.get('file')} "
                               f"{str(source.get('sha256'))[:12]}, fov {l}, extra channels {list(cfg.extra_channels().names)}, "
                               f"still input {cfg.still_bins and cfg.still_count}, last action {self.policy.last_action_mode}, action rule {rule.asdict()}, seed {seed}) "
                               f"ready in {time.perf_counter() - t0:.2f} s")
        self.action_pub = self.create_publisher(AgentAction, "action", DEFAULT_DEPTH)
        self.create_subscription(AgentObservation, "observation", self.on_observation, 10)

    def on_observation(self, msg: AgentObservation) -> None:
        log = self.get_logger()
        if msg.robot_id != self.robot_id:
            log.error(f"observation for robot {msg.robot_id} on robot {self.robot_id}'s topic: not answered")
            return
        try:
            inputs = self.policy.message_inputs(msg)
        except ValueError as exc:
            log.error(f"step {msg.step}: {exc}: not answered")
            return
        action = int(self.policy.act(*inputs)[0])
        out = AgentAction()
        out.header.stamp = self.get_clock().now().to_msg()
        out.step = msg.step
        out.robot_id = self.robot_id
        out.action = action
        self.action_pub.publish(out)


def main(args=None):
    run_node("policy_node", PolicyNode, args)


if __name__ == "__main__":
    main()
