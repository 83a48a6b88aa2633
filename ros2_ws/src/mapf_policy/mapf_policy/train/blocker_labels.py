"""What the expert says to the policy's pushed blockers: `scripts/blocker_labels MODEL`.

Plays greedy episodes of a model (the paper's rule) on generated cases that neither training (seeds 0-2 of the
actor stream by default) nor the ladder (the comparison stream) uses, labels every state with the expert, as
greedy DAgger does, and counts at the rows of pushed blockers (dqn_hscl.pushed_blockers: agents that stay on a
cell another agent's refused move tried to enter) how the labels split: a move, a stay, a move dropped as
infeasible (dqn_hscl.infeasible_labels), or no label (the expert failed or its time budget was spent). A greedy
fixed point repeats one state for the rest of the episode, so the rows are also grouped by distinct observation:
for each, its labels and the model's softmax(Q / T) there.

The question it answers (issue 20, session 22): is the stay the learner picks at a blocker the mode of the labels
it was shown there?
"""
from __future__ import annotations

import argparse
import collections
import json
import sys

import numpy as np
import torch
from tqdm import tqdm

from mapf_policy.model_io import load_model
from mapf_policy.network import network_inputs
from mapf_policy.train.demos import ACTOR_STREAM, instance_rng
from mapf_policy.train.dqn_hscl import acting, episode_rows, play_episode
from mapf_policy.train.expert import make_oracle
from mapf_world.env import MapfEnv
from mapf_world.instances import generate_instance

KINDS = ("move", "stay", "move dropped as infeasible", "no label")


def blocker_label_split(model, episodes: int, seed: int = 101, agents: int = 4, size: int = 20, density: float = 0.3,
                        expert: str = "odrmstar", budget: float = 5.0, temperature: float = 0.1,
                        max_steps: int = 256, progress: bool = False) -> dict:
    """Greedy episodes of `model` (a path) with expert labels; the split of the labels at pushed blockers' rows."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    net, cfg, meta = load_model(model)
    mode = meta.get("last_action", "requested")
    act = acting(net)
    rng = np.random.default_rng(seed)
    rows_by_kind, states, solved = collections.Counter(), [], 0
    for ep in tqdm(range(episodes), disable=not progress, desc="episodes"):
        inst = generate_instance(instance_rng(seed, ACTOR_STREAM, ep), size=size, density=density, n_agents=agents)
        env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=max_steps, last_action=mode,
                      **cfg.env_channels())
        oracle = make_oracle(expert, env.grid, env.goals, env.dist, 10.0, min(2.0, budget))
        steps, stats = play_episode(act, env, 0.0, rng, oracle, budget)
        solved += stats["success"]
        rows = episode_rows(steps, stats["success"], 0.99, 2, feasible_labels=True)
        raw = np.stack(steps["expert"]).reshape(-1)
        groups = collections.defaultdict(list)
        for i in np.flatnonzero(rows["blocker"]):
            label = int(rows["expert"][i])
            kind = "no label" if raw[i] < 0 else "move dropped as infeasible" if label < 0 else "stay" if label == 0 else "move"
            rows_by_kind[kind] += 1
            groups[(rows["fov"][i].tobytes(), int(rows["last_action"][i]), rows["position"][i].tobytes())].append((i, label))
        for members in groups.values():
            i = members[0][0]
            t, agent = divmod(i, env.n_agents)
            with torch.inference_mode():
                q = act(*network_inputs(steps["obs"][t], cfg)).numpy()[agent]
            p = np.exp((q - q.max()) / temperature)
            labels = collections.Counter(lab for _, lab in members)
            states.append({"episode": ep, "rows": len(members), "labels": {int(k): v for k, v in sorted(labels.items())},
                           "argmax": int(q.argmax()), "p": [round(float(x), 3) for x in p / p.sum()]})
    return {"model": str(model), "episodes": episodes, "solved": solved, "rows": {k: rows_by_kind[k] for k in KINDS},
            "states": states, "summary": summarize(states)}


def summarize(states: list[dict]) -> dict:
    """Per distinct blocker state: is the labels' mode a move or the stay, do its move labels agree on one direction,
    and does the model's argmax follow the mode."""
    out = collections.Counter()
    for s in states:
        labels = {k: v for k, v in s["labels"].items() if k >= 0}
        if not labels:
            out["no usable label"] += 1
            continue
        mode = max(labels, key=lambda k: (labels[k], -k))
        out["mode move" if mode > 0 else "mode stay"] += 1
        out["one move direction" if len([k for k in labels if k > 0]) == 1 else "no or several move directions"] += 1
        out["argmax is the mode"] += int(s["argmax"] == mode)
    return dict(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/blocker_labels", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="model file (.pt)")
    p.add_argument("--episodes", type=int, default=150, help="greedy episodes (default 150)")
    p.add_argument("--seed", type=int, default=101, help="seed of the cases, actor stream (default 101; training uses 0-2)")
    p.add_argument("--agents", type=int, default=4)
    p.add_argument("--size", type=int, default=20)
    p.add_argument("--expert", default="odrmstar", help="labeller (default odrmstar; shortest_path for a quick check)")
    p.add_argument("--budget", type=float, default=5.0, help="expert seconds per episode, as in training (default 5)")
    p.add_argument("--json", help="also write the result here")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    try:
        res = blocker_label_split(args.model, args.episodes, args.seed, args.agents, args.size, expert=args.expert,
                                  budget=args.budget, progress=not args.no_progress)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{res['model']}: {res['solved']} of {res['episodes']} greedy episodes solved ({args.agents} agents, "
          f"{args.size}x{args.size})")
    print("pushed blockers' rows: " + ", ".join(f"{k} {v}" for k, v in res["rows"].items()))
    print(f"distinct blocker states: {len(res['states'])}; " + ", ".join(f"{k} {v}" for k, v in res["summary"].items()))
    for s in res["states"]:
        print(f"  episode {s['episode']}: {s['rows']} rows, labels {s['labels']}, argmax {s['argmax']}, p {s['p']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
