"""How a policy's cases fail: `scripts/failure_modes` (held-out generated cases, never benchmark cases).

Plays cases of the COMPARE seed stream with an action rule, as `scripts/compare_models` does, and reads
the trajectories:
- **off at end**: the agents not on their goals when a failed case hits the step limit. A *tail* failure
  leaves at most `--tail-agents` of them (the team was nearly done), a *jam* more;
- **all but k**: the first step at which all but k agents stand on their goals at once;
- **goal departures**: how often an agent standing on its goal is off it one step later, split by
  whether another agent stands in one of its four neighbour cells (the shipped rule keeps an agent with
  no neighbour greedy, so departures happen almost only beside others);
- **off-goal agent-steps without a move**: waits and refused moves of agents not on their goals, and
  **refused moves** per agent-step (into an agent, an obstacle or a swap; the harness counts them);
- a second table, from the actions the solver chose: off-goal agent-steps split into **chosen waits** and
  **refused moves** (together the steps without a move above), and **refused moves by cause**: each move
  the rules refused, by what stood in its way, in this order: an obstacle or the map's edge; a *swap*
  (the agent in the target cell tried to move into the mover's cell); the target's occupant *waited*
  (chose to stay), on its goal or off it; the occupant's own move was refused (a *cascade* behind a
  blocked agent); or a *contest* (another mover got the cell, free or vacated in the same step; the
  lowest index wins);
- **flickering agents**: in a failed case, agents that left their goal at least twice in the last
  `--window` steps. A case succeeds only at a step where every agent is on its goal, so a few agents
  that keep stepping off and back can hold a nearly finished team past the step limit.
`--expert` adds the same figures for ODrM*'s plans on the same cases. It prints the two Markdown tables and
writes `failures.json` and `on_goal.png` (agents on their goals over time, one
line per case; with `--expert`, the median of ODrM*'s plans in blue).
  scripts/failure_modes models/hscl.pt --sizes 32 64 --cases 40 --seed 26 --out runs/failures
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from mapf_policy.model_io import load_model
from mapf_policy.train.compare import add_rule_arguments, held_out_cases, policy_solver, rule_from_args
from mapf_world.evaluate import run_case
from mapf_world.grid import DELTAS
from mapf_world.rules import resolve_moves
from mapf_world.solvers import PLAN_FAILED_REASONS, get_solver

ALL_BUT = (10, 5, 1, 0)  # "all but k agents on their goals"
EXPERT_LABEL = "ODrM* (epsilon 10)"
NEIGHBOURS = np.array([(-1, 0), (1, 0), (0, -1), (0, 1)])
# Causes of a refused move, in the order they are tested (the first that applies names it).
REFUSAL_CAUSES = ("obstacle", "swap", "occupant waited on its goal", "occupant waited off its goal",
                  "occupant refused", "contest")


def beside_others(positions: np.ndarray) -> np.ndarray:
    """(T, N) bool from (T, N, 2) cells: another agent stands in one of the agent's four neighbour cells."""
    positions = np.asarray(positions)
    out = np.zeros(positions.shape[:2], dtype=bool)
    for t, cells in enumerate(positions):
        occupied = {(int(r), int(c)) for r, c in cells}
        for i, (r, c) in enumerate(cells):
            out[t, i] = any((int(r + dr), int(c + dc)) in occupied for dr, dc in NEIGHBOURS)
    return out


