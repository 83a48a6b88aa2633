"""Play held-out rung-3 cases with every agent taking the relabelling expert's action each step (replanned)."""
import sys, json, time
import numpy as np
from mapf_policy.train.demos import COMPARE_STREAM, generated_cases
from mapf_policy.train.expert import make_oracle
from mapf_world.env import MapfEnv
kind, seed, cases = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
agents, side = int(sys.argv[4]), int(sys.argv[5])
out = []
t0 = time.time()
for k, inst in enumerate(generated_cases(seed, COMPARE_STREAM, [agents], cases, side, 0.3)):
    env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=256)
    env.reset()
    oracle = make_oracle(kind, env.grid, env.goals, env.dist, 10.0, 2.0)
    done = term = False; steps = 0; hist = {}
    while not done:
        a = oracle.actions(env.positions)
        _, _, term, trunc, _ = env.step(a); steps += 1
        done = term or trunc
    out.append((bool(term), steps))
    print(k, term, steps, flush=True)
s = [o[0] for o in out]
print(json.dumps({"kind": kind, "seed": seed, "cases": cases, "success": float(np.mean(s)), "successes": int(sum(s)),
                  "avg_step": float(np.mean([o[1] for o in out])), "failed": [i for i, o in enumerate(out) if not o[0]],
                  "seconds": round(time.time() - t0, 1)}))
