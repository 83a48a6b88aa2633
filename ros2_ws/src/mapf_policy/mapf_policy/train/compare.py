"""Compare model files on generated held-out cases (never benchmark cases): `scripts/compare_models`.

For ablations and snapshot choice. Every model meets the same cases: seed stream COMPARE_STREAM,
apart from the demonstration, actor and validation streams, so no model trained on them. Actions by
the paper's greedy rule by default (--action-rule paper, so that snapshot tables stay comparable); with
another rule they are chosen as by `scripts/evaluate --solver hscl` with the same rule options, the
generator restarting from --sample-seed at each case. The benchmark's rules and step limit; average step
counts the limit for a failed case.
  scripts/compare_models models/hscl.pt runs/*/last.pt --sizes 4 8 16 --cases 25 --json out.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from tqdm import tqdm

from mapf_policy.action_selection import PAPER_RULE, ActionRule, make_rule
from mapf_policy.inference import InferenceNet
from mapf_policy.model_io import load_model
from mapf_policy.network import QNetwork
from mapf_policy.policy import Policy
from mapf_policy.solver import HsclSolver
from mapf_policy.train.actor import evaluate_by_size, summarize_by_size
from mapf_policy.train.demos import COMPARE_STREAM, generated_cases
from mapf_world.evaluate import run_case


def held_out_cases(sizes, cases: int, seed: int, map_size: int, density: float) -> list:
    return generated_cases(seed, COMPARE_STREAM, sizes, cases, map_size, density)


def policy_solver(net: QNetwork, path, rule: ActionRule, sample_seed: int = 0, meta: dict | None = None) -> HsclSolver:
    """The evaluation solver of a loaded model under `rule`, as `scripts/evaluate --solver hscl` builds it. `meta`
    (the model file's metadata) carries the last-action mode the model was trained with; without it the solver
    assumes the first design's 'requested'."""
    policy = Policy(net, num_threads=None, rule=rule, seed=sample_seed, meta=meta)
    return HsclSolver("hscl", policy, sample_seed, Path(path))


def evaluate_with_rule(net: QNetwork, path, instances: list, max_steps: int, rule: ActionRule,
                       sample_seed: int, progress: bool, meta: dict | None = None) -> dict:
    """Like evaluate_by_size, with actions chosen by `rule` through the evaluation solver (same dict layout)."""
    solver = policy_solver(net, path, rule, sample_seed, meta)
    desc = Path(path).parent.name + "/" + Path(path).name
    outcomes = []
    for k, inst in enumerate(tqdm(instances, desc=desc, unit="case", disable=not progress)):
        result = run_case(solver, inst, max_steps, k)
        outcomes.append((inst.n_agents, result.success, result.steps))
    return summarize_by_size(outcomes)


def compare(paths, sizes, cases: int, seed: int = 0, map_size: int = 40, density: float = 0.3,
            max_steps: int = 256, progress: bool = True, rule: ActionRule = PAPER_RULE,
            sample_seed: int = 0) -> dict:
    """{model path: {team size: {success_rate, average_step, successes, cases}}}."""
    instances = held_out_cases(sizes, cases, seed, map_size, density)
    out = {}
    for path in paths:
        net, ncfg, meta = load_model(path)  # raises a clear error for a missing, corrupt or foreign file
        # The solver's path also serves the second design's inputs (channels beyond the paper's six, the still
        # count); the greedy actor below builds the paper's observation only.
        if rule != PAPER_RULE or ncfg.extra_channels().count or ncfg.still_bins:
            out[str(path)] = evaluate_with_rule(net, path, instances, max_steps, rule, sample_seed, progress, meta)
            continue
        out[str(path)] = evaluate_by_size(InferenceNet(net.eval()), instances, ncfg.fov_size, max_steps, progress,
                                          desc=Path(path).parent.name + "/" + Path(path).name,
                                          last_action=meta.get("last_action", "requested"))
    return out


def markdown(results: dict, sizes) -> str:
    head = "| model | " + " | ".join(f"{n} agents: success, avg step" for n in sizes) + " |"
    rows = [head, "|" + "---|" * (len(sizes) + 1)]
    for path, by_size in results.items():
        cells = [f"{v['successes']}/{v['cases']}, {v['average_step']:.1f}" for v in (by_size[str(n)] for n in sizes)]
        rows.append(f"| {path} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def add_rule_arguments(p: argparse.ArgumentParser, default_rule: str) -> None:
    """The action-rule options shared by the held-out tools; `rule_from_args` reads them."""
    p.add_argument("--action-rule", default=default_rule, metavar="NAME",
                   help=f"'paper' (greedy argmax only) or 'default' (the shipped sampled rule); default here: "
                        f"{default_rule}. The options below replace single fields of it")
    p.add_argument("--action-temperature", type=float, default=None, metavar="T",
                   help="sample actions from softmax(Q/T) as scripts/evaluate does; 0 = greedy")
    p.add_argument("--backtrack-penalty", type=float, default=None, metavar="P",
                   help="Q-value penalty on the move back to the previous step's cell; 0 = off")
    p.add_argument("--goal-stay-bonus", type=float, default=None, metavar="B",
                   help="ablation: added to the Q-value of staying for an agent on its own goal; 0 = off")
    p.add_argument("--mask-obstacle-moves", default=None, action=argparse.BooleanOptionalAction,
                   help="never choose a move into a static obstacle or off the map")
    p.add_argument("--sample-seed", type=int, default=0, metavar="S",
                   help="seed of the action sampling, restarted at each case (default 0)")
    p.add_argument("--sample-settled", action="store_true",
                   help="ablation: sample settled agents too (on their goal, no agent beside them), which the "
                        "policy otherwise keeps greedy")


def rule_from_args(args) -> ActionRule:
    """The ActionRule of `add_rule_arguments`' options (ValueError names a bad value)."""
    overrides = {k: v for k, v in (("action_temperature", args.action_temperature),
                                   ("backtrack_penalty", args.backtrack_penalty),
                                   ("goal_stay_bonus", args.goal_stay_bonus),
                                   ("mask_obstacle_moves", args.mask_obstacle_moves)) if v is not None}
    if args.sample_settled:
        overrides["settled_greedy"] = False
    return make_rule(args.action_rule, **overrides)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/compare_models", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("models", nargs="+", help="model files (models/hscl.pt, runs/<run>/last.pt, ...)")
    p.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 16], help="team sizes (default 4 8 16)")
    p.add_argument("--cases", type=int, default=25, help="cases per team size (default 25)")
    p.add_argument("--seed", type=int, default=0, help="seed of the held-out cases (default 0)")
    p.add_argument("--map-size", type=int, default=40)
    p.add_argument("--density", type=float, default=0.3)
    p.add_argument("--max-steps", type=int, default=256)
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    add_rule_arguments(p, default_rule="paper")
    p.add_argument("--json", type=Path, help="also write the results here")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    bad = [n for n in args.sizes if n < 1] + ([args.cases] if args.cases < 1 else [])
    if bad:
        p.error(f"--sizes and --cases must be positive, got {bad}")
    missing = [m for m in args.models if not Path(m).is_file()]
    if missing:
        p.error(f"no such model file: {', '.join(missing)}")
    torch.set_num_threads(args.threads)
    try:
        rule = rule_from_args(args)
        results = compare(args.models, args.sizes, args.cases, args.seed, args.map_size, args.density,
                          args.max_steps, progress=not args.no_progress, rule=rule, sample_seed=args.sample_seed)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(markdown(results, args.sizes))
    if args.json:
        args.json.write_text(json.dumps({"sizes": args.sizes, "cases": args.cases, "seed": args.seed,
                                         "action_rule": rule.asdict(), "sample_seed": args.sample_seed,
                                         "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
