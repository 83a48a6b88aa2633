"""scripts/bench_runtime: the robot runtime's targets (issue 21), measured: memory, start-up and action time.

    scripts/bench_runtime [--model models/hscl.pt] [--robots-per-process 32] [--observations 2000]

Prints, for the torch-free runtime (the exported .npz run by numpy, what the policy node uses) and, for
comparison, for the torch Policy:
- one action on one core: RuntimePolicy.act / Policy.act on one agent's observation (observations of generated
  40x40 episodes), this process pinned to one CPU, one BLAS / torch thread: median and 90th percentile of the
  thread's CPU time and of the wall time (which on a loaded machine also counts waiting for the core);
- start-up to first action of a fresh Python process: import, load the model, act once (wall time from the
  parent's spawn to the child's answer) and that process's RSS;
- the policy node: from spawning `policy_node` to its first AgentAction on the live graph, and its RSS then;
- a robot container with N policy nodes: its RSS divided by N, and the time to its N-th robot's first action.
Targets: <= 150 MB RSS per robot, <= 3 s start-up to first action, <= 1 ms per action on one core.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one BLAS thread, as in the policy node

import numpy as np  # noqa: E402

CHILD = """
import sys, time
t0 = time.perf_counter()
import numpy as np
kind, path = sys.argv[1], sys.argv[2]
if kind == "numpy":
    from mapf_policy.runtime_policy import RuntimePolicy as P
    policy = P(path, seed=0)
else:
    from mapf_policy.policy import Policy as P
    policy = P(path, seed=0)
cfg = policy.cfg
still = [np.eye(cfg.still_bins, dtype=np.float32)[:1]] if cfg.still_bins else []
policy.act(np.zeros((1, cfg.fov_channels, cfg.fov_size, cfg.fov_size), np.float32), np.eye(5, dtype=np.float32)[:1],
           np.zeros((1, 2), np.float32), *still)
rss = [l for l in open('/proc/self/status') if l.startswith('VmRSS')][0].split()[1]
print(f"ready {rss}", flush=True)
"""


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
    return float("nan")


def time_actions(policy, obs: tuple, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(wall, CPU) milliseconds per act() on one agent, over n observations, after 50 untimed calls. The CPU
    time (this thread's) is what one action costs a core; the wall time also holds waits for a busy core."""
    def rows(k: int) -> list:
        return [x[k:k + 1] for x in obs if x is not None]  # fov, last action, position, still input if any

    for k in range(50):
        policy.act(*rows(k))
    wall, cpu = np.empty(n), np.empty(n)
    for k in range(n):
        t0, c0 = time.perf_counter(), time.thread_time()
        policy.act(*rows(k))
        wall[k], cpu[k] = time.perf_counter() - t0, time.thread_time() - c0
    return wall * 1e3, cpu * 1e3


