"""Helpers of the headless ROS 2 fleet tests: ROS_DOMAIN_ID claims, the fleet launcher, a graph probe.

Every node runs as its own process, started exactly as `ros2 run` would (mapf_world.fleet_launch).
Domain ids are claimed with lock files in 100..229, so tests of concurrent sessions never share one.
"""
from __future__ import annotations

import signal
import time
from pathlib import Path

from mapf_world.fleet_launch import claim_domain_id, fleet_env  # noqa: F401 (the tests' fixtures and modules use them)

REPO_ROOT = Path(__file__).resolve().parents[2]
TRAINED_MODEL = REPO_ROOT / "models" / "hscl.pt"
DATA = Path(__file__).resolve().parent / "data"

# Robots of the small test map: rows 0, 2 and 4 are free corridors, so each robot has a direct path.
SMALL_MAP = DATA / "fleet_small.map"
SMALL_SCEN = DATA / "fleet_small.scen"


def robot_model(model: Path, out: Path) -> Path:
    """The torch-free export the policy nodes run: the shipped one next to a .pt when it belongs to it, else one
    written into `out` (an untrained test model)."""
    from mapf_policy.export import check_belongs, export_model
    if model.suffix == ".npz":
        return model
    shipped = model.with_suffix(".npz")
    if shipped.is_file():
        check_belongs(model, shipped)  # a stale shipped export fails here, naming the fix
        return shipped
    target = Path(out) / f"{model.stem}.npz"
    return target if target.is_file() else export_model(model, target)


class Fleet:
    """World + recorder + per robot a policy node and a drive executor, each a process."""

    def __init__(self, out: Path, domain: int, model: Path, n_robots: int = 3, world: dict | None = None,
                 real_time_factor: float = 20.0, rate_hz: float = 10.0, policy: dict | None = None):
        from mapf_world.fleet_launch import ProcessGroup, node_command
        self.node_command = node_command
        self.out = Path(out)
        self.domain = domain
        self.model = model
        self.n = n_robots
        self.mcap = self.out / "fleet.mcap"
        self.summary = self.out / "summary.json"
        self.group = ProcessGroup(self.out / "logs", fleet_env(domain))
        # The observation the model reads (last-action mode, channels beyond the paper's six), as scripts/demo sets it.
        from mapf_world.fleet_demo import policy_model_params
        observation = policy_model_params(robot_model(model, self.out))[1]
        self.world_params = dict(instance_source="map", map_file=str(SMALL_MAP), scen_file=str(SMALL_SCEN),
                                 n_robots=n_robots, max_steps=12, action_timeout_s=1.0, ready_grace_s=1.0,
                                 summary_path=str(self.summary), linger_s=0.5, wait_for_recorder="recorder") | (
            observation | (world or {}))
        self.drive_params = dict(real_time_factor=real_time_factor, rate_hz=rate_hz)
        self.policy_params = dict(policy or {})  # beyond model_path, e.g. the action rule

    def policy_command(self, i: int):
        return self.node_command("mapf_policy", "policy_node", namespace=f"/robot_{i}",
                                 params=dict(model_path=str(robot_model(self.model, self.out))) | self.policy_params)

    def start(self) -> "Fleet":
        g = self.group
        g.start("recorder", self.node_command("mapf_world", "recorder", params=dict(output=str(self.mcap))))
        for i in range(self.n):
            g.start(f"drive_{i}", self.node_command("mapf_policy", "drive_executor", namespace=f"/robot_{i}",
                                                    params=self.drive_params))
            g.start(f"policy_{i}", self.policy_command(i))
        g.start("world", self.node_command("mapf_world", "world_node", params=self.world_params))
        return self

    def wait_running(self, timeout: float = 60.0) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if ": running" in self.group.log_text("world"):
                return
            if self.group.procs["world"].poll() is not None:
                break
            time.sleep(0.1)
        raise AssertionError("the world never started running; its log:\n" + self.group.log_text("world")[-3000:])

    def wait_world(self, timeout: float = 90.0) -> int:
        return self.group.procs["world"].wait(timeout=timeout)

    def stop(self) -> dict:
        """SIGINT to every node (recorder last); their exit codes."""
        codes = self.group.stop_all([n for n in self.group.procs if n != "recorder"], sig=signal.SIGINT)
        codes |= self.group.stop_all(["recorder"], sig=signal.SIGINT)
        return codes


class GraphProbe:
    """An rclpy node in the test process, on the fleet's domain, to look at the live graph."""

    def __init__(self, domain: int):
        import rclpy
        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("graph_probe", context=self.context)
        from rclpy.executors import SingleThreadedExecutor
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def spin_until(self, predicate, timeout: float, what: str, context=None):
        """Spin until `predicate()` is true and return its value; on timeout fail, with `context()` (for example
        a process's log tail) in the message when given."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)
            value = predicate()
            if value:
                return value
        extra = f"\n{context()}" if context is not None else ""
        raise AssertionError(f"timed out after {timeout} s waiting for {what}{extra}")

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)
