"""The ladder of the second design: `scripts/ladder MODEL --rung N`, each rung passed before the next.

Greedy argmax (the paper's rule, no exploration, no mask), on held-out generated cases of the comparison
stream (COMPARE_STREAM: never trained on, never the benchmark), density 0.3, 256 steps. A model's
observation uses the last-action mode it was trained with (its metadata; 'requested' for older models).

  rung 1  1 agent on 10x10            success 1.0
  rung 2  4 agents on 20x20           success >= 0.99
  rung 3  16 agents on 40x40          success >= 0.99
  rung 4  1-64 agents on 40x40        success >= the paper's greedy figures (Table III) at 4..64, 1.0 below

`--epsilon E` (a diagnostic, never a rung check): each agent acts at random with probability E, which tells how much
of a greedy shortfall is the greedy rule's fixed points (deterministic agents that repeat a refused move or a wait).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from mapf_policy.action_selection import obstacle_moves
from mapf_policy.model_io import load_model
from mapf_policy.network import network_inputs
from mapf_policy.train.demos import COMPARE_STREAM, generated_cases
from mapf_policy.train.dqn_hscl import RecurrentActor, acting, greedy_outcomes, play_episode, pushed_blockers
from mapf_world.env import MapfEnv
from mapf_world.grid import DELTAS, STAY
from mapf_world.observation import N_CHANNELS
from mapf_world.planners.odrmstar import OBJECTIVES
from mapf_world.planners.prioritized import first_move_costs

# rung -> (what, [(agents, map side, success bar)])
RUNGS = {
    1: ("1 agent on 10x10", [(1, 10, 1.0)]),
    2: ("4 agents on 20x20", [(4, 20, 0.99)]),
    3: ("16 agents on 40x40", [(16, 40, 0.99)]),
    4: ("1-64 agents on 40x40", [(1, 40, 1.0), (2, 40, 1.0), (4, 40, 1.0), (8, 40, 0.995), (16, 40, 0.995),
                                 (32, 40, 0.955), (64, 40, 0.845)]),
}


def model_last_action(meta: dict) -> str:
    """The last-action mode a model was trained with (models before the second design: 'requested')."""
    return meta.get("last_action", "requested")


def run_rung(path, rung: int, cases: int, seed: int = 0, density: float = 0.3, max_steps: int = 256,
             progress: bool = True, agents: list[int] | None = None, epsilon: float = 0.0) -> list[dict]:
    """One row per team size of the rung (only those in `agents`, when given). `epsilon` > 0: each agent acts at
    random with that probability (a diagnostic of how much the greedy rule's fixed points cost; no rung is passed
    that way)."""
    if not 0.0 <= epsilon < 1.0:
        raise ValueError(f"epsilon must lie in [0, 1), got {epsilon}")
    if rung not in RUNGS:
        raise ValueError(f"rung must be one of {sorted(RUNGS)}, got {rung}")
    sizes = [a for a, _, _ in RUNGS[rung][1]]
    if agents is not None and not set(agents) & set(sizes):
        raise ValueError(f"rung {rung} has team sizes {sizes}, none of --agents {agents}")
    net, _, meta = load_model(path)
    forward, mode = acting(net), model_last_action(meta)
    rows = []
    for n_agents, side, bar in RUNGS[rung][1]:
        if agents is not None and n_agents not in agents:
            continue
        insts = generated_cases(seed, COMPARE_STREAM, [n_agents], cases, side, density)
        t0 = time.perf_counter()
        outcomes = greedy_outcomes(forward, tqdm(insts, desc=f"rung {rung}: {n_agents} agents, {side}x{side}", unit="case",
                                                 disable=not progress), mode, max_steps, epsilon)
        success = float(np.mean([s for s, _ in outcomes]))
        rows.append({"rung": rung, "agents": n_agents, "map": side, "cases": cases, "success_rate": success,
                     "successes": int(sum(s for s, _ in outcomes)),
                     "average_step": float(np.mean([t for _, t in outcomes])), "bar": bar,
                     "passed": success >= bar and epsilon == 0, "epsilon": epsilon,
                     "last_action": mode, "seconds": round(time.perf_counter() - t0, 1)})
    return rows


def moves_outweigh_stay(q: np.ndarray, temperature: float) -> bool:
    """Whether staying is the argmax of one agent's Q-values `q` although the four moves together carry more
    probability under softmax(q / temperature): a plurality stay over a majority that is split over directions."""
    prob = np.exp((q - q.max()) / temperature)
    return bool(q.argmax() == STAY and prob[STAY] / prob.sum() < 0.5)


def stuck_report(path, agents: int, side: int, cases: int, seed: int = 0, density: float = 0.3,
                 max_steps: int = 256, expert_objective: str = "free_goal_wait", expert_epsilon: float = 10.0) -> dict:
    """Where greedy failures stand at their last step: agents whose move was refused, whether that move is
    their argmax, its lead over the runner-up, and whether ODrM* (bound `expert_epsilon`, `expert_objective`, 2 s)
    labels that same move.

    A refused move repeated at a fixed point (the same observation each step) is a greedy deadlock.
    `fixed_point`: failed cases whose agents all stood still over the last 10 steps; `refused_with_room`: refused
    agents with 3 or 4 free neighbour cells (room to step aside; 2 or fewer: a corridor or a dead end).
    The other side of a push: `blockers`, agents that chose to stay at the last step on a cell a refused agent
    tried to enter; `blocker_on_goal` of them stand on their goal, `blocker_label_moves` of them ODrM* would
    move (the joint plan has the blocker give way), and `blocker_label_rank_counts[r]` counts those whose
    labelled move has rank r in their Q-values (0: it is the argmax). `blocker_moves_outweigh_stay` counts the
    blockers whose four moves together carry more probability than staying under softmax(Q / T), T the training
    temperature (the policy a cross-entropy imitation learner fits), while staying is still the argmax: moving is
    what the labels say more often, but split over directions, so no single move outranks the stay.
    How the team loops at the end (trajectory_period): `period_counts[p]` counts the failed cases whose positions
    repeat with period p + 1 over the last steps (1: a fixed point, 2: agents stepping back and forth, ...; the last
    entry: no period up to MAX_PERIOD, a team that wanders); `off_goal` the agents off their goal at the end,
    `moving_off_goal` those of them that move within the loop, `moving_on_goal` agents on their goal at the end that
    leave it within the loop (making way and coming back). Inside the loop (the last `period` steps of a failed case
    that loops), `loop_agent_steps` counts the agents' steps, `loop_argmax_is_label` those whose greedy action is the
    label of the model's own expert (train_args' `expert`: ODrM* or the prioritized plan) from that state, and
    `loops_expert_leaves` the looping cases in which some agent's label differs at some step: where the expert would
    leave the loop, so the network fails to fit or to tell apart a state that it was taught."""
    from mapf_policy.train.expert import ExpertFailed, make_oracle

    net, _, meta = load_model(path)
    forward, mode = acting(net), model_last_action(meta)
    temperature = float(meta.get("train_args", {}).get("temperature", 0.1))  # of the imitation term
    out = {"failed_cases": 0, "fixed_point": 0, "refused": 0, "refused_with_room": 0, "refused_is_argmax": 0,
           "label_is_refused_move": 0, "labelled": 0, "blockers": 0, "blocker_on_goal": 0, "blocker_label_moves": 0,
           "blocker_label_rank": [], "blocker_moves_outweigh_stay": 0, "lead": [],
           "period_counts": [0] * (MAX_PERIOD + 1), "off_goal": 0, "moving_off_goal": 0, "moving_on_goal": 0,
           "loops": 0, "loop_agent_steps": 0, "loop_argmax_is_label": 0, "loops_expert_leaves": 0}
    loop_expert = model_expert(meta)
    for inst in generated_cases(seed, COMPARE_STREAM, [agents], cases, side, density):
        env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=max_steps, last_action=mode,
                      **net.cfg.env_channels())
        steps, stats = play_episode(forward, env, 0.0, np.random.default_rng(0))
        if stats["success"]:
            continue
        out["failed_cases"] += 1
        trail = np.stack([o["position"] for o in steps["obs"][-11:]])
        out["fixed_point"] += int((trail == trail[-1]).all())
        positions = np.stack([o["position"] for o in steps["obs"]]).astype(np.int64)
        period = trajectory_period(positions)
        out["period_counts"][(period or MAX_PERIOD + 1) - 1] += 1
        window = positions[-(period or MAX_PERIOD) - 1:]
        moving = (window != window[-1]).any(axis=(0, 2))  # (N,) an agent that moves within the loop
        home = (positions[-1] == env.goals).all(axis=1)
        out["off_goal"] += int((~home).sum())
        out["moving_off_goal"] += int((moving & ~home).sum())
        out["moving_on_goal"] += int((moving & home).sum())
        if period:
            out["loops"] += 1
            leaves = False
            for t in range(len(positions) - 1 - period, len(positions) - 1):
                try:
                    loop_label = make_oracle(loop_expert, env.grid, env.goals, env.dist, expert_epsilon, 2.0,
                                             objective=expert_objective).actions(positions[t])
                except ExpertFailed:
                    continue
                same = loop_label == steps["action"][t]
                out["loop_agent_steps"] += len(same)
                out["loop_argmax_is_label"] += int(same.sum())
                leaves |= not same.all()
            out["loops_expert_leaves"] += int(leaves)
        obs, action, refused = steps["obs"][-2], steps["action"][-1], steps["failed"][-1]
        if isinstance(forward, RecurrentActor):  # its last call was at obs, with the memory it had then
            q = forward.q.numpy()
        else:
            with torch.inference_mode():
                q = forward(*network_inputs(obs, forward.cfg)).numpy()
        before = obs["position"].astype(np.int64)  # the cells at the last step
        try:
            label = make_oracle("odrmstar", env.grid, env.goals, env.dist, expert_epsilon, 2.0,
                                objective=expert_objective).actions(before)
        except ExpertFailed:
            label = None
        free = 4 - obstacle_moves(obs["fov"][:, :N_CHANNELS]).sum(axis=1)  # free neighbour cells (paper channels)
        last_step = np.stack([before, steps["obs"][-1]["position"]]).astype(np.int64)
        for j in np.flatnonzero(pushed_blockers(last_step, action[None], refused[None])[0]):
            out["blockers"] += 1
            out["blocker_on_goal"] += int((before[j] == env.goals[j]).all())
            out["blocker_moves_outweigh_stay"] += int(moves_outweigh_stay(q[j], temperature))
            if label is not None and label[j] != 0:
                out["blocker_label_moves"] += 1
                out["blocker_label_rank"].append(int((q[j] > q[j][label[j]]).sum()))
        for i in np.flatnonzero(refused):
            out["refused_with_room"] += int(free[i] >= 3)
            top = np.sort(q[i])
            out["refused"] += 1
            out["refused_is_argmax"] += int(q[i].argmax() == action[i])
            out["lead"].append(float(top[-1] - top[-2]))
            if label is not None:
                out["labelled"] += 1
                out["label_is_refused_move"] += int(label[i] == action[i])
    out["median_lead"] = float(np.median(out.pop("lead"))) if out["refused"] else float("nan")
    ranks = out.pop("blocker_label_rank")
    out["blocker_label_rank_counts"] = [ranks.count(r) for r in range(5)]  # how often the label is 1st, 2nd, ...
    return out


def model_expert(meta: dict) -> str:
    """The oracle whose labels a model was trained on (train_args' `expert`): ODrM* or the prioritized plan; ODrM*
    for models without it and for experts that are no oracle of make_oracle's."""
    expert = meta.get("train_args", {}).get("expert", "odrmstar")
    return expert if expert in ("odrmstar", "prioritized") else "odrmstar"


def interacting(positions: np.ndarray, goals: np.ndarray, radius: int) -> np.ndarray:
    """(N,) bool: the agents off their goal with another agent within `radius` cells (Chebyshev: in a field of
    view of side 2 radius + 1 centred on them), the agent-steps where the expert's label depends on the others."""
    positions = np.asarray(positions, dtype=np.int64)
    gap = np.abs(positions[:, None, :] - positions[None, :, :]).max(axis=2)
    np.fill_diagonal(gap, radius + 1)
    return (gap <= radius).any(axis=1) & ~(positions == np.asarray(goals)).all(axis=1)


CONTACTS = ("earlier agent adjacent", "only later agents adjacent", "nobody adjacent")


def contact_split(positions: np.ndarray, agent: int) -> tuple[str, set]:
    """Which of CONTACTS an agent's row is (4-neighbour cells; "earlier" = lower index, the agents the priority
    channel says it gives way to), and the cells of the earlier agents touching it."""
    gap = np.abs(positions - positions[agent]).sum(axis=1)
    touching = np.flatnonzero(gap == 1)
    earlier = {tuple(positions[j]) for j in touching if j < agent}
    return (CONTACTS[0] if earlier else CONTACTS[1] if len(touching) else CONTACTS[2]), earlier


def label_agreement(path, agents: int, side: int, cases: int, seed: int = 0, density: float = 0.3,
                    max_steps: int = 256, every: int = 3) -> dict:
    """Held-out imitation accuracy where it matters: at every `every`-th step of each greedy episode, how often the
    greedy action of an interacting agent (off its goal, another agent in its field of view) is the label of the
    model's own expert (train_args' `expert`, ODrM* or the prioritized plan, one plan per episode) from that state;
    split by solved and failed episodes. The training log's `agreement` is over replay batches, where about half the
    labelled rows have nobody in view, and `agreement_meet` over the batches' rows of this kind: both on the
    training distribution, this one on held-out greedy play (issue 20, thirtieth session).

    With the prioritized expert, `*_agree_tied` also counts an argmax that the plan ranks equal to its label (the
    same plan length, `first_move_costs`): the label's pick among equal moves follows the search's fixed direction
    order, which a model trained on turned rows (`--augment`) cannot learn, nor needs to. `by_contact` splits the
    rows by what touches the agent (`contact_split`) and counts how often the argmax and the label move into an
    earlier agent's cell (issue 20, thirty-fourth and thirty-seventh sessions).

    A diagnostic, not a target: offline imitation fits into a trained model raised this figure from 0.946 to 0.970
    while rung 3 fell from 0.96 to about 0.6 (issue 20, forty-second session). Success on the rungs decides."""
    from mapf_policy.train.expert import ExpertFailed, make_oracle

    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    net, _, meta = load_model(path)
    forward, mode = acting(net), model_last_action(meta)
    expert = model_expert(meta)
    tied = expert == "prioritized"
    out = {"expert": expert, "unlabelled_states": 0, "by_contact": {}}
    for kind in ("solved", "failed"):
        out.update({f"{kind}_steps": 0, f"{kind}_agree": 0, f"{kind}_agree_tied": 0 if tied else None})
    for inst in generated_cases(seed, COMPARE_STREAM, [agents], cases, side, density):
        env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=max_steps, last_action=mode,
                      **net.cfg.env_channels())
        steps, stats = play_episode(forward, env, 0.0, np.random.default_rng(0))
        oracle = make_oracle(expert, env.grid, env.goals, env.dist, 10.0, 2.0)
        kind = "solved" if stats["success"] else "failed"
        for t in range(0, len(steps["action"]), every):
            cells = steps["obs"][t]["position"].astype(np.int64)
            mask = interacting(cells, env.goals, net.cfg.fov_size // 2)
            if not mask.any():
                continue
            try:
                label = oracle.actions(cells)
            except ExpertFailed:
                out["unlabelled_states"] += 1
                continue
            act = steps["action"][t]
            agree = label == act
            # With ties: the argmax is one of the prioritized plan's best moves; for an agent it has no row for (the
            # plan failed at or before it, and the ODrM* fallback labelled the state), the label alone.
            if tied:
                costs = first_move_costs(env.grid, cells, env.goals, env.dist)
                best = np.where(costs >= 0, costs, np.iinfo(np.int64).max).min(axis=1)
                planned = (costs >= 0).any(axis=1)
                agree_tied = np.where(planned, costs[np.arange(len(act)), act] == best, agree)
                out[f"{kind}_agree_tied"] += int(agree_tied[mask].sum())
            out[f"{kind}_steps"] += int(mask.sum())
            out[f"{kind}_agree"] += int(agree[mask].sum())
            for i in np.flatnonzero(mask):
                split, earlier = contact_split(cells, i)
                into = [int(a != STAY and tuple(cells[i] + DELTAS[a]) in earlier) for a in (act[i], label[i])]
                row = out["by_contact"].setdefault(f"{kind} | {split}", {
                    "rows": 0, "agree": 0, "agree_tied": 0 if tied else None, "argmax_into_earlier": 0,
                    "label_into_earlier": 0})
                row["rows"] += 1
                row["agree"] += int(agree[i])
                row["argmax_into_earlier"] += into[0]
                row["label_into_earlier"] += into[1]
                if tied:
                    row["agree_tied"] += int(agree_tied[i])
    return out


MAX_PERIOD = 32  # the longest loop trajectory_period looks for


def trajectory_period(positions: np.ndarray, max_period: int = MAX_PERIOD) -> int | None:
    """The smallest p <= max_period with which the joint positions (T + 1, N, 2) repeat over their last 2 p + 1 steps
    (positions[t] == positions[t - p] for the last p + 1 steps t), or None: a deterministic team in a joint loop
    repeats its positions too, one that wanders does not."""
    for p in range(1, max_period + 1):
        if len(positions) < 2 * p + 1:
            return None
        if (positions[-p - 1:] == positions[-2 * p - 1:-p]).all():
            return p
    return None


def markdown(model: str, rows: list[dict]) -> str:
    rule = "greedy argmax" if not rows[0].get("epsilon") else f"epsilon-greedy {rows[0]['epsilon']} (a diagnostic, not a rung check)"
    lines = [f"model `{model}`, {rule}, held-out cases (seed stream {COMPARE_STREAM}), last action: {rows[0]['last_action']}",
             "", "| rung | agents | map | cases | success | average step | bar | passed |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['rung']} | {r['agents']} | {r['map']}x{r['map']} | {r['cases']} | {r['success_rate']:.3f} "
                     f"({r['successes']}) | {r['average_step']:.2f} | {r['bar']} | {'yes' if r['passed'] else 'NO'} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/ladder", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="model file (.pt)")
    p.add_argument("--rung", type=int, nargs="+", default=[1], help="rungs to check (default: 1)")
    p.add_argument("--cases", type=int, default=100, help="cases per team size (default 100)")
    p.add_argument("--seed", type=int, default=0, help="seed of the held-out cases (default 0)")
    p.add_argument("--agents", type=int, nargs="+", help="only these team sizes of the rungs (rung 4: 1 2 4 8 16 32 64)")
    p.add_argument("--json", help="also write the rows here")
    p.add_argument("--epsilon", type=float, default=0.0,
                   help="diagnostic: each agent acts at random with this probability (0: greedy, the paper's rule; a "
                        "rung is passed only greedy)")
    p.add_argument("--stuck", action="store_true",
                   help="also report, for each rung's failed cases, the refused moves at the last step (stuck_report)")
    p.add_argument("--stuck-expert-objective", default="free_goal_wait", choices=sorted(OBJECTIVES),
                   help="ODrM* objective of --stuck's labels (free_goal_wait, the training default; goal_keeping; sum_of_costs)")
    p.add_argument("--stuck-expert-epsilon", type=float, default=10.0, help="ODrM* bound of --stuck's labels (default 10)")
    p.add_argument("--agreement", action="store_true",
                   help="also report, for each rung's team sizes, how often the greedy action of an agent with another "
                        "agent in view is its expert's label (label_agreement; every third step), with the prioritized "
                        "expert also counting moves its plan ranks equal to the label, and split by what touches the agent")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if args.cases < 1:
        print("error: --cases must be >= 1", file=sys.stderr)
        return 2
    if (args.stuck or args.agreement) and args.epsilon > 0:
        print("error: --stuck and --agreement report on greedy play; drop --epsilon", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    try:
        rows = [r for k in args.rung
                for r in run_rung(args.model, k, args.cases, args.seed, progress=not args.no_progress, agents=args.agents,
                                  epsilon=args.epsilon)]
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(markdown(args.model, rows))
    if args.stuck:
        for r in rows:
            if not r["passed"]:
                rep = stuck_report(args.model, r["agents"], r["map"], args.cases, args.seed,
                                   expert_objective=args.stuck_expert_objective, expert_epsilon=args.stuck_expert_epsilon)
                r["stuck"] = rep
                print(f"\n{r['agents']} agents, {r['map']}x{r['map']}: {rep['failed_cases']} failed cases, "
                      f"{rep['fixed_point']} of them at a fixed point (no agent moved in the last 10 steps); at the last "
                      f"step {rep['refused']} refused moves ({rep['refused_with_room']} with room to step aside); the "
                      f"refused move is the argmax in {rep['refused_is_argmax']} "
                      f"(median lead {rep['median_lead']:.3f}); ODrM* labels it in {rep['label_is_refused_move']} of "
                      f"{rep['labelled']} labelled. {rep['blockers']} agents stayed on a cell pushed into "
                      f"({rep['blocker_on_goal']} on their goal); ODrM* moves {rep['blocker_label_moves']} of them, its "
                      f"move ranked 1st..5th in their Q-values {rep['blocker_label_rank_counts']} times; "
                      f"{rep['blocker_moves_outweigh_stay']} of them stay although their four moves together outweigh "
                      f"the stay under softmax(Q / T). Loops at the end by period 1..{MAX_PERIOD}, then none: "
                      f"{ {(p + 1 if p < MAX_PERIOD else 'none'): c for p, c in enumerate(rep['period_counts']) if c} }; {rep['off_goal']} agents "
                      f"off their goal, {rep['moving_off_goal']} of them moving in the loop; {rep['moving_on_goal']} "
                      f"agents on their goal leave it within the loop. In the loops ({rep['loops']}), the argmax is the "
                      f"expert's label at {rep['loop_argmax_is_label']} of {rep['loop_agent_steps']} agent-steps; the "
                      f"expert would leave {rep['loops_expert_leaves']} of them")
    if args.agreement:
        for r in rows:
            rep = label_agreement(args.model, r["agents"], r["map"], args.cases, args.seed)
            r["agreement"] = rep
            share = {k: rep[f"{k}_agree"] / rep[f"{k}_steps"] if rep[f"{k}_steps"] else float("nan")
                     for k in ("solved", "failed")}
            print(f"\n{r['agents']} agents, {r['map']}x{r['map']}: at the sampled agent-steps with another agent in view, "
                  f"the argmax is the {rep['expert']} label at {rep['solved_agree']} of {rep['solved_steps']} "
                  f"({share['solved']:.3f}) in solved cases and {rep['failed_agree']} of {rep['failed_steps']} "
                  f"({share['failed']:.3f}) in failed ones; {rep['unlabelled_states']} states without a label")
            if rep["solved_agree_tied"] is not None:
                print(f"  counting moves the plan ranks equal to its label: {rep['solved_agree_tied']} solved, "
                      f"{rep['failed_agree_tied']} failed")
            for split, c in sorted(rep["by_contact"].items()):
                tied_part = "" if c["agree_tied"] is None else f", {c['agree_tied'] / c['rows']:.3f} with ties"
                print(f"  {split}: {c['rows']} rows, agreement {c['agree'] / c['rows']:.3f}{tied_part}; argmax / label "
                      f"into an earlier agent {c['argmax_into_earlier'] / c['rows']:.3f} / "
                      f"{c['label_into_earlier'] / c['rows']:.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0 if all(r["passed"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
