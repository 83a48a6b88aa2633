"""The fleet demo: ground station, recorder and, per robot, a policy node and a drive executor, on their
own ROS_DOMAIN_ID, with the shipped model: a seeded random map, a MovingAI map and scenario, or a case of a
benchmark .npz file.

Usage: scripts/demo [--robots 3] [--out DIR] [--seed S] [--real-time-factor F] [...]
       scripts/demo --npz ../shared/benchmarks/dhc_40x40_d0.3/agents_64.npz --case 0 --robots 64 \
           --robots-per-process 32 --max-steps 256
Every node is its own process, or (--robots-per-process N) the policy nodes of N robots share one robot
container process and their drive executors another (mapf_policy/robot_container.py; each robot keeps its
own nodes, namespace and state). The robots run the exported model (scripts/export_model), without torch.
Runs until every robot is on its goal or the step limit, then prints a summary (steps, success,
failed moves, wall time, CPU and memory per robot or per shared process) and where the MCAP log and the
pictures are.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from mapf_world.fleet_drill import Drill, parse_ids
from mapf_world.fleet_launch import ProcessGroup, executable, fleet_env, node_command, param_value


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
    npz: str = ""
    """Benchmark .npz file instead of a random map: case --case, with all its agents (--robots must match)."""
    case: int = 0
    """Case index in --npz."""
    max_steps: int = 64
    """Step limit of the run."""
    model: str = "models/hscl.pt"
    """Model of the policy (relative: to the repository root): a .pt file, whose export (same path, .npz)
    the robots run after checking it belongs to it, or an exported .npz itself."""
    action_rule: str = "default"
    """Action rule of every robot: 'default' (sampled, the shipped rule) or 'paper' (greedy argmax only)."""
    robots_per_process: int = 0
    """0: every node its own process; N: robot containers of N robots (policy nodes in one, drives in another)."""
    real_time_factor: float = 10.0
    """How much faster than real time the drive executors run (stamps and speeds stay physical)."""
    rate_hz: float = 10.0
    """Control/odometry rate of the drive executors in simulated time."""
    idle_rate_hz: float = 0.0
    """Odometry rate of a robot standing still, in simulated time (0: rate_hz; the first standstill after a
    move is always sent). Fewer messages for large fleets whose robots mostly wait."""
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
    kill_policies: str = ""
    """Fault drill: robot ids (e.g. 0,1,2,3) whose policy nodes run as their own processes, get SIGKILL after
    --kill-after steps and are started again --restart-after steps later (mapf_world/fleet_drill.py)."""
    kill_after: int = 20
    """Fault drill: steps done before the SIGKILL."""
    restart_after: int = 5
    """Fault drill: steps done between the SIGKILL and the restart."""
    pictures: bool = True
    """Draw fleet.png and fleet.gif from the log (--no-pictures: skip; the GIF of a long 64-robot run takes minutes)."""


def parse_args(argv) -> DemoConfig:
    ap = argparse.ArgumentParser(prog="scripts/demo", description=__doc__.split("\n\n")[0])
    defaults = DemoConfig()
    for name, value in asdict(defaults).items():
        if isinstance(value, bool):
            ap.add_argument("--" + name.replace("_", "-"), default=value, action=argparse.BooleanOptionalAction,
                            help=f"{_field_doc(name)} (default {value!r})")
            continue
        ap.add_argument("--" + name.replace("_", "-"), type=type(value), default=value,
                        help=f"{_field_doc(name)} (default {value!r})")
    cfg = DemoConfig(**vars(ap.parse_args(argv)))
    if cfg.robots < 1:
        ap.error(f"--robots must be >= 1, got {cfg.robots}")
    if bool(cfg.map) != bool(cfg.scen):
        ap.error("--map and --scen go together")
    if cfg.npz and cfg.map:
        ap.error("--npz and --map/--scen are two different instance sources: give one")
    if not cfg.real_time_factor > 0:
        ap.error(f"--real-time-factor must be > 0, got {cfg.real_time_factor}")
    if cfg.robots_per_process < 0:
        ap.error(f"--robots-per-process must be >= 0 (0: a process per node), got {cfg.robots_per_process}")
    from mapf_policy.action_selection import RULES
    if cfg.action_rule not in RULES:
        ap.error(f"--action-rule must be one of {sorted(RULES)}, got {cfg.action_rule!r}")
    return cfg


def world_instance_params(cfg: DemoConfig) -> dict:
    """The world node's instance parameters for the demo's instance source."""
    if cfg.npz:
        return dict(instance_source="npz", npz_file=str(Path(cfg.npz).resolve()), npz_index=cfg.case)
    if cfg.map:
        return dict(instance_source="map", map_file=str(Path(cfg.map).resolve()), scen_file=str(Path(cfg.scen).resolve()))
    return dict(instance_source="random", seed=cfg.seed, size=cfg.size, density=cfg.density)


def check_instance(cfg: DemoConfig):
    """The instance the world will run, loaded here first so that bad input stops the demo before any process
    starts; ValueError naming the problem (case index out of range, more robots than the case's agents, ...)."""
    from mapf_world.fleet_core import load_fleet_instance
    params = world_instance_params(cfg)
    if cfg.npz:
        from mapf_world.instances import load_npz
        if not Path(cfg.npz).is_file():
            raise ValueError(f"--npz {cfg.npz} does not exist")
        cases = load_npz(cfg.npz)
        if not 0 <= cfg.case < len(cases):
            raise ValueError(f"--case {cfg.case} is outside 0..{len(cases) - 1}: {cfg.npz} holds {len(cases)} cases")
        agents = cases[cfg.case].n_agents
        if cfg.robots != agents:
            more = "more robots than" if cfg.robots > agents else "fewer robots than"
            raise ValueError(f"--robots {cfg.robots}: {more} the {agents} agents of case {cfg.case} of {cfg.npz} "
                             f"(a benchmark case runs with all its agents: --robots {agents})")
    return load_fleet_instance(params.pop("instance_source"), n_robots=cfg.robots, **params)


def policy_model_params(model: Path) -> tuple[dict, dict]:
    """(policy_node parameters, world_node observation parameters) for `model`: an exported .npz as is; a .pt
    through its export (same path, .npz), which must exist and come from this very file (source_sha256); ValueError
    saying how to make it. The world's parameters say how it must build the robots' observations for this model:
    `last_action` (the export's metadata; older models: 'requested') and, for a model that reads channels beyond
    the paper's six, `extra_channels` (their names, from the export's network config)."""
    from mapf_policy.config import NetworkConfig
    from mapf_policy.runtime_net import file_sha256, read_export

    def world(header: dict) -> dict:
        names = list(NetworkConfig.from_dict(header["network_config"]).extra_channels().names)
        return {"last_action": header["meta"].get("last_action", "requested")} | (
            {"extra_channels": names} if names else {})

    if model.suffix == ".npz":
        header, _ = read_export(model)
        return dict(model_path=str(model)), world(header)
    export = model.with_suffix(".npz")
    if not export.is_file():
        raise ValueError(f"the robots run the export of {model}, and {export} does not exist: "
                         f"scripts/export_model {model}")
    header, _ = read_export(export)
    sha = file_sha256(model)
    if header["source"].get("sha256") != sha:
        raise ValueError(f"{export} was not exported from {model} (its source SHA-256 is "
                         f"{str(header['source'].get('sha256'))[:12]}..., the model's {sha[:12]}...): "
                         f"scripts/export_model {model}")
    return dict(model_path=str(export), source_sha256=sha), world(header)


def robot_chunks(cfg: DemoConfig) -> list[list[int]]:
    """Robot ids per process: one each (robots_per_process 0), else consecutive groups of robots_per_process."""
    ids = list(range(cfg.robots))
    k = cfg.robots_per_process or 1
    return [ids[i:i + k] for i in range(0, len(ids), k)]


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


def start_robots(group: ProcessGroup, cfg: DemoConfig, policy_params: dict, drive_params: dict,
                 own_policy: list[int]) -> tuple[dict, dict]:
    """Start every robot's policy node and drive executor; ({process name: robot ids it serves}, {robot: command
    of its own policy process} for the robots of `own_policy`, which never share a policy process)."""
    served, commands = {}, {}
    for i in own_policy:
        commands[i] = node_command("mapf_policy", "policy_node", namespace=f"/robot_{i}", params=policy_params)
        group.start(f"policy_{i}", commands[i])
        served[f"policy_{i}"] = [i]
    for ids in robot_chunks(cfg):
        if not cfg.robots_per_process:
            if ids[0] in own_policy:
                ns = f"/robot_{ids[0]}"
                group.start(f"drive_{ids[0]}", node_command("mapf_policy", "drive_executor", namespace=ns,
                                                            params=drive_params))
                served[f"drive_{ids[0]}"] = ids
                continue
            ns = f"/robot_{ids[0]}"
            group.start(f"drive_{ids[0]}", node_command("mapf_policy", "drive_executor", namespace=ns, params=drive_params))
            group.start(f"policy_{ids[0]}", node_command("mapf_policy", "policy_node", namespace=ns, params=policy_params))
            served |= {f"policy_{ids[0]}": ids, f"drive_{ids[0]}": ids}
            continue
        span = f"{ids[0]}-{ids[-1]}"
        for kind, params in (("drive", drive_params), ("policy", policy_params)):
            mine = ids if kind == "drive" else [i for i in ids if i not in own_policy]
            if not mine:
                continue
            cmd = [str(executable("mapf_policy", "robot_container")), "--robots", ",".join(map(str, mine)),
                   "--nodes", kind]
            for key, value in params.items():
                cmd += [f"--{kind}-param", f"{key}:={param_value(value)}"]
            group.start(f"{kind}_{span}", cmd)
            served[f"{kind}_{span}"] = mine
    return served, commands


def run(cfg: DemoConfig) -> int:
    root = Path(os.environ.get("MAPF_ROOT", Path.cwd()))
    model = Path(cfg.model) if Path(cfg.model).is_absolute() else root / cfg.model
    if not model.is_file():
        print(f"demo: error: model file {model} not found; train one (scripts/train) or pass --model PATH",
              file=sys.stderr)
        return 2
    try:
        inst = check_instance(cfg)
        from mapf_policy.action_selection import RULES
        from mapf_policy.policy_node import RULE_PARAMETERS
        rule = RULES[cfg.action_rule]
        model_params, observation_params = policy_model_params(model)
        policy_params = model_params | {k: getattr(rule, k) for k in RULE_PARAMETERS}
        drilled = parse_ids(cfg.kill_policies)
        if any(i >= cfg.robots for i in drilled):
            raise ValueError(f"--kill-policies {cfg.kill_policies}: the run has robots 0..{cfg.robots - 1}")
    except (ValueError, OSError) as exc:
        print(f"demo: error: {exc}", file=sys.stderr)
        return 2
    out = Path(cfg.out) if cfg.out else root / "runs" / "fleet" / time.strftime("%Y%m%d-%H%M%S")
    out.mkdir(parents=True, exist_ok=True)
    domain = cfg.domain_id if cfg.domain_id >= 0 else int(os.environ.get("ROS_DOMAIN_ID", 1 + os.getpid() % 100))
    env = fleet_env(domain)
    (out / "config.json").write_text(json.dumps(asdict(cfg) | {"domain_id": domain, "model": str(model),
                                                               "policy": policy_params}, indent=1) + "\n")
    mcap, summary_path = out / "fleet.mcap", out / "summary.json"

    world_params = dict(max_steps=cfg.max_steps, cell_size=cfg.cell_size, action_timeout_s=cfg.action_timeout_s,
                        summary_path=str(summary_path), n_robots=cfg.robots, wait_for_recorder="recorder") \
        | observation_params \
        | world_instance_params(cfg)
    drive_params = dict(cell_size=cfg.cell_size, real_time_factor=cfg.real_time_factor, rate_hz=cfg.rate_hz,
                        idle_rate_hz=cfg.idle_rate_hz)
    group = ProcessGroup(out / "logs", env)
    t0 = time.monotonic()
    print(f"demo: {cfg.robots} robots on {inst.name}, ROS_DOMAIN_ID {domain}, model {policy_params['model_path']}, "
          f"action rule {cfg.action_rule}, output {out}")
    code = 0
    served = {}
    try:
        group.start("recorder", node_command("mapf_world", "recorder", params={"output": str(mcap)}))
        served, commands = start_robots(group, cfg, policy_params, drive_params, drilled)
        drill = Drill(group, drilled, commands, cfg.kill_after, cfg.restart_after)
        group.start("world", node_command("mapf_world", "world_node", params=world_params))
        before = {}
        if wait_for_line(group, "world", ": running", cfg.timeout_s):
            before = {name: group.usage(name) for name in served}
            t_run = time.monotonic()
        world_code = None
        while time.monotonic() - t0 < cfg.timeout_s:
            drill.poll()
            try:
                world_code = group.procs["world"].wait(timeout=0.2)
                break
            except subprocess.TimeoutExpired:
                continue
        else:
            print(f"demo: error: the run did not end within {cfg.timeout_s} s; stopping", file=sys.stderr)
        after = {name: group.usage(name) for name in served}
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

    usage_lines = usage_report(served, before, after, t_end - t_run) if before else []
    walls = summary["step_wall_s"]
    print(f"demo: {summary['state']}: {summary['detail']}")
    print(f"  instance   {summary['instance']}")
    print(f"  steps      {summary['steps']} (limit {summary['max_steps']}), success {summary['success']}, "
          f"failed moves {summary['failed_moves']}, timeouts {summary['timeouts']}, rejected {summary['rejected']}")
    launch = f" (from the demo's launch: {t_run - t0:.2f} s)" if before else ""
    print(f"  wall time  run {summary['wall_s']:.2f} s, startup {summary['startup_s'] or 0:.2f} s{launch}, "
          f"total {t_end - t0:.2f} s; per step mean {summary['mean_step_wall_s']:.3f} s, "
          f"max {max(walls) if walls else 0:.3f} s (real_time_factor {cfg.real_time_factor}); observations out "
          f"-> all actions in: mean {summary['mean_action_wall_s'] * 1000:.1f} ms")
    if usage_lines:
        print("  per robot process, during the run:" if not cfg.robots_per_process else
              "  per shared process (and its share per robot), during the run:")
        print("\n".join(usage_lines))
    for event in drill.events:
        print(f"  fault drill {event}")
    sys.stdout.flush()  # the figures first: reading a 64-robot log back takes minutes on a busy machine
    from mapf_world.fleet_replay import load_run, render, timeline
    log = load_run(mcap)
    if drilled:
        from mapf_world.fleet_check import failed_answers
        by_robot: dict = {}
        for step, robot, why in failed_answers(log.statuses):
            by_robot.setdefault(robot, []).append(f"{step}{'' if why == 'timeout' else ' ' + why}")
        print("  fault drill, robots without a valid action in the log (steps): "
              + ("; ".join(f"robot {r}: {', '.join(v)}" for r, v in sorted(by_robot.items())) or "none"))
    (out / "timeline.txt").write_text("\n".join(timeline(log)) + "\n")
    pictures = render(log, out) if cfg.pictures else []
    print(f"  MCAP log   {mcap} ({log.counts.total()} messages)")
    for p in pictures:
        print(f"  picture    {p}")
    print(f"  timeline   {out / 'timeline.txt'}; summary {summary_path}; logs {out / 'logs'}")
    return 0 if world_code == 0 else 1


def usage_report(served: dict, before: dict, after: dict, span: float) -> list[str]:
    """Lines of CPU and RSS during the run: per robot (a process per node), or per shared process with the
    share of each of its robots, then the totals."""
    total_cpu, total_rss = 0.0, {"policy": 0.0, "drive": 0.0}
    by_robot: dict = {}
    for name, ids in served.items():
        b, a = before.get(name), after.get(name)
        if not (a and b):
            continue
        kind = name.split("_")[0]
        cpu = 100 * (a.cpu_s - b.cpu_s) / span
        total_cpu += cpu
        total_rss[kind] += a.rss_mb
        text = f"{kind} {cpu:.1f}% CPU, {a.rss_mb:.0f} MB RSS (peak {a.peak_rss_mb:.0f} MB)"
        if len(ids) > 1:
            text += f"; per robot {cpu / len(ids):.2f}% CPU, {a.rss_mb / len(ids):.1f} MB RSS"
        by_robot.setdefault(f"robot {ids[0]}" if len(ids) == 1 else f"robots {ids[0]}-{ids[-1]}", []).append(text)
    lines = [f"  {who}: " + "; ".join(parts) for who, parts in by_robot.items()]
    n = len({i for ids in served.values() for i in ids})
    lines.append(f"  all robots: {total_cpu:.1f}% CPU, policy {total_rss['policy']:.0f} MB + drive "
                 f"{total_rss['drive']:.0f} MB RSS; per robot {total_cpu / n:.2f}% CPU, policy "
                 f"{total_rss['policy'] / n:.1f} MB + drive {total_rss['drive'] / n:.1f} MB RSS")
    return lines


def main(argv=None) -> int:
    return run(parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
