"""Inference-speed benchmark of the policy (scripts/bench_inference): one agent, and 64 agents in one batch.

Times Policy.act end to end (numpy observation in, actions out) with torch.inference_mode, after warm-up,
and prints the median and 90th percentile over repeats. Targets (issue 4): one agent <= 2 ms, 64 agents <= 10 ms.
"""
from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from mapf_policy.action_selection import RULES
from mapf_policy.config import NetworkConfig
from mapf_policy.network import QNetwork
from mapf_policy.policy import Policy
from mapf_policy.solver import default_model_path


def time_batch(policy: Policy, batch: int, repeats: int, rng: np.random.Generator) -> np.ndarray:
    fov = (rng.random((batch, 6, 9, 9)) < 0.3).astype(np.float32)
    last = np.eye(5, dtype=np.float32)[rng.integers(0, 5, batch)]
    pos = rng.integers(0, 40, (batch, 2)).astype(np.float32)
    for _ in range(10):
        policy.act(fov, last, pos)
    times = np.empty(repeats)
    for k in range(repeats):
        t0 = time.perf_counter()
        policy.act(fov, last, pos)
        times[k] = time.perf_counter() - t0
    return times * 1e3


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--model", default=None, help="model file (default models/hscl.pt; untrained weights if absent)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--repeats", type=int, default=200, help="timed calls per batch size")
    parser.add_argument("--action-rule", default="default", choices=sorted(RULES),
                        help="'default': the shipped rule (sampling, obstacle mask, backtrack penalty); "
                             "'paper': greedy argmax only")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64], help="batch sizes to time")
    args = parser.parse_args(argv)
    path = args.model or default_model_path()
    if args.model is None and not path.is_file():
        print(f"note: {path} absent, timing an untrained network of the same architecture")
        model = QNetwork(NetworkConfig())
    else:
        model = str(path)
    policy = Policy(model, num_threads=args.threads, rule=RULES[args.action_rule])
    rng = np.random.default_rng(0)
    print(f"cpu: {platform.processor() or platform.machine()}, torch {torch.__version__}, threads {torch.get_num_threads()}, "
          f"action rule {args.action_rule} {policy.rule.asdict()}")
    for b in args.batches:
        ms = time_batch(policy, b, args.repeats, rng)
        print(f"batch {b:3d}: median {np.median(ms):.3f} ms, p90 {np.percentile(ms, 90):.3f} ms ({args.repeats} repeats)")


if __name__ == "__main__":
    main()
