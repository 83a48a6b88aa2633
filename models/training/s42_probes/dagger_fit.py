"""Offline DAgger-at-scale probe (42nd session): does one round of many more distinct 16-agent labelled rows lift rung 3?

collect MODEL SEED CASES OUT.pt [heldout|inview]: rows as wd_probe.py (16 agents on 40x40; ACTOR_STREAM SEED, half greedy
  play of MODEL and half expert-driven; or with `heldout`, greedy play on COMPARE_STREAM SEED, interacting rows only).
fit_strict ...: the same with the recipe's target instead: the label itself, each row in a random one of the
  eight orientations (symmetry.Augmenter), needs rows collected with labels (this file's later form).
fit MODEL OUT_MODEL EPOCHS HELDOUT.pt ROWS.pt...: cross-entropy on Q / T towards the uniform over the prioritized
  plan's equal-best moves, AdamW lr 1e-4 batch 192, from MODEL's weights; held-out agreement after each epoch; the
  fitted weights are saved with MODEL's metadata (so scripts/ladder reads them the same way).
"""
import copy, sys, time
import numpy as np, torch
import torch.nn.functional as F
from mapf_policy.model_io import load_model, save_model
from mapf_policy.network import network_inputs
from mapf_policy.train.demos import ACTOR_STREAM, COMPARE_STREAM, generated_cases
from mapf_policy.train.dqn_hscl import acting, play_episode, infeasible_labels
from mapf_policy.train.expert import make_oracle
from mapf_policy.train.ladder import interacting, model_last_action
from mapf_world.env import MapfEnv
from mapf_world.planners.prioritized import first_move_costs

torch.set_num_threads(1)
IN_VIEW = False  # set by `collect ... inview`


def collect(net, meta, insts, expert_share, rng, keep_other):
    cfg, mode = net.cfg, model_last_action(meta)
    forward = acting(net)
    X, Y, M, L = [], [], [], []
    for k, inst in enumerate(insts):
        env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=256, last_action=mode, **cfg.env_channels())
        oracle = make_oracle("prioritized", env.grid, env.goals, env.dist, 10.0, 2.0)
        steps, _ = play_episode(forward, env, 0.0, rng, oracle=oracle, budget=1e9,
                                expert_drives=(k % 2 == 0) and expert_share > 0)
        pos = np.stack([o["position"] for o in steps["obs"]]).astype(np.int64)
        expert = np.stack(steps["expert"])
        bad = infeasible_labels(pos, expert)
        for t in range(len(steps["action"])):
            inter = interacting(pos[t], env.goals, cfg.fov_size // 2)
            # with IN_VIEW, also every agent on its goal with another in view (the rows where it gives way)
            near = interacting(pos[t], pos[t] + 10_000, cfg.fov_size // 2) if IN_VIEW else inter
            keep = (expert[t] >= 0) & ~bad[t] & (near | (rng.random(env.n_agents) < keep_other))
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
            L.append(torch.from_numpy(expert[t][keep]))
        if k % 20 == 0:
            print(f"case {k}: {sum(len(y) for y in Y)} rows", flush=True)
    return {"X": [torch.cat(c) for c in zip(*X)], "Y": torch.cat(Y), "M": torch.cat(M), "L": torch.cat(L)}


def agreement(model, X, Y, M):
    with torch.inference_mode():
        q = torch.cat([model(*(x[i:i + 4096] for x in X)) for i in range(0, len(Y), 4096)])
    hit = Y.gather(1, q.argmax(1, keepdim=True)).squeeze(1)
    return float(hit[M].float().mean())


if sys.argv[1] == "collect":
    net, _, meta = load_model(sys.argv[2])
    seed, cases, out = int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
    held = len(sys.argv) > 6 and sys.argv[6] == "heldout"
    IN_VIEW = len(sys.argv) > 6 and sys.argv[6] == "inview"
    insts = generated_cases(seed, COMPARE_STREAM if held else ACTOR_STREAM, [16], cases, 40, 0.3)
    torch.save(collect(net, meta, insts, 0.0 if held else 0.5, np.random.default_rng(seed), 0.0 if held else 0.25), out)
elif sys.argv[1] in ("fit", "fit_strict"):
    STRICT = sys.argv[1] == "fit_strict"
    net, cfg, meta = load_model(sys.argv[2])
    out_model, epochs, held = sys.argv[3], int(sys.argv[4]), torch.load(sys.argv[5])
    parts = [torch.load(f) for f in sys.argv[6:]]
    X = [torch.cat(c) for c in zip(*(p["X"] for p in parts))]
    Y, M = torch.cat([p["Y"] for p in parts]), torch.cat([p["M"] for p in parts])
    # FIT_ROWS=inter / other / ongoal / alone: only the interacting rows (off goal, another agent in view), only
    # the others, or the others split
    subset = __import__("os").environ.get("FIT_ROWS", "all")
    if subset != "all":
        # ongoal / alone: the others split by whether another agent is in view (fov channel 1): the rest of the rows
        # with someone in view are agents on their goals
        seen = X[0][:, 1].flatten(1).sum(1) > 0
        sel = {"inter": M, "other": ~M, "ongoal": ~M & seen, "alone": ~M & ~seen}[subset]
        X, Y, M = [x[sel] for x in X], Y[sel], M[sel]
        parts = [{"L": torch.cat([p["L"] for p in parts])[sel]}] if "L" in parts[0] else parts
    T = float(meta.get("train_args", {}).get("temperature", 0.1))
    strict = STRICT
    if strict:  # the recipe's target: the label itself, each row in a random one of the eight orientations
        from mapf_policy.train.symmetry import Augmenter, direction_blocks
        L = torch.cat([p["L"] for p in parts])
        aug = Augmenter(cfg.fov_size, cfg.fov_channels, direction_blocks(cfg))
        shape = torch.full((192, 2), 40.0)
    print(f"train rows {len(Y)} ({int(M.sum())} interacting); held out {len(held['Y'])}", flush=True)
    print(f"epoch 0 held out {agreement(net, held['X'], held['Y'], held['M']):.4f}", flush=True)
    model = copy.deepcopy(net).train()
    opt = torch.optim.AdamW(model.parameters(), lr=float(__import__("os").environ.get("FIT_LR", "1e-4")), weight_decay=0.0)
    g, t0 = torch.Generator().manual_seed(0), time.time()
    g_aug = torch.Generator().manual_seed(1)
    for ep in range(epochs):
        perm = torch.randperm(len(Y), generator=g)
        for i in range(0, len(perm) - 191, 192):
            b = perm[i:i + 192]
            if strict:
                sym = torch.randint(0, 8, (len(b),), generator=g_aug)
                fov, last, pos = X[0][b], X[1][b], X[2][b]
                inp = (aug.fov(fov, sym), last.gather(1, aug.action_src[sym]), aug.position(pos, shape, sym)) + tuple(
                    x[b] for x in X[3:])
                loss = F.cross_entropy(model(*inp) / T, aug.action[sym, L[b]])
            else:
                target = Y[b].float() / Y[b].float().sum(1, keepdim=True)
                loss = F.cross_entropy(model(*(x[b] for x in X)) / T, target)
            opt.zero_grad(); loss.backward(); opt.step()
        model.eval()
        print(f"epoch {ep + 1} held out {agreement(model, held['X'], held['Y'], held['M']):.4f} ({time.time() - t0:.0f} s)",
              flush=True)
        save_model(f"{out_model[:-3]}_ep{ep + 1}.pt", model, cfg, dict(meta, offline_fit=sys.argv[6:]))
        model.train()