def refused_moves(grid: np.ndarray, positions: np.ndarray, actions: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """(N,) int: for each agent whose move the rules refuse in one joint step, the index of its cause in
    REFUSAL_CAUSES (the first that applies, in that order); -1 for the others. positions (N, 2) at the
    start of the step, actions (N,) 0..4 as the agents chose them."""
    grid, positions, goals = np.asarray(grid), np.asarray(positions, dtype=np.int64), np.asarray(goals)
    actions = np.asarray(actions, dtype=np.int64)
    _, failed = resolve_moves(grid, positions, actions)
    causes = np.full(len(positions), -1, dtype=np.int64)
    h, w = grid.shape
    target = positions + DELTAS[actions]
    occupant = {(int(r), int(c)): j for j, (r, c) in enumerate(positions)}
    for i in np.flatnonzero(failed):
        r, c = (int(v) for v in target[i])
        j = occupant.get((r, c))
        if not (0 <= r < h and 0 <= c < w) or grid[r, c]:
            cause = "obstacle"
        elif j is not None and actions[j] != 0 and (target[j] == positions[i]).all():
            cause = "swap"
        elif j is not None and actions[j] == 0:
            cause = "occupant waited " + ("on its goal" if (positions[j] == goals[j]).all() else "off its goal")
        elif j is not None and failed[j]:
            cause = "occupant refused"
        else:
            cause = "contest"
        causes[i] = REFUSAL_CAUSES.index(cause)
    return causes


def refusal_causes(grid: np.ndarray, positions: np.ndarray, actions: np.ndarray, goals: np.ndarray) -> dict:
    """{cause: count} of the moves the rules refuse in one joint step (refused_moves, counted)."""
    return _count_causes(refused_moves(grid, positions, actions, goals))


def _count_causes(causes: np.ndarray) -> dict:
    counts = np.bincount(causes[causes >= 0], minlength=len(REFUSAL_CAUSES))
    return {k: int(v) for k, v in zip(REFUSAL_CAUSES, counts)}


def trace_case(positions: np.ndarray, goals: np.ndarray, success: bool, window: int = 64,
               plan_failed: bool = False, failed_moves: int = 0, chosen: dict | None = None) -> dict:
    """What one case's trajectory shows. positions (T + 1, N, 2): the cells from the start to the end.
    `plan_failed`: a planner gave up before moving (the trajectory is the start only). `failed_moves`:
    the moves the rules refused during the case (the harness counts them). `chosen`: what the recorded
    actions show (case_actions), copied into the trace; None where they were not recorded."""
    positions, goals = np.asarray(positions), np.asarray(goals)
    if positions.ndim != 3 or positions.shape[2] != 2 or goals.shape != positions.shape[1:]:
        raise ValueError(f"positions must be (T + 1, N, 2) and goals (N, 2), got {positions.shape} and {goals.shape}")
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    n = positions.shape[1]
    on = (positions == goals[None]).all(axis=2)  # (T + 1, N)
    count = on.sum(axis=1)
    departed = on[:-1] & ~on[1:]  # (T, N): on the goal at t, off it at t + 1
    still = (positions[1:] == positions[:-1]).all(axis=2)  # (T, N): stayed, or a move that failed
    beside = beside_others(positions[:-1])
    first = {k: (int(np.argmax(count >= n - k)) if (count >= n - k).any() else None) for k in ALL_BUT if k < n}
    flickering = 0 if success else int((departed[-window:].sum(axis=0) >= 2).sum())
    return {
        "n_agents": n, "success": bool(success), "plan_failed": bool(plan_failed), "steps": len(positions) - 1,
        "on_goal": count.tolist(), "off_at_end": int(n - count[-1]), "all_but": first,
        "on_goal_beside": int((on[:-1] & beside).sum()), "departures_beside": int((departed & beside).sum()),
        "on_goal_alone": int((on[:-1] & ~beside).sum()), "departures_alone": int((departed & ~beside).sum()),
        "flickering": flickering, "agent_steps": int(on[:-1].size), "off_goal": int((~on[:-1]).sum()),
        "still_off_goal": int((~on[:-1] & still).sum()), "failed_moves": int(failed_moves),
        "refusals": dict(chosen["refusals"]) if chosen is not None else None,
        "waits_off_goal": chosen["waits_off_goal"] if chosen is not None else None,
        "refused_off_goal": chosen["refused_off_goal"] if chosen is not None else None,
    }


def _rate(num: int, den: int) -> float | None:
    return num / den if den else None


def _median(values: list) -> float | None:
    return float(np.median(values)) if values else None


def _refusal_shares(traces: list[dict]) -> dict | None:
    """{cause: share of the refused moves} over the traces that recorded causes; None without refusals."""
    counted = [t["refusals"] for t in traces if t.get("refusals") is not None]
    total = sum(sum(r.values()) for r in counted)
    return {k: sum(r[k] for r in counted) / total for k in REFUSAL_CAUSES} if total else None


def summarize(traces: list[dict], max_steps: int, tail_agents: int) -> dict:
    """One team size's traces -> the figures of the table (failures count max_steps in the average step).
    Cases a planner gave up on count as failures but enter no other figure."""
    if not traces:
        raise ValueError("no cases to summarize")
    played = [t for t in traces if not t.get("plan_failed", False)]
    failed = [t for t in played if not t["success"]]
    recorded = [t for t in played if t.get("waits_off_goal") is not None]
    n = traces[0]["n_agents"]

    def total(key: str) -> int:
        return sum(t[key] for t in played)

    return {
        "cases": len(traces), "successes": sum(t["success"] for t in traces),
        "plan_failures": len(traces) - len(played),
        "average_step": float(np.mean([t["steps"] if t["success"] else max_steps for t in traces])),
        "tail_failures": sum(t["off_at_end"] <= tail_agents for t in failed),
        "jams": sum(t["off_at_end"] > tail_agents for t in failed),
        "median_off_at_end": _median([t["off_at_end"] for t in failed]),
        "median_all_but": {str(k): _median([t["all_but"][k] for t in played if t["all_but"][k] is not None])
                           for k in ALL_BUT if k < n},
        "departure_rate_beside": _rate(total("departures_beside"), total("on_goal_beside")),
        "departure_rate_alone": _rate(total("departures_alone"), total("on_goal_alone")),
        "still_off_goal_share": _rate(total("still_off_goal"), total("off_goal")),
        "failed_move_rate": _rate(total("failed_moves"), total("agent_steps")),
        "refusal_shares": _refusal_shares(played),
        "wait_off_goal_share": _rate(sum(t["waits_off_goal"] for t in recorded),
                                     sum(t["off_goal"] for t in recorded)) if recorded else None,
        "refused_off_goal_share": _rate(sum(t["refused_off_goal"] for t in recorded),
                                        sum(t["off_goal"] for t in recorded)) if recorded else None,
        "failed_with_flicker": sum(t["flickering"] > 0 for t in failed),
        "mean_flickering": float(np.mean([t["flickering"] for t in failed])) if failed else None,
    }


def expert_solver(time_limit: float = 10.0):
    """ODrM* at the training expert's bound (epsilon 10), planning each case once, for a reference row."""
    return get_solver("odrmstar", epsilon=10.0, time_limit=time_limit)


class _Recorder:
    """Evaluation-harness solver protocol around another solver: keeps the actions of the current case."""

    def __init__(self, solver):
        self.solver, self.actions = solver, []
        # run_case builds the env with the solver's last-action mode (the model's; planners have none)
        self.last_action = getattr(solver, "last_action", "requested")
        # ... and with the channels and revisit count the model reads (a second-design model's; else none)
        self.env_channels = getattr(solver, "env_channels", {})

    def reset(self, env) -> None:
        self.actions = []
        self.solver.reset(env)

    def act(self, obs: dict) -> np.ndarray:
        actions = self.solver.act(obs)
        self.actions.append(np.array(actions, dtype=np.int64))
        return actions


def case_actions(inst, positions: np.ndarray, actions: list) -> dict:
    """What the chosen actions of a played case show: {"refusals": refusal_causes summed over the steps,
    "waits_off_goal" / "refused_off_goal": off-goal agent-steps whose action was to stay / was a refused
    move}. positions (T + 1, N, 2) and the T joint actions."""
    if len(actions) != len(positions) - 1:
        raise ValueError(f"{len(actions)} joint actions for a trajectory of {len(positions) - 1} steps")
    if not actions:  # solved at the start: nothing was chosen
        return {"refusals": dict.fromkeys(REFUSAL_CAUSES, 0), "waits_off_goal": 0, "refused_off_goal": 0}
    goals = np.asarray(inst.goals)
    causes = np.array([refused_moves(inst.grid, cells, acts, goals) for cells, acts in zip(positions[:-1], actions)])
    off = ~(np.asarray(positions[:-1]) == goals).all(axis=2)  # (T, N)
    return {"refusals": _count_causes(causes.ravel()), "waits_off_goal": int((off & (np.array(actions) == 0)).sum()),
            "refused_off_goal": int((off & (causes >= 0)).sum())}


def run(solver, instances: list, max_steps: int = 256, window: int = 64, progress: bool = True,
        desc: str = "cases") -> dict:
    """{team size (str): [trace per case]}: `solver` (evaluation-harness protocol) on each instance."""
    out: dict[str, list] = {}
    recorder = _Recorder(solver)
    for k, inst in enumerate(tqdm(instances, desc=desc, unit="case", disable=not progress)):
        result = run_case(recorder, inst, max_steps, k)
        plan_failed = result.reason in PLAN_FAILED_REASONS
        chosen = None if plan_failed else case_actions(inst, result.positions, recorder.actions)
        if chosen is not None and sum(chosen["refusals"].values()) != result.failed_moves:
            raise RuntimeError(f"case {k}: {sum(chosen['refusals'].values())} refusals by cause, the harness "
                               f"counted {result.failed_moves}")
        out.setdefault(str(inst.n_agents), []).append(trace_case(
            result.positions, inst.goals, result.success, window, plan_failed, result.failed_moves, chosen))
    return out


def _fmt(v, spec: str = ".1f") -> str:
    return "-" if v is None else format(v, spec)


def markdown(summaries: dict, tail_agents: int) -> str:
    """summaries: {row label (model or expert): {team size: summary}}."""
    rows = [f"| solver | agents | solved, avg step | failures: tail (<= {tail_agents} off) / jam | median off at end "
            "| median first step with all but 10 / 5 / 1 / 0 on goal | goal departures per step, beside others / alone "
            "| failed cases with flickering agents (mean number) | off-goal agent-steps without a move "
            "| refused moves per agent-step |", "|---|---|---|---|---|---|---|---|---|---|"]
    for label, summary in summaries.items():
        for n, s in summary.items():
            solved = f"{s['successes']}/{s['cases']}, {s['average_step']:.1f}"
            if s["plan_failures"]:
                solved += f" ({s['plan_failures']} gave up)"
            firsts = " / ".join(_fmt(s["median_all_but"].get(str(k)), ".0f") for k in ALL_BUT)
            rows.append(f"| {label} | {n} | {solved} | {s['tail_failures']} / {s['jams']} "
                        f"| {_fmt(s['median_off_at_end'])} | {firsts} | {_fmt(s['departure_rate_beside'], '.3f')} / "
                        f"{_fmt(s['departure_rate_alone'], '.3f')} | {s['failed_with_flicker']} "
                        f"({_fmt(s['mean_flickering'])}) | {_fmt(s['still_off_goal_share'], '.3f')} "
                        f"| {_fmt(s['failed_move_rate'], '.3f')} |")
    return "\n".join(rows)


def refusal_markdown(summaries: dict) -> str:
    """The second table: off-goal agent-steps split into waits and refused moves, and the shares of the
    refused moves by cause ("-" where nothing was refused)."""
    rows = ["| solver | agents | off-goal agent-steps: chosen waits / refused moves | "
            + " | ".join(f"refused: {k}" for k in REFUSAL_CAUSES) + " |", "|---|---|---|" + "---|" * len(REFUSAL_CAUSES)]
    for label, summary in summaries.items():
        for n, s in summary.items():
            shares = s["refusal_shares"]
            causes = " | ".join(_fmt(shares[k] if shares else None, ".3f") for k in REFUSAL_CAUSES)
            rows.append(f"| {label} | {n} | {_fmt(s['wait_off_goal_share'], '.3f')} / "
                        f"{_fmt(s['refused_off_goal_share'], '.3f')} | {causes} |")
    return "\n".join(rows)


def _median_curve(cases: list[dict], max_steps: int) -> np.ndarray:
    """Median over cases of the agents on their goals at each step; a case that ended keeps its last count."""
    curves = np.array([np.pad(t["on_goal"], (0, max_steps + 1 - len(t["on_goal"])), mode="edge") for t in cases])
    return np.median(curves, axis=0)


def plot(traces: dict, path: Path, max_steps: int, reference: dict | None = None,
         reference_label: str = "ODrM*") -> Path:
    """Agents on their goals over time, one panel per team size: solved cases green, failed ones red, and
    the median of `reference`'s cases (the expert's) in blue where given."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(traces), figsize=(5.5 * len(traces), 4), squeeze=False, constrained_layout=True)
    for ax, (n, cases) in zip(axes[0], traces.items()):
        for t in cases:
            ax.plot(t["on_goal"], color="tab:green" if t["success"] else "tab:red", alpha=0.35, lw=1)
        played = [t for t in (reference or {}).get(n, []) if not t.get("plan_failed", False)]
        if played:
            ax.plot(_median_curve(played, max_steps), color="tab:blue", lw=2.5,
                    label=f"{reference_label}, median of {len(played)} plans")
            ax.legend(loc="lower right")
        solved = sum(t["success"] for t in cases)
        ax.set(title=f"{n} agents: {solved}/{len(cases)} solved (green), failed (red)", xlabel="step",
               ylabel="agents on their goals", xlim=(0, max_steps), ylim=(0, int(n) + 0.5))
        ax.axhline(int(n), color="grey", lw=0.5)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/failure_modes", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="model file (models/hscl.pt, runs/<run>/last.pt, ...)")
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64], help="team sizes (default 32 64)")
    p.add_argument("--cases", type=int, default=40, help="cases per team size (default 40)")
    p.add_argument("--seed", type=int, default=0, help="seed of the held-out cases (default 0)")
    p.add_argument("--map-size", type=int, default=40)
    p.add_argument("--density", type=float, default=0.3)
    p.add_argument("--max-steps", type=int, default=256)
    p.add_argument("--tail-agents", type=int, default=5,
                   help="a failure with at most this many agents off goal at the end is a tail failure (default 5)")
    p.add_argument("--window", type=int, default=64,
                   help="last steps of a failed case in which flickering agents are counted (default 64)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    add_rule_arguments(p, default_rule="default")
    p.add_argument("--expert", action="store_true",
                   help="add a reference row: ODrM* (epsilon 10, the training's expert) on the same cases")
    p.add_argument("--expert-time-limit", type=float, default=10.0,
                   help="seconds ODrM* may plan one case before it gives up (default 10)")
    p.add_argument("--out", type=Path, default=None, help="directory for failures.json and on_goal.png")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    bad = [v for v in [*args.sizes, args.cases, args.max_steps, args.window] if v < 1]
    if bad or args.tail_agents < 0 or not args.expert_time_limit > 0:
        p.error(f"--sizes, --cases, --max-steps, --window and --expert-time-limit must be positive and "
                f"--tail-agents >= 0, got {bad or [args.tail_agents, args.expert_time_limit]}")
    if not Path(args.model).is_file():
        p.error(f"no such model file: {args.model}")
    torch.set_num_threads(args.threads)
    instances = held_out_cases(args.sizes, args.cases, args.seed, args.map_size, args.density)
    try:
        rule = rule_from_args(args)
        net, _, meta = load_model(args.model)  # a clear error for a missing, corrupt or foreign file
        solvers = {str(args.model): policy_solver(net, args.model, rule, args.sample_seed, meta)}
        if args.expert:
            solvers[EXPERT_LABEL] = expert_solver(args.expert_time_limit)
        traces = {label: run(solver, instances, args.max_steps, args.window, progress=not args.no_progress,
                             desc=label) for label, solver in solvers.items()}
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    summaries = {label: {n: summarize(t, args.max_steps, args.tail_agents) for n, t in by_size.items()}
                 for label, by_size in traces.items()}
    print(markdown(summaries, args.tail_agents))
    print("\nWhy off-goal agents do not move, and refused moves by cause (share of all refused moves):\n")
    print(refusal_markdown(summaries))
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "failures.json").write_text(json.dumps(
            {"model": str(args.model), "sizes": args.sizes, "cases": args.cases, "seed": args.seed,
             "action_rule": rule.asdict(), "sample_seed": args.sample_seed, "max_steps": args.max_steps,
             "tail_agents": args.tail_agents, "window": args.window, "expert_time_limit": args.expert_time_limit,
             "summaries": summaries, "traces": traces}, indent=1))
        picture = plot(traces[str(args.model)], args.out / "on_goal.png", args.max_steps,
                       traces.get(EXPERT_LABEL))
        print(f"wrote {args.out / 'failures.json'} and {picture}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
