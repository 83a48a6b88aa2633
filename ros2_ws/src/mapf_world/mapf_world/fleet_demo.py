"""The fleet demo: ground station, recorder and, per robot, a policy node and a drive executor, each
its own process on its own ROS_DOMAIN_ID, on a seeded 0.3-density map with the shipped model.

Usage: scripts/demo [--robots 3] [--out DIR] [--seed S] [--real-time-factor F] [...]
Runs until every robot is on its goal or the step limit, then prints a summary (steps, success,
failed moves, wall time, CPU and memory per robot) and where the MCAP log and the pictures are.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from mapf_world.fleet_launch import ProcessGroup, node_command


@dataclass
class DemoConfig:
    robots: int = 3
    """Number of robots (one policy node and one drive executor each)."""
    seed: int = 0
    """Seed of the random instance."""
    size: int = 10
    """Side of the square random map (cells)."""
    density: float = 0.3
    """Obstacle density of the random map (the paper's real experiment: 0.3)."""
    map: str = ""
    """MovingAI .map instead of a random map (needs --scen)."""
    scen: str = ""
    """MovingAI .scen: the first --robots agents."""
    max_steps: int = 64
    """Step limit of the run."""
    model: str = "models/hscl.pt"
    """Model file of the policy (relative: to the repository root)."""
    real_time_factor: float = 10.0
    """How much faster than real time the drive executors run (stamps and speeds stay physical)."""
    rate_hz: float = 10.0
    """Control/odometry rate of the drive executors in simulated time."""
    cell_size: float = 0.3
    """Metres per cell."""
    action_timeout_s: float = 2.0
    """Wall seconds the world waits for an action."""
    domain_id: int = -1
    """ROS_DOMAIN_ID of the run (-1: from the environment, else derived from the process id)."""
    out: str = ""
    """Output directory (default runs/fleet/<time>)."""
    timeout_s: float = 300.0
    """Give up (and stop everything) after this many wall seconds."""


def parse_args(argv) -> DemoConfig:
    ap = argparse.ArgumentParser(prog="scripts/demo", description=__doc__.split("\n\n")[0])
    defaults = DemoConfig()
    for name, value in asdict(defaults).items():
        ap.add_argument("--" + name.replace("_", "-"), type=type(value), default=value,
                        help=f"{_field_doc(name)} (default {value!r})")
    cfg = DemoConfig(**vars(ap.parse_args(argv)))
    if cfg.robots < 1:
        ap.error(f"--robots must be >= 1, got {cfg.robots}")
    if bool(cfg.map) != bool(cfg.scen):
        ap.error("--map and --scen go together")
    if not cfg.real_time_factor > 0:
        ap.error(f"--real-time-factor must be > 0, got {cfg.real_time_factor}")
    return cfg


def _field_doc(name: str) -> str:
    import inspect
    src = inspect.getsource(DemoConfig)
    lines = src.splitlines()
    for k, line in enumerate(lines):
        if line.strip().startswith(f"{name}:") and k + 1 < len(lines):
            return lines[k + 1].strip().strip('"')
    return ""


def wait_for_line(group: ProcessGroup, name: str, text: str, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if text in group.log_text(name):
            return True
        if group.procs[name].poll() is not None:
            return False
        time.sleep(0.1)
    return False


def run(cfg: DemoConfig) -> int:
    root = Path(os.environ.get("MAPF_ROOT", Path.cwd()))
    model = Path(cfg.model) if Path(cfg.model).is_absolute() else root / cfg.model
    if not model.is_file():
        print(f"demo: error: model file {model} not found; train one (scripts/train) or pass --model PATH",
              file=sys.stderr)
        return 2
    out = Path(cfg.out) if cfg.out else root / "runs" / "fleet" / time.strftime("%Y%m%d-%H%M%S")
    out.mkdir(parents=True, exist_ok=True)
    domain = cfg.domain_id if cfg.domain_id >= 0 else int(os.environ.get("ROS_DOMAIN_ID", 1 + os.getpid() % 100))
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    (out / "config.json").write_text(json.dumps(asdict(cfg) | {"domain_id": domain, "model": str(model)}, indent=1) + "\n")
    mcap, summary_path = out / "fleet.mcap", out / "summary.json"

    world_params = dict(max_steps=cfg.max_steps, cell_size=cfg.cell_size, action_timeout_s=cfg.action_timeout_s,
                        summary_path=str(summary_path), n_robots=cfg.robots)
    if cfg.map:
        world_params |= dict(instance_source="map", map_file=str(Path(cfg.map).resolve()),
                             scen_file=str(Path(cfg.scen).resolve()))
    else:
        world_params |= dict(instance_source="random", seed=cfg.seed, size=cfg.size, density=cfg.density)
    group = ProcessGroup(out / "logs", env)
    robots = [f"{kind}_{i}" for i in range(cfg.robots) for kind in ("policy", "drive")]
    t0 = time.monotonic()
    print(f"demo: {cfg.robots} robots, ROS_DOMAIN_ID {domain}, model {model}, output {out}")
    code = 0
    try:
        group.start("recorder", node_command("mapf_world", "recorder", params={"output": str(mcap)}))
        for i in range(cfg.robots):
            ns = f"/robot_{i}"
            group.start(f"drive_{i}", node_command("mapf_policy", "drive_executor", namespace=ns, params=dict(
                cell_size=cfg.cell_size, real_time_factor=cfg.real_time_factor, rate_hz=cfg.rate_hz)))
            group.start(f"policy_{i}", node_command("mapf_policy", "policy_node", namespace=ns,
                                                    params=dict(model_path=str(model))))
        group.start("world", node_command("mapf_world", "world_node", params=world_params))
        before = {}
        if wait_for_line(group, "world", ": running", cfg.timeout_s):
            before = {name: group.usage(name) for name in robots}
            t_run = time.monotonic()
        try:
            world_code = group.procs["world"].wait(timeout=max(1.0, cfg.timeout_s - (time.monotonic() - t0)))
        except Exception:
            print(f"demo: error: the run did not end within {cfg.timeout_s} s; stopping", file=sys.stderr)
            world_code = None
        after = {name: group.usage(name) for name in robots}
        t_end = time.monotonic()
    finally:
        codes = group.stop_all([n for n in group.procs if n != "recorder"])
        codes |= group.stop_all(["recorder"])
    bad = {n: c for n, c in codes.items() if c not in (0, None) and n != "world"}
    if world_code is None or world_code == 2 or not summary_path.is_file():
        tail = group.log_text("world").splitlines()[-15:]
        print("demo: error: the world node did not finish; its log ends:\n  " + "\n  ".join(tail), file=sys.stderr)
        return 1
    if bad:
        print(f"demo: warning: processes exited with errors: {bad} (logs in {out / 'logs'})", file=sys.stderr)
    summary = json.loads(summary_path.read_text())

    from mapf_world.fleet_replay import load_run, render, timeline
    log = load_run(mcap)
    (out / "timeline.txt").write_text("\n".join(timeline(log)) + "\n")
    pictures = render(log, out)

    usage_lines = []
    if before:
        span = t_end - t_run
        for i in range(cfg.robots):
            parts = []
            for kind in ("policy", "drive"):
                b, a = before.get(f"{kind}_{i}"), after.get(f"{kind}_{i}")
                if a and b:
                    parts.append(f"{kind} {100 * (a.cpu_s - b.cpu_s) / span:.1f}% CPU, {a.rss_mb:.0f} MB RSS "
                                 f"(peak {a.peak_rss_mb:.0f} MB)")
            usage_lines.append(f"  robot {i}: " + "; ".join(parts))
    walls = summary["step_wall_s"]
    print(f"demo: {summary['state']}: {summary['detail']}")
    print(f"  instance   {summary['instance']}")
    print(f"  steps      {summary['steps']} (limit {summary['max_steps']}), success {summary['success']}, "
          f"failed moves {summary['failed_moves']}, timeouts {summary['timeouts']}, rejected {summary['rejected']}")
    print(f"  wall time  run {summary['wall_s']:.2f} s, startup {summary['startup_s'] or 0:.2f} s, "
          f"total {t_end - t0:.2f} s; per step mean {summary['mean_step_wall_s']:.3f} s, "
          f"max {max(walls) if walls else 0:.3f} s (real_time_factor {cfg.real_time_factor}); observations out "
          f"-> all actions in: mean {summary['mean_action_wall_s'] * 1000:.1f} ms")
    if usage_lines:
        print("  per robot process, during the run:")
        print("\n".join(usage_lines))
    print(f"  MCAP log   {mcap} ({log.counts.total()} messages)")
    for p in pictures:
        print(f"  picture    {p}")
    print(f"  timeline   {out / 'timeline.txt'}; summary {summary_path}; logs {out / 'logs'}")
    return 0 if world_code == 0 else 1


def main(argv=None) -> int:
    return run(parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
