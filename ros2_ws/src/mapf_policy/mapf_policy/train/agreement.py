"""Where a model disagrees with the expert: `scripts/expert_agreement`.

Training logs one agreement figure (argmax Q = expert action, over a batch). Most rows of a large team's
episode are agents waiting on their goals or walking in free space, where agreement is near 1, so that
figure hides the crowded states where teams jam. This tool plays generated held-out episodes (seed stream
COMPARE_STREAM, never benchmark cases) with each model, as the training actors do (softmax(Q / T) with
settled agents greedy, no epsilon), labels every visited state with the expert (ODrM*) until its time
budget is spent, and reports agreement per situation:
  on goal   the agent stands on its goal (action_selection.on_goal);
  crowd     other agents in its field of view: 0-1, 2-3, 4 or more.
Those split the rows. One more situation overlaps them: "on goal, agent beside" (on its goal with another
agent in a neighbour cell), where a line under the table says how often the label and the model's argmax
are a move: the situation in which agents step off their goals (scripts/failure_modes).
Each model meets the same instances but visits its own states, which is what its behaviour depends on.
With --states-from REF, REF alone plays the episodes and every model is scored on REF's labelled states:
the same rows for every model, so differences are the models' and not their visits' (the expert labels
each state once).
With --second-epsilon E, a second ODrM* at bound E labels the same states: the report adds each model's
agreement with it and the two experts' agreement with each other. Where the experts disagree, a label is
one of several good actions, so part of a policy's disagreement there is a choice, not an error.
  scripts/expert_agreement models/hscl.pt runs/<run>/last.pt --sizes 32 64 --cases 4 --seed 16
  scripts/expert_agreement runs/<run>/last.pt --states-from models/hscl.pt --sizes 64 --cases 4 --seed 18
With --second-order, the second expert hands the agents to the planner in another order (config.EXPERT_ORDERS):
how much of the labels is the planner's tie-breaking by agent index, which no agent can observe.
  scripts/expert_agreement models/hscl.pt --states-from models/hscl.pt --second-epsilon 2 --expert-budget 60
  scripts/expert_agreement models/hscl.pt --states-from models/hscl.pt --second-order reversed --expert-budget 60
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from mapf_policy.action_selection import on_goal, settled
from mapf_policy.config import EXPERT_ORDERS
from mapf_policy.inference import InferenceNet
from mapf_policy.model_io import load_model
from mapf_policy.train.actor import run_episode
from mapf_policy.train.demos import COMPARE_STREAM, generated_cases
from mapf_policy.train.expert import make_oracle
from mapf_policy.train.replay import to_tensors
from mapf_world.env import MapfEnv

# Crowd buckets: (label, smallest, largest) count of other agents in the field of view.
CROWDS = (("0-1", 0, 1), ("2-3", 2, 3), ("4+", 4, 10**9))


BESIDE = "on goal, agent beside"


def situations(fov: np.ndarray) -> dict:
    """(B,) bool masks by situation from (B, 6, l, l) observations: 'on goal' / 'off goal' x crowd bucket,
    which split the rows, and BESIDE (on its goal with another agent in a neighbour cell: not settled), which
    overlaps the on-goal buckets."""
    c = fov.shape[-1] // 2
    goal = on_goal(fov)
    others = fov[:, 1].reshape(len(fov), -1).sum(axis=1) - fov[:, 1, c, c]
    out = {}
    for where, mask in (("on goal", goal), ("off goal", ~goal)):
        for label, lo, hi in CROWDS:
            out[f"{where}, {label} in view"] = mask & (others >= lo) & (others <= hi)
    out[BESIDE] = goal & ~settled(fov)
    return out


TALLY_FIELDS = ("rows", "agree", "label_moves", "argmax_moves")


def tally(q: np.ndarray, expert: np.ndarray, fov: np.ndarray) -> dict:
    """{situation: counts} over the labelled rows (expert >= 0), plus 'all'. Counts: rows, agree (argmax Q =
    label), label_moves (the label is a move, not stay), argmax_moves (the argmax is a move)."""
    labelled = expert >= 0
    best = q.argmax(axis=1)
    masks = {"all": np.ones(len(expert), dtype=bool), **situations(fov)}
    return {name: {"rows": int((mask & labelled).sum()), "agree": int((mask & labelled & (best == expert)).sum()),
                   "label_moves": int((mask & labelled & (expert > 0)).sum()),
                   "argmax_moves": int((mask & labelled & (best > 0)).sum())}
            for name, mask in masks.items()}


def add_tallies(a: dict, b: dict) -> dict:
    return {k: {f: a.get(k, {}).get(f, 0) + v[f] for f in TALLY_FIELDS} for k, v in b.items()}


@dataclass(frozen=True)
class Setup:
    """How the episodes are played and labelled (the same for every model of one call)."""

    action_temperature: float = 0.04
    """Episode actions: softmax(Q / T) with settled agents greedy; 0 = argmax (the training actors' rule)."""
    expert_budget: float = 15.0
    """Seconds of ODrM* planning per episode (both experts together); later states stay unlabelled."""
    expert_epsilon: float = 10.0
    """Suboptimality bound of the expert that labels the states (training's default)."""
    second_epsilon: float | None = None
    """A second ODrM* bound that labels the same states too: how consistent the expert's labels are."""
    max_steps: int = 256
    expert_order: str = "index"
    """Agent order of the first expert (config.EXPERT_ORDERS)."""
    second_order: str = "index"
    """Agent order of the second expert."""


class SecondOpinion:
    """Labelling oracle that asks a second expert about every state the first one labels.

    `labels` gets the second expert's (N,) actions, one entry per labelled step in order. When either
    expert fails, ExpertFailed stops the labelling of the episode for both, so the two label sets cover
    the same steps."""

    def __init__(self, first, second):
        self.first, self.second, self.labels = first, second, []

    def actions(self, positions: np.ndarray) -> np.ndarray:
        first = self.first.actions(positions)
        self.labels.append(self.second.actions(positions))
        return first


def load_forward(path) -> tuple:
    """(InferenceNet, NetworkConfig) of a model file; a clear error for a missing, corrupt or foreign file."""
    net, ncfg, _ = load_model(path)
    if ncfg.extra_channels().count or ncfg.still_bins:
        raise ValueError(f"{path} reads inputs beyond the paper's (issue 20's second design: "
                         f"{list(ncfg.extra_channels().names)}, still input {ncfg.still_bins}); this tool plays the "
                         f"first design's actors. For such a model: scripts/ladder {path} --rung 3 --agreement")
    return InferenceNet(net.eval()), ncfg


def play(forward, fov_size: int, inst, k: int, setup: Setup) -> tuple:
    """One episode as the training actors play it (no epsilon): its labelled rows and its success.

    rows["expert"] holds the first expert's labels (-1: unlabelled); with a second expert, rows["second"]
    holds its labels of the same rows."""
    env = MapfEnv(inst.grid, inst.starts, inst.goals, fov_size=fov_size, max_steps=setup.max_steps)
    oracle = make_oracle("odrmstar", env.grid, env.goals, env.dist, setup.expert_epsilon, setup.expert_budget,
                         setup.expert_order)
    if setup.second_epsilon is not None:
        oracle = SecondOpinion(oracle, make_oracle("odrmstar", env.grid, env.goals, env.dist, setup.second_epsilon,
                                                   setup.expert_budget, setup.second_order))
    rng = np.random.default_rng(k)
    rec, stats = run_episode(forward, env, 0.0, rng, oracle, setup.expert_budget,
                             action_temperature=setup.action_temperature)
    rows = rec.arrays()
    if setup.second_epsilon is not None:
        labelled = rows["expert"] >= 0  # the labelled steps, a prefix of the episode: one row per agent each
        rows["second"] = np.full(len(labelled), -1, dtype=np.int64)
        if oracle.labels:
            rows["second"][labelled] = np.concatenate(oracle.labels)
    return rows, bool(stats["success"])


def score(forward, rows: dict) -> dict:
    """One model's greedy choice on the given rows: {"tallies": vs the expert} (+ "tallies_second": vs the
    second expert, and "experts": first expert vs second, when rows have a second label)."""
    t = to_tensors(rows, torch.device("cpu"))
    with torch.inference_mode():
        q = forward(t["fov"], t["last_action"], t["position"]).numpy()
    expert = rows["expert"].astype(np.int64)
    out = {"tallies": tally(q, expert, rows["fov"])}
    if "second" in rows:
        first_as_q = np.eye(q.shape[1])[np.maximum(expert, 0)]  # unlabelled rows are skipped by tally()
        out["tallies_second"] = tally(q, rows["second"], rows["fov"])
        out["experts"] = tally(first_as_q, rows["second"], rows["fov"])
    return out


def add_scores(a: dict, b: dict) -> dict:
    return {key: add_tallies(a.get(key, {}), b[key]) for key in b}


def model_agreement(path, instances: list, setup: Setup, progress: bool = False) -> dict:
    """Summed tallies over the instances for one model file on its own states, and the episodes' outcomes."""
    forward, ncfg = load_forward(path)
    totals, solved = {}, 0
    for k, inst in enumerate(tqdm(instances, desc=Path(path).name, unit="episode", disable=not progress)):
        rows, success = play(forward, ncfg.fov_size, inst, k, setup)
        totals = add_scores(totals, score(forward, rows))
        solved += int(success)
    return {**totals, "episodes": len(instances), "solved": solved}


def shared_agreement(reference, paths: list, instances: list, setup: Setup, progress: bool = False) -> tuple:
    """Every model scored on the states that `reference` visits: ({path: tallies}, reference's outcomes).

    Episodes are played and labelled once; each one's rows are scored by every model before the next
    episode, so memory stays at one episode's rows."""
    ref_forward, ref_cfg = load_forward(reference)
    forwards = {}
    for path in paths:
        forward, ncfg = load_forward(path)
        if ncfg.fov_size != ref_cfg.fov_size:
            raise ValueError(f"{path} sees a {ncfg.fov_size}x{ncfg.fov_size} field of view but the states come "
                             f"from {reference}, which sees {ref_cfg.fov_size}x{ref_cfg.fov_size}")
        forwards[str(path)] = forward
    totals, solved = {p: {} for p in forwards}, 0
    for k, inst in enumerate(tqdm(instances, desc=f"states of {Path(reference).name}", unit="episode",
                                  disable=not progress)):
        rows, success = play(ref_forward, ref_cfg.fov_size, inst, k, setup)
        for p, forward in forwards.items():
            totals[p] = add_scores(totals[p], score(forward, rows))
        solved += int(success)
    results = {p: {**t, "episodes": len(instances), "solved": None} for p, t in totals.items()}
    return results, {"model": str(reference), "episodes": len(instances), "solved": solved}


def expert_name(epsilon: float, order: str) -> str:
    return f"eps {epsilon:g}" + ("" if order == "index" else f", {order} order")


def _cell(t: dict) -> str:
    return f"{t['agree'] / t['rows']:.3f} ({t['rows']})" if t["rows"] else "- (0)"


def markdown(results: dict, setup: Setup, shared: bool = False) -> str:
    """One column per model (agreement with the expert); with a second expert, a column per model against
    it and the experts' agreement with each other (once when every model saw the same states). Without
    shared states, each model's solved episodes stand under its first column."""
    columns = []  # (header, tallies, episodes-solved cell)
    first, second = expert_name(setup.expert_epsilon, setup.expert_order), None
    if setup.second_epsilon is not None:
        second = expert_name(setup.second_epsilon, setup.second_order)
    for p, r in results.items():
        name, solved = Path(p).name, "" if shared else f"{r['solved']}/{r['episodes']}"
        if setup.second_epsilon is None:
            columns.append((f"{name}: agreement (rows)", r["tallies"], solved))
            continue
        columns.append((f"{name} vs {first}", r["tallies"], solved))
        columns.append((f"{name} vs {second}", r["tallies_second"], ""))
        if not shared:
            columns.append((f"{first} vs {second} ({name}'s states)", r["experts"], ""))
    if setup.second_epsilon is not None and shared:
        columns.append((f"{first} vs {second}", next(iter(results.values()))["experts"], ""))
    rows = ["| situation | " + " | ".join(c[0] for c in columns) + " |", "|" + "---|" * (len(columns) + 1)]
    for name in columns[0][1]:
        rows.append(f"| {name} | " + " | ".join(_cell(c[1].get(name, {"rows": 0, "agree": 0})) for c in columns) + " |")
    if not shared:
        rows.append("| episodes solved | " + " | ".join(c[2] for c in columns) + " |")
    rows.append("")
    for p, r in results.items():  # how often the labels and each model's argmax leave a goal beside an agent
        b = r["tallies"].get(BESIDE, {"rows": 0})
        if b["rows"]:
            rows.append(f"{Path(p).name} vs {first}, {BESIDE}: the label is a move in "
                        f"{b['label_moves'] / b['rows']:.3f} and the model's argmax in "
                        f"{b['argmax_moves'] / b['rows']:.3f} of {b['rows']} rows")
    return "\n".join(rows)


def add_setup_arguments(p: argparse.ArgumentParser) -> None:
    """The episode and labelling options (Setup's first expert) and the world options, shared with
    scripts/collect_rows."""
    p.add_argument("--action-temperature", type=float, default=0.04, metavar="T",
                   help="the episodes' actions: softmax(Q/T), settled agents greedy; 0 = argmax (default 0.04)")
    p.add_argument("--expert-budget", type=float, default=15.0, metavar="S",
                   help="seconds of ODrM* planning per episode; later states stay unlabelled (default 15)")
    p.add_argument("--expert-epsilon", type=float, default=10.0, help="ODrM* suboptimality bound (default 10)")
    p.add_argument("--expert-order", choices=EXPERT_ORDERS, default="index",
                   help="order in which the agents are handed to ODrM* (default index: the instance's; "
                        "see mapf_policy/train/expert.py)")
    p.add_argument("--map-size", type=int, default=40)
    p.add_argument("--density", type=float, default=0.3)
    p.add_argument("--max-steps", type=int, default=256)


def setup_from_args(p: argparse.ArgumentParser, args, second_epsilon: float | None = None,
                    second_order: str = "index") -> Setup:
    """Setup from the options of add_setup_arguments; a usage error (exit 2) names a bad value."""
    if args.max_steps < 1:
        p.error(f"--max-steps must be positive, got {args.max_steps}")
    if not (args.action_temperature >= 0 and args.expert_budget > 0 and args.expert_epsilon >= 1):
        p.error("--action-temperature must be >= 0, --expert-budget > 0 and --expert-epsilon >= 1")
    return Setup(args.action_temperature, args.expert_budget, args.expert_epsilon, second_epsilon, args.max_steps,
                 args.expert_order, second_order)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/expert_agreement", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("models", nargs="+", help="model files")
    p.add_argument("--states-from", type=Path, metavar="REF",
                   help="score every model on the states that REF visits (same rows for all) instead of its own")
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64], help="team sizes (default 32 64)")
    p.add_argument("--cases", type=int, default=4, help="episodes per team size (default 4)")
    p.add_argument("--seed", type=int, default=0, help="seed of the held-out instances (default 0)")
    add_setup_arguments(p)
    p.add_argument("--second-epsilon", type=float, metavar="E",
                   help="also label the same states with ODrM* at bound E and report agreement with it and "
                        "between the two experts (how consistent the labels are)")
    p.add_argument("--second-order", choices=EXPERT_ORDERS,
                   help="agent order of the second expert (implies one, at --second-epsilon or else the first's "
                        "bound): how much the labels depend on the order")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--json", type=Path, help="also write the tallies here")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    bad = [n for n in args.sizes + [args.cases] if n < 1]
    if bad:
        p.error(f"--sizes and --cases must be positive, got {bad}")
    if args.second_epsilon is not None and not args.second_epsilon >= 1:
        p.error(f"--second-epsilon must be >= 1, got {args.second_epsilon}")
    if args.second_order is not None and args.second_epsilon is None:
        args.second_epsilon = args.expert_epsilon
    setup = setup_from_args(p, args, args.second_epsilon, args.second_order or "index")
    missing = [str(m) for m in args.models + ([args.states_from] if args.states_from else []) if not Path(m).is_file()]
    if missing:
        p.error(f"no such model file: {', '.join(missing)}")
    torch.set_num_threads(args.threads)
    instances = generated_cases(args.seed, COMPARE_STREAM, args.sizes, args.cases, args.map_size, args.density)
    states = None
    try:
        if args.states_from:
            results, states = shared_agreement(args.states_from, args.models, instances, setup,
                                               not args.no_progress)
        else:
            results = {str(m): model_agreement(m, instances, setup, not args.no_progress) for m in args.models}
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(markdown(results, setup, shared=states is not None))
    if states:
        print(f"\nStates visited by {states['model']}, which solved {states['solved']}/{states['episodes']} episodes.")
    if args.json:
        args.json.write_text(json.dumps({"sizes": args.sizes, "cases": args.cases, "seed": args.seed,
                                         "setup": asdict(setup), "states_from": states, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
