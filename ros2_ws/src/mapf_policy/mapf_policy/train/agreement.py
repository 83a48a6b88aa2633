"""Where a model disagrees with the expert: `scripts/expert_agreement`.

Training logs one agreement figure (argmax Q = expert action, over a batch). Most rows of a large team's
episode are agents waiting on their goals or walking in free space, where agreement is near 1, so that
figure hides the crowded states where teams jam. This tool plays generated held-out episodes (seed stream
COMPARE_STREAM, never benchmark cases) with each model, as the training actors do (softmax(Q / T) with
settled agents greedy, no epsilon), labels every visited state with the expert (ODrM*) until its time
budget is spent, and reports agreement per situation:
  on goal   the agent stands on its goal (action_selection.on_goal);
  crowd     other agents in its field of view: 0-1, 2-3, 4 or more.
Each model meets the same instances but visits its own states, which is what its behaviour depends on.
  scripts/expert_agreement models/hscl.pt runs/<run>/last.pt --sizes 32 64 --cases 4 --seed 16
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from mapf_policy.action_selection import on_goal
from mapf_policy.inference import InferenceNet
from mapf_policy.model_io import load_model
from mapf_policy.train.actor import run_episode
from mapf_policy.train.demos import COMPARE_STREAM, generated_cases
from mapf_policy.train.expert import make_oracle
from mapf_policy.train.replay import to_tensors
from mapf_world.env import MapfEnv

# Crowd buckets: (label, smallest, largest) count of other agents in the field of view.
CROWDS = (("0-1", 0, 1), ("2-3", 2, 3), ("4+", 4, 10**9))


def situations(fov: np.ndarray) -> dict:
    """(B,) bool masks by situation from (B, 6, l, l) observations: 'on goal' / 'off goal' x crowd bucket."""
    c = fov.shape[-1] // 2
    goal = on_goal(fov)
    others = fov[:, 1].reshape(len(fov), -1).sum(axis=1) - fov[:, 1, c, c]
    out = {}
    for where, mask in (("on goal", goal), ("off goal", ~goal)):
        for label, lo, hi in CROWDS:
            out[f"{where}, {label} in view"] = mask & (others >= lo) & (others <= hi)
    return out


def tally(q: np.ndarray, expert: np.ndarray, fov: np.ndarray) -> dict:
    """{situation: {rows, agree}} counts over the labelled rows (expert >= 0), plus 'all'."""
    labelled = expert >= 0
    agree = (q.argmax(axis=1) == expert) & labelled
    out = {"all": {"rows": int(labelled.sum()), "agree": int(agree.sum())}}
    for name, mask in situations(fov).items():
        out[name] = {"rows": int((mask & labelled).sum()), "agree": int((mask & agree).sum())}
    return out


def add_tallies(a: dict, b: dict) -> dict:
    return {k: {f: a.get(k, {}).get(f, 0) + v[f] for f in ("rows", "agree")} for k, v in b.items()}


def model_agreement(path, instances: list, action_temperature: float, oracle_budget: float,
                    expert_epsilon: float, progress: bool, max_steps: int = 256) -> dict:
    """Summed tallies over the instances for one model file, and the episodes' outcomes."""
    net, ncfg, _ = load_model(path)  # a clear error for a missing, corrupt or foreign file
    forward = InferenceNet(net.eval())
    totals, solved = {}, 0
    for k, inst in enumerate(tqdm(instances, desc=Path(path).name, unit="episode", disable=not progress)):
        env = MapfEnv(inst.grid, inst.starts, inst.goals, fov_size=ncfg.fov_size, max_steps=max_steps)
        oracle = make_oracle("odrmstar", env.grid, env.goals, env.dist, expert_epsilon, oracle_budget)
        rng = np.random.default_rng(k)
        rec, stats = run_episode(forward, env, 0.0, rng, oracle, oracle_budget, action_temperature=action_temperature)
        rows = rec.arrays()
        t = to_tensors(rows, torch.device("cpu"))
        with torch.inference_mode():
            q = forward(t["fov"], t["last_action"], t["position"])
        totals = add_tallies(totals, tally(q.numpy(), rows["expert"].astype(np.int64), rows["fov"]))
        solved += int(stats["success"])
    return {"tallies": totals, "episodes": len(instances), "solved": solved}


def markdown(results: dict) -> str:
    names = list(next(iter(results.values()))["tallies"])
    head = "| situation | " + " | ".join(f"{Path(p).name}: agreement (rows)" for p in results) + " |"
    rows = [head, "|" + "---|" * (len(results) + 1)]
    for name in names:
        cells = []
        for r in results.values():
            t = r["tallies"].get(name, {"rows": 0, "agree": 0})
            cells.append(f"{t['agree'] / t['rows']:.3f} ({t['rows']})" if t["rows"] else "- (0)")
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    rows.append("| episodes solved | " + " | ".join(f"{r['solved']}/{r['episodes']}" for r in results.values()) + " |")
    return "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/expert_agreement", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("models", nargs="+", help="model files")
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64], help="team sizes (default 32 64)")
    p.add_argument("--cases", type=int, default=4, help="episodes per team size (default 4)")
    p.add_argument("--seed", type=int, default=0, help="seed of the held-out instances (default 0)")
    p.add_argument("--action-temperature", type=float, default=0.04, metavar="T",
                   help="the episodes' actions: softmax(Q/T), settled agents greedy; 0 = argmax (default 0.04)")
    p.add_argument("--expert-budget", type=float, default=15.0, metavar="S",
                   help="seconds of ODrM* planning per episode; later states stay unlabelled (default 15)")
    p.add_argument("--expert-epsilon", type=float, default=10.0, help="ODrM* suboptimality bound (default 10)")
    p.add_argument("--map-size", type=int, default=40)
    p.add_argument("--density", type=float, default=0.3)
    p.add_argument("--max-steps", type=int, default=256)
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--json", type=Path, help="also write the tallies here")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    bad = [n for n in args.sizes + [args.cases, args.max_steps] if n < 1]
    if bad:
        p.error(f"--sizes, --cases and --max-steps must be positive, got {bad}")
    if not (args.action_temperature >= 0 and args.expert_budget > 0 and args.expert_epsilon >= 1):
        p.error("--action-temperature must be >= 0, --expert-budget > 0 and --expert-epsilon >= 1")
    missing = [m for m in args.models if not Path(m).is_file()]
    if missing:
        p.error(f"no such model file: {', '.join(missing)}")
    torch.set_num_threads(args.threads)
    instances = generated_cases(args.seed, COMPARE_STREAM, args.sizes, args.cases, args.map_size, args.density)
    try:
        results = {str(m): model_agreement(m, instances, args.action_temperature, args.expert_budget,
                                           args.expert_epsilon, not args.no_progress, args.max_steps)
                   for m in args.models}
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(markdown(results))
    if args.json:
        args.json.write_text(json.dumps({"sizes": args.sizes, "cases": args.cases, "seed": args.seed,
                                         "action_temperature": args.action_temperature,
                                         "expert_budget": args.expert_budget, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
