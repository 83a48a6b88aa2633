"""Offline probe (42nd session): does weight decay let the network generalise its expert's labels better?

Training rows: 16 agents on 40x40, ACTOR_STREAM seed 1000 (never the ladder's stream), half greedy play of the model
and half expert-driven, labelled by the prioritized expert at every step, infeasible labels dropped; all interacting
rows (off goal, another agent in view) and a quarter of the others. Held out: greedy play of the same model on
COMPARE_STREAM seed 7 (the --agreement diagnosis cases), interacting rows. Labels: the set of moves the prioritized plan ranks equal (first_move_costs; the label alone where it has no plan),
so the search's fixed direction order is no target. Fit: cross-entropy on Q / T towards the uniform over that set from the
model's weights, Adam(W), lr 1e-4, batch 192; agreement (argmax Q == label) on held-out rows after each epoch.
  scripts/env python wd_probe.py MODEL TRAIN_CASES EPOCHS WD [WD ...]
"""
import copy, json, sys, time
import numpy as np, torch
import torch.nn.functional as F
from mapf_policy.model_io import load_model
from mapf_policy.network import network_inputs
from mapf_policy.train.demos import ACTOR_STREAM, COMPARE_STREAM, generated_cases
from mapf_policy.train.dqn_hscl import acting, play_episode, infeasible_labels
from mapf_policy.train.expert import make_oracle
from mapf_policy.train.ladder import interacting, model_last_action
from mapf_world.env import MapfEnv
from mapf_world.planners.prioritized import first_move_costs

torch.set_num_threads(1)
path, n_train, epochs, wds = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), [float(w) for w in sys.argv[4:]]
net, _, meta = load_model(path)
cfg, mode = net.cfg, model_last_action(meta)
T = float(meta.get("train_args", {}).get("temperature", 0.1))
radius = 4


def rows(insts, expert_share, rng, keep_other):
    forward = acting(net)
    X, Y, M = [], [], []
    for k, inst in enumerate(insts):
        env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=256, last_action=mode, **cfg.env_channels())
        oracle = make_oracle("prioritized", env.grid, env.goals, env.dist, 10.0, 2.0)
        steps, _ = play_episode(forward, env, 0.0, rng, oracle=oracle, budget=1e9,
                                expert_drives=(k % 2 == 0) and expert_share > 0)
        pos = np.stack([o["position"] for o in steps["obs"]]).astype(np.int64)
        expert = np.stack(steps["expert"])
        bad = infeasible_labels(pos, expert)
        for t in range(len(steps["action"])):
            inter = interacting(pos[t], env.goals, radius)
            keep = (expert[t] >= 0) & ~bad[t] & (inter | (rng.random(env.n_agents) < keep_other))
            if not keep.any():
                continue
            costs = first_move_costs(env.grid, pos[t], env.goals, env.dist)
            best = np.where(costs >= 0, costs, np.iinfo(np.int64).max).min(axis=1)
            ok = np.where((costs >= 0).any(axis=1)[:, None], costs == best[:, None],
                          np.eye(5, dtype=bool)[expert[t].clip(0)])
            inp = network_inputs(steps["obs"][t], cfg)
            X.append(tuple(x[torch.from_numpy(keep)] for x in inp))
            Y.append(torch.from_numpy(ok[keep]))
            M.append(torch.from_numpy(inter[keep]))
    return [torch.cat(c) for c in zip(*X)], torch.cat(Y), torch.cat(M)


def agreement(model, X, Y, M):
    with torch.inference_mode():
        q = torch.cat([model(*(x[i:i + 4096] for x in X)) for i in range(0, len(Y), 4096)])
    hit = Y.gather(1, q.argmax(1, keepdim=True)).squeeze(1)
    return float(hit[M].float().mean()), float(hit.float().mean())


t0 = time.time()
rng = np.random.default_rng(0)
Xtr, Ytr, Mtr = rows(generated_cases(1000, ACTOR_STREAM, [16], n_train, 40, 0.3), 0.5, rng, 0.25)
Xte, Yte, Mte = rows(generated_cases(7, COMPARE_STREAM, [16], 40, 40, 0.3), 0.0, rng, 0.0)
print(f"rows: train {len(Ytr)} ({int(Mtr.sum())} interacting), held out {len(Yte)}; {time.time() - t0:.0f} s", flush=True)
base = agreement(net, Xte, Yte, Mte)
out = {"model": path, "train_cases": n_train, "train_rows": len(Ytr), "heldout_rows": len(Yte), "base": base, "fits": {}}
print("base held-out interacting agreement", base, flush=True)
for wd in wds:
    model = copy.deepcopy(net).train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4, weight_decay=wd)
    g = torch.Generator().manual_seed(0)
    curve = []
    for ep in range(epochs):
        perm = torch.randperm(len(Ytr), generator=g)
        for i in range(0, len(perm) - 191, 192):
            b = perm[i:i + 192]
            target = Ytr[b].float() / Ytr[b].float().sum(1, keepdim=True)  # uniform over the plan's equal moves
            loss = F.cross_entropy(model(*(x[b] for x in Xtr)) / T, target)
            opt.zero_grad(); loss.backward(); opt.step()
        model.eval()
        tr = agreement(model, Xtr, Ytr, Mtr)[0]
        te = agreement(model, Xte, Yte, Mte)[0]
        model.train()
        curve.append({"epoch": ep + 1, "train_interacting": tr, "heldout_interacting": te})
        print(f"wd {wd}: epoch {ep + 1} train {tr:.3f} held out {te:.3f} ({time.time() - t0:.0f} s)", flush=True)
    out["fits"][str(wd)] = curve
json.dump(out, open(f"runs/probe/wd_probe_{n_train}.json", "w"), indent=1)
