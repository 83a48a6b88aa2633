"""Evaluation harness behind scripts/evaluate: any registered solver, step by step through MapfEnv.

Metrics per file (the paper's, plus two that help compare planners):
- success rate: cases where all agents stood on their goals at the same step within max-steps;
- average step: mean over cases of the steps taken, a failed case counting max-steps;
- mean sum of costs: per case, the sum over agents of the step at which the agent last arrived at
  its goal and stayed there to the end of the run (0 if it never left its start on the goal); an
  agent off its goal at the end counts the case's steps (max-steps for a failed case);
- wall time of the file.
Every run is checked with validate_solution before it is counted.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from mapf_world.env import MapfEnv
from mapf_world.instances import Instance, load_npz
from mapf_world.solvers import REGISTRY, PlanFailed, Solver, get_solver
from mapf_world.validate import validate_solution


@dataclass
class CaseResult:
    index: int
    steps: int  # max_steps for failed cases
    success: bool
    sum_of_costs: int
    failed_moves: int
    reason: str | None  # None on success; "max_steps", or PlanFailed.reason ("unsolvable", "timeout")
    seconds: float
    positions: np.ndarray = field(repr=False)  # (steps+1, N, 2): the agents' cells at every counted step


def sum_of_costs(positions: np.ndarray, goals: np.ndarray, steps: int) -> int:
    """Sum over agents of the step from which each stays on its goal to the end; `steps` if off goal."""
    on_goal = np.all(positions == goals[None], axis=2)  # (T+1, N)
    total = 0
    for i in range(on_goal.shape[1]):
        col = on_goal[:, i]
        if not col[-1]:
            total += steps
            continue
        off = np.flatnonzero(~col)
        total += 0 if off.size == 0 else int(off[-1]) + 1
    return total


def run_case(solver: Solver, inst: Instance, max_steps: int, index: int = 0) -> CaseResult:
    """One case step by step. Its trajectory holds the agents' cells at every step it counts:
    steps+1 frames, steps = the success step, or max_steps for a failed case. When the solver gives
    up (PlanFailed: a planner that timed out or found no plan), its robots have no plan and stand
    still, so the rest of the episode is played with every agent staying, up to max_steps."""
    t0 = time.perf_counter()
    # A learned solver's observations carry the last action the way its model was trained, and the channels its
    # network reads (MapfEnv keyword arguments, `env_channels`); planners read neither.
    env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=max_steps,
                  last_action=getattr(solver, "last_action", "requested"), **getattr(solver, "env_channels", {}))
    obs, info = env.reset()
    trajectory = [env.positions]
    failed_moves = 0
    reason = None
    success = bool(info["success"])
    done = success  # a case solved at the start asks the solver nothing
    try:
        if not done:
            solver.reset(env)
        while not done:
            obs, _, terminated, truncated, info = env.step(solver.act(obs))
            trajectory.append(env.positions)
            failed_moves += int(info["failed"].sum())
            success = bool(info["success"])
            done = terminated or truncated
        if not success:
            reason = "max_steps"
    except PlanFailed as exc:
        reason = exc.reason
        stay = np.zeros(len(inst.starts), dtype=np.int64)
        while not done:
            obs, _, terminated, truncated, info = env.step(stay)
            trajectory.append(env.positions)
            done = terminated or truncated
        success = False  # the solver failed, even if standing still ended on the goals (it cannot)
    seconds = time.perf_counter() - t0
    positions = np.stack(trajectory)
    validate_solution(inst.grid, inst.starts, inst.goals, positions, success=success)
    steps = env.step_count if success else max_steps
    if positions.shape[0] != steps + 1:
        raise RuntimeError(f"case {index}: {positions.shape[0]} frames for {steps} counted steps")
    soc = sum_of_costs(positions, inst.goals, steps)
    return CaseResult(index, steps, success, soc, failed_moves, reason, seconds, positions)


def evaluate_file(
    solver: Solver | str, instances: list[Instance], max_steps: int = 256, progress=None
) -> list[CaseResult]:
    """Run `solver` (an object or a registry name) on every instance; `progress(result)` after each."""
    if isinstance(solver, str):
        solver = get_solver(solver)
    results = []
    for k, inst in enumerate(instances):
        results.append(run_case(solver, inst, max_steps, index=k))
        if progress is not None:
            progress(results[-1])
    return results


def summarize(results: list[CaseResult], solver_name: str, n_agents: int, wall_time: float) -> dict:
    n = len(results)
    return {
        "solver": solver_name,
        "agents": n_agents,
        "cases": n,
        "success_rate": sum(r.success for r in results) / n if n else float("nan"),
        "average_step": float(np.mean([r.steps for r in results])) if n else float("nan"),
        "mean_sum_of_costs": float(np.mean([r.sum_of_costs for r in results])) if n else float("nan"),
        "wall_time_s": wall_time,
    }


def trajectories_arrays(results: list[CaseResult], max_steps: int) -> dict:
    """The trajectory file (docs/ARCHITECTURE.md, "Trajectory files"): positions (K, T+1, N, 2) int16,
    case k's real cells in frames 0..steps[k] and its last cells repeated after them up to the
    longest case; steps (K,); success (K,); max_steps (the episode limit, a scalar)."""
    t_max = max(r.positions.shape[0] for r in results)
    padded = []
    for r in results:
        pad = np.repeat(r.positions[-1:], t_max - r.positions.shape[0], axis=0)
        padded.append(np.concatenate([r.positions, pad]))
    return {
        "positions": np.stack(padded).astype(np.int16),
        "steps": np.array([r.steps for r in results], dtype=np.int32),
        "success": np.array([r.success for r in results], dtype=bool),
        "max_steps": np.int32(max_steps),
    }


ROW = "{solver:<28} {agents:>6} {cases:>6} {success:>8} {avg:>9} {soc:>10} {wall:>9}"


def _row(s: dict) -> str:
    return ROW.format(
        solver=s["solver"], agents=s["agents"], cases=s["cases"], success=f"{s['success_rate']:.3f}",
        avg=f"{s['average_step']:.2f}", soc=f"{s['mean_sum_of_costs']:.1f}", wall=f"{s['wall_time_s']:.1f}s",
    )


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="scripts/evaluate",
        description=__doc__.split("\n\n")[0] + " Known solvers: " + ", ".join(sorted(REGISTRY)) + ".",
        epilog="Sum of costs: sum over agents of the step at which each agent last arrived at its goal and "
               "stayed there; an agent not on its goal at the end counts the case's steps (max-steps when "
               "the case failed). Average step counts max-steps for a failed case.",
    )
    p.add_argument("--solver", required=True, metavar="NAME", help="registered solver name")
    p.add_argument("--instances", required=True, nargs="+", type=Path, metavar="FILE.npz",
                   help="benchmark .npz file(s)")
    p.add_argument("--cases", type=int, default=None, metavar="K",
                   help="use the first K cases of each file (default: all)")
    p.add_argument("--max-steps", type=int, default=256, metavar="T", help="episode limit (default 256)")
    p.add_argument("--json", type=Path, default=None, metavar="OUT.json",
                   help="write the table and per-case results here")
    p.add_argument("--trajectories", type=Path, default=None, metavar="OUT.npz",
                   help="write positions/steps/success .npz here (with several files: one per file, "
                        "named <OUT stem>.<instances stem>.npz)")
    p.add_argument("--epsilon", type=float, default=None, metavar="EPS", help="solver option (ODrM* inflation)")
    p.add_argument("--time-limit", type=float, default=None, metavar="SECONDS",
                   help="solver option (planning seconds per case)")
    p.add_argument("--model", type=Path, default=None, metavar="PATH", help="solver option (policy weights)")
    p.add_argument("--action-rule", default=None, metavar="NAME",
                   help="solver option (learned policies): 'default' (sampled, the shipped rule) or 'paper' "
                        "(greedy argmax only); the options below replace single fields of it")
    p.add_argument("--action-temperature", type=float, default=None, metavar="T",
                   help="solver option (learned policies): sample actions from softmax(Q/T); 0 = greedy argmax "
                        "(default: the solver's own, see its settings in the JSON)")
    p.add_argument("--backtrack-penalty", type=float, default=None, metavar="P",
                   help="solver option (learned policies): Q-value penalty on moving back to the previous cell; 0 = off")
    p.add_argument("--mask-obstacle-moves", default=None, action=argparse.BooleanOptionalAction,
                   help="solver option (learned policies): never choose a move into an obstacle or off the map")
    p.add_argument("--seed", type=int, default=None, metavar="S",
                   help="solver option (learned policies): seed of the action sampling, restarted at each case")
    p.add_argument("--per-agent-seeds", action="store_true",
                   help="solver option (learned policies): agent i samples from its own generator seeded with seed + i, "
                        "as robot i of the fleet does (policy_node seed -1), so a sampled run equals the fleet's")
    args = p.parse_args(argv)
    if args.cases is not None and args.cases < 1:
        p.error(f"--cases must be >= 1, got {args.cases}")
    if args.max_steps < 1:
        p.error(f"--max-steps must be >= 1, got {args.max_steps}")
    return args


def _trajectory_path(out: Path, source: Path, several: bool) -> Path:
    return out.with_name(f"{out.stem}.{source.stem}.npz") if several else out


def main(argv=None) -> int:
    args = parse_args(argv)
    options = {k: v for k, v in (("epsilon", args.epsilon), ("time_limit", args.time_limit), ("model", args.model),
                                 ("action_rule", args.action_rule), ("action_temperature", args.action_temperature),
                                 ("backtrack_penalty", args.backtrack_penalty),
                                 ("mask_obstacle_moves", args.mask_obstacle_moves), ("seed", args.seed),
                                 ("per_agent_seeds", args.per_agent_seeds or None))
               if v is not None}
    try:
        solver = get_solver(args.solver, **options)
        files = [(path, load_npz(path)) for path in args.instances]
        for path, instances in files:
            if args.cases is not None and args.cases > len(instances):
                raise ValueError(f"{path}: --cases {args.cases} but the file holds {len(instances)} cases")
    except (ValueError, OSError) as exc:
        print(f"evaluate: error: {exc}", file=sys.stderr)
        return 2
    from tqdm import tqdm

    report = {"solver": args.solver, "options": {k: str(v) for k, v in options.items()},
              "settings": getattr(solver, "settings", {}),
              "max_steps": args.max_steps, "files": []}
    print(ROW.format(solver="solver", agents="agents", cases="cases", success="success", avg="avg_step",
                     soc="mean_soc", wall="wall"))
    for path, instances in files:
        instances = instances[: args.cases] if args.cases else instances
        start = time.perf_counter()
        solved = [0]

        with tqdm(total=len(instances), desc=path.name, file=sys.stderr, leave=False) as bar:
            def progress(result: CaseResult) -> None:
                solved[0] += result.success
                bar.set_postfix(solved=solved[0], refresh=False)
                bar.update(1)

            results = evaluate_file(solver, instances, args.max_steps, progress=progress)
        summary = summarize(results, args.solver, instances[0].n_agents, time.perf_counter() - start)
        print(_row(summary), flush=True)
        cases = [{f.name: getattr(r, f.name) for f in fields(CaseResult) if f.name != "positions"} for r in results]
        report["files"].append({"file": str(path), **summary, "results": cases})
        if args.trajectories:
            out = _trajectory_path(args.trajectories, path, len(files) > 1)
            np.savez_compressed(out, **trajectories_arrays(results, args.max_steps))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
