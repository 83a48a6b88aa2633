"""Benchmark of the centralized planners on the DHC test set (behind scripts/bench_planners).

Every plan is executed step by step through MapfEnv by the evaluation harness (evaluate.run_case),
so "average step" means what it means for a learned policy: steps taken, 256 for a failed case.
Per team size it prints solved cases (and how the others ended), average step, mean sum of costs
over solved cases, the median and 90th percentile of planner seconds per case (PlanResult.seconds:
checks + search + validation, not the MapfEnv replay), next to the reference row of issue 3 (the
C++ ODrM* of PRIMAL, epsilon = 10, 10 s per case, run on this machine).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mapf_world.evaluate import run_case
from mapf_world.instances import load_npz
from mapf_world.planners.odrmstar import OBJECTIVES
from mapf_world.planners.solvers import make_cbs, make_odrmstar

SIZES = (4, 8, 16, 32, 64)
SET_NAME = "dhc_40x40_d0.3"
DEFAULT_ROOT = Path("/work/shared/benchmarks")
# Issue 3: C++ ODrM* (epsilon 10, 10 s per case): solved, average step, median seconds per case.
REFERENCE = {4: (200, 49.74, 0.004), 8: (200, 54.91, 0.009), 16: (200, 61.74, 0.019),
             32: (200, 67.46, 0.040), 64: (196, 81.60, 0.104)}


@dataclass
class BenchConfig:
    """One benchmark run."""

    solver: str = "odrmstar"  # odrmstar | cbs
    bench_dir: Path | None = None  # folder with agents_NN.npz (default: see resolve_bench_dir)
    sizes: tuple[int, ...] = SIZES  # team sizes to run
    cases: int | None = None  # first K cases of each file (default: all 200)
    time_limit: float = 10.0  # planner seconds per case
    epsilon: float = 10.0  # ODrM* inflation
    objective: str = "free_goal_wait"  # ODrM* objective (planners/odrmstar.py)
    max_steps: int = 256  # episode limit of the replay (and the step count of a failed case)
    json: Path | None = None  # per-case results here


def resolve_bench_dir(bench_dir: Path | None) -> Path:
    """--bench-dir, else MAPF_BENCHMARK_DIR (the benchmarks root holding dhc_40x40_d0.3/, as in
    tests/conftest.py, or that folder itself), else /work/shared/benchmarks/dhc_40x40_d0.3."""
    if bench_dir is None:
        root = Path(os.environ.get("MAPF_BENCHMARK_DIR", DEFAULT_ROOT))
        bench_dir = root / SET_NAME if (root / SET_NAME).is_dir() else root
    if not bench_dir.is_dir():
        raise ValueError(f"benchmark folder {bench_dir} not found (use --bench-dir or MAPF_BENCHMARK_DIR)")
    return bench_dir


def make_solver(cfg: BenchConfig):
    if cfg.solver == "odrmstar":
        return make_odrmstar(epsilon=cfg.epsilon, time_limit=cfg.time_limit, objective=cfg.objective)
    if cfg.solver == "cbs":
        return make_cbs(time_limit=cfg.time_limit)
    raise ValueError(f"unknown solver {cfg.solver!r} (odrmstar or cbs)")


def run_size(cfg: BenchConfig, path: Path, solver) -> dict:
    from tqdm import tqdm

    instances = load_npz(path)
    instances = instances[: cfg.cases] if cfg.cases else instances
    rows = []
    with tqdm(total=len(instances), desc=path.name, file=sys.stderr, leave=False) as bar:
        for k, inst in enumerate(instances):
            res = run_case(solver, inst, cfg.max_steps, index=k)
            plan = solver.last_result
            if res.failed_moves:
                raise RuntimeError(f"{path.name} case {k}: {res.failed_moves} failed moves replaying the plan")
            rows.append({"case": k, "success": res.success, "steps": res.steps, "reason": res.reason,
                         "sum_of_costs": res.sum_of_costs if res.success else None,
                         "plan_status": plan.status, "plan_seconds": plan.seconds, "expansions": plan.expansions})
            bar.set_postfix(solved=sum(r["success"] for r in rows), refresh=False)
            bar.update(1)
    secs = np.array([r["plan_seconds"] for r in rows])
    solved = [r for r in rows if r["success"]]
    n = instances[0].n_agents
    return {
        "agents": n, "cases": len(rows), "solved": len(solved),
        "unsolvable": sum(r["plan_status"] == "unsolvable" for r in rows),
        "timeout": sum(r["plan_status"] == "timeout" for r in rows),
        "average_step": float(np.mean([r["steps"] for r in rows])),
        "mean_sum_of_costs_solved": float(np.mean([r["sum_of_costs"] for r in solved])) if solved else float("nan"),
        "median_seconds": float(np.median(secs)), "p90_seconds": float(np.percentile(secs, 90)),
        "max_seconds": float(secs.max()), "results": rows,
    }


HEADER = (f"{'agents':>6} {'cases':>5} {'solved':>6} {'unsolv':>6} {'tmout':>5} {'avg_step':>8} {'ref':>6} "
          f"{'diff%':>6} {'soc(solved)':>11} {'med_s':>7} {'p90_s':>7} {'ref_med_s':>9} {'ref_solved':>10}")


def format_row(s: dict) -> str:
    ref = REFERENCE.get(s["agents"])
    ref_step = f"{ref[1]:.2f}" if ref else "-"
    diff = f"{100 * (s['average_step'] / ref[1] - 1):+.1f}" if ref else "-"
    ref_med = f"{ref[2]:.3f}" if ref else "-"
    ref_solved = f"{ref[0]}/200" if ref else "-"
    return (f"{s['agents']:>6} {s['cases']:>5} {s['solved']:>6} {s['unsolvable']:>6} {s['timeout']:>5} "
            f"{s['average_step']:>8.2f} {ref_step:>6} {diff:>6} {s['mean_sum_of_costs_solved']:>11.1f} "
            f"{s['median_seconds']:>7.3f} {s['p90_seconds']:>7.3f} {ref_med:>9} {ref_solved:>10}")


def parse_args(argv=None) -> BenchConfig:
    p = argparse.ArgumentParser(prog="scripts/bench_planners", description=__doc__.split("\n\n")[0])
    p.add_argument("--solver", choices=("odrmstar", "cbs"), default="odrmstar")
    p.add_argument("--bench-dir", type=Path, default=None,
                   help="folder with agents_NN.npz (default: $MAPF_BENCHMARK_DIR/dhc_40x40_d0.3, else "
                        "/work/shared/benchmarks/dhc_40x40_d0.3)")
    p.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="team sizes (default: all five)")
    p.add_argument("--cases", type=int, default=None, help="first K cases per file (default: all)")
    p.add_argument("--time-limit", type=float, default=10.0, help="planner seconds per case (default 10)")
    p.add_argument("--epsilon", type=float, default=10.0, help="ODrM* inflation (default 10)")
    p.add_argument("--objective", choices=sorted(OBJECTIVES), default="free_goal_wait", help="ODrM* objective")
    p.add_argument("--json", type=Path, default=None, help="write the summary and per-case results here")
    a = p.parse_args(argv)
    if a.cases is not None and a.cases < 1:
        p.error(f"--cases must be >= 1, got {a.cases}")
    return BenchConfig(solver=a.solver, bench_dir=a.bench_dir, sizes=tuple(a.sizes), cases=a.cases,
                       time_limit=a.time_limit, epsilon=a.epsilon, objective=a.objective, json=a.json)


def main(argv=None) -> int:
    cfg = parse_args(argv)
    try:
        bench_dir = resolve_bench_dir(cfg.bench_dir)
        paths = [bench_dir / f"agents_{n:02d}.npz" for n in cfg.sizes]
        missing = [str(p) for p in paths if not p.is_file()]
        if missing:
            raise ValueError(f"missing benchmark file(s): {', '.join(missing)}")
        solver = make_solver(cfg)
    except ValueError as exc:
        print(f"bench_planners: error: {exc}", file=sys.stderr)
        return 2
    shown = {k: str(v) for k, v in asdict(cfg).items()}
    if cfg.solver == "cbs":
        shown.pop("epsilon"), shown.pop("objective")
    print(f"config: {shown} bench_dir={bench_dir}")
    print(HEADER, flush=True)
    summaries = []
    start = time.perf_counter()
    for path in paths:
        s = run_size(cfg, path, solver)
        summaries.append(s)
        print(format_row(s), flush=True)
    print(f"wall time {time.perf_counter() - start:.1f} s; reference: C++ ODrM* of PRIMAL, epsilon 10, 10 s per case "
          "(issue 3); seconds are planner seconds per case")
    if cfg.json:
        cfg.json.parent.mkdir(parents=True, exist_ok=True)
        cfg.json.write_text(json.dumps({"config": shown, "sizes": summaries}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