def fresh_process(kind: str, path: Path) -> tuple[float, float]:
    """(seconds from spawn to the first action, RSS MB then) of a new Python process running `kind`."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", CHILD, kind, str(path)], capture_output=True, text=True, env=env)
    elapsed = time.perf_counter() - t0
    if out.returncode != 0 or "ready" not in out.stdout:
        raise RuntimeError(f"{kind} child failed: {out.stderr[-2000:]}")
    return elapsed, int(out.stdout.split()[-1]) / 1024


def first_actions(cmd: list, robots: list[int], domain: int, log: Path, export: Path) -> tuple[float, float]:
    """Start `cmd` (policy node or container, running `export`), publish an all-zero observation shaped for that
    model to each robot until all have answered: (seconds from spawn to the last robot's first action, the
    process's RSS MB then)."""
    from mapf_policy.runtime_policy import RuntimePolicy
    model = RuntimePolicy(export)
    cfg, mode = model.cfg, model.last_action_mode
    from mapf_msgs.msg import AgentAction, AgentObservation
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from mapf_world.fleet_launch import fleet_env
    env = fleet_env(domain)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node("bench_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    answered, pubs = set(), {}
    for i in robots:
        node.create_subscription(AgentAction, f"/robot_{i}/action", lambda m: answered.add(m.robot_id), 10)
        pubs[i] = node.create_publisher(AgentObservation, f"/robot_{i}/observation", 10)
    with open(log, "w") as f:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=env)
    try:
        last_send = 0.0
        while len(answered) < len(robots):
            if proc.poll() is not None or time.perf_counter() - t0 > 120:
                raise RuntimeError(f"no answer from every robot; log {log}:\n{log.read_text()[-2000:]}")
            if time.perf_counter() - last_send > 0.02:
                last_send = time.perf_counter()
                for i in robots:
                    if i not in answered and pubs[i].get_subscription_count():
                        msg = AgentObservation(step=0, robot_id=i, fov_size=cfg.fov_size, fov_channels=cfg.fov_channels,
                                               extra_channels=list(cfg.extra_channels().names), last_action_mode=mode)
                        msg.fov = [0.0] * (cfg.fov_channels * cfg.fov_size ** 2)
                        msg.last_action = [1.0, 0.0, 0.0, 0.0, 0.0]
                        pubs[i].publish(msg)
            executor.spin_once(timeout_sec=0.005)
        elapsed = time.perf_counter() - t0
        return elapsed, rss_mb(proc.pid)
    finally:
        proc.send_signal(2)
        proc.wait(timeout=20)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="scripts/bench_runtime", description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=Path("models/hscl.pt"), help="the torch model; its export is "
                                                                               "the same path with .npz")
    ap.add_argument("--observations", type=int, default=2000, help="timed single-agent actions")
    ap.add_argument("--robots-per-process", type=int, default=32, help="policy nodes in the measured container")
    ap.add_argument("--no-torch", action="store_true", help="skip the torch comparison rows")
    args = ap.parse_args(argv)
    from mapf_policy.export import default_export_path, episode_observations
    from mapf_policy.runtime_policy import RuntimePolicy
    from mapf_world.fleet_launch import claim_domain_id, executable, node_command
    export = default_export_path(args.model)
    cores = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {sorted(cores)[0]})  # one core for the action timings
    obs = episode_observations(args.observations + 50, seed=11, cfg=RuntimePolicy(export).cfg)
    print(f"model {export} (from {args.model}); {args.observations} observations of generated 40x40 episodes; "
          f"load average {os.getloadavg()[0]:.1f}", flush=True)
    rows = [("numpy", RuntimePolicy(export, seed=0))]
    if not args.no_torch:
        from mapf_policy.policy import Policy
        rows.append(("torch", Policy(str(args.model), seed=0)))
    for name, policy in rows:
        wall, cpu = time_actions(policy, obs, args.observations)
        print(f"{name:5s} one action on one core: CPU median {np.median(cpu):.3f} ms, p90 {np.percentile(cpu, 90):.3f} ms; "
              f"wall median {np.median(wall):.3f} ms, p90 {np.percentile(wall, 90):.3f} ms", flush=True)
    os.sched_setaffinity(0, cores)  # the processes below (and their DDS threads) as a robot would run them
    for name in [r[0] for r in rows]:
        elapsed, rss = fresh_process(name, export if name == "numpy" else args.model)
        print(f"{name:5s} fresh process, spawn -> first action: {elapsed:.2f} s, RSS {rss:.0f} MB", flush=True)
    domain, _lock = claim_domain_id(from_top=True)
    logs = Path(os.environ.get("TMPDIR", "/tmp"))
    elapsed, rss = first_actions(node_command("mapf_policy", "policy_node", namespace="/robot_0",
                                              params=dict(model_path=str(export.resolve()))), [0], domain,
                                 logs / "bench_runtime_policy_node.log", export)
    print(f"policy_node (one robot, one process): spawn -> first action {elapsed:.2f} s, RSS {rss:.0f} MB", flush=True)
    n = args.robots_per_process
    cmd = [str(executable("mapf_policy", "robot_container")), "--robots", f"0-{n - 1}", "--nodes", "policy",
           "--policy-param", f"model_path:={export.resolve()}"]
    elapsed, rss = first_actions(cmd, list(range(n)), domain, logs / "bench_runtime_container.log", export)
    print(f"robot_container ({n} policy nodes): spawn -> every robot's first action {elapsed:.2f} s, RSS {rss:.0f} MB, "
          f"{rss / n:.1f} MB per robot")


if __name__ == "__main__":
    main()
