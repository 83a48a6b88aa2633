"""Inference-speed benchmark of the policy (scripts/bench_inference): one agent, and 64 agents in one batch.

Times Policy.act end to end (numpy observation in, actions out) with torch.inference_mode, after warm-up,
and prints the median and 90th percentile over repeats. Targets (issue 4): one agent <= 2 ms, 64 agents <= 10 ms.
`--forward` names the ways of computing the Q-values to time, interleaved in rounds so that a slow spell of
the machine hits all alike: `fast` (the default, what every entry point uses on CPU) is InferenceNet
(inference.py); `im2col` is InferenceNet without its Winograd layers; `winograd` is InferenceNet with them
at every batch size; `reference` is QNetwork.forward itself, on channels-last memory.
"""
from __future__ import annotations

import argparse
import copy
import platform
import time

import numpy as np
import torch

from mapf_policy.action_selection import RULES
from mapf_policy.config import NetworkConfig
from mapf_policy.inference import InferenceNet
from mapf_policy.network import QNetwork
from mapf_policy.policy import Policy
from mapf_policy.solver import default_model_path


FORWARDS = ("fast", "im2col", "winograd", "reference")


def random_inputs(batch: int, rng: np.random.Generator, cfg: NetworkConfig | None = None) -> tuple:
    """(fov, last_action, position[, still]) of `batch` agents for a network of `cfg`: 0/1 channels at density 0.3
    (as many as it reads), one-hot actions, cells of 40x40, and a one-hot still input if it reads one."""
    cfg = cfg or NetworkConfig()
    fov = (rng.random((batch, cfg.fov_channels, cfg.fov_size, cfg.fov_size)) < 0.3).astype(np.float32)
    last = np.eye(5, dtype=np.float32)[rng.integers(0, 5, batch)]
    pos = rng.integers(0, 40, (batch, 2)).astype(np.float32)
    still = (np.eye(cfg.still_bins, dtype=np.float32)[rng.integers(0, cfg.still_bins, batch)],) if cfg.still_bins else ()
    return (fov, last, pos) + still


def time_batch(policy: Policy, inputs: tuple, repeats: int) -> np.ndarray:
    """Milliseconds of `repeats` calls of policy.act, after 10 untimed ones."""
    for _ in range(10):
        policy.act(*inputs)
    times = np.empty(repeats)
    for k in range(repeats):
        t0 = time.perf_counter()
        policy.act(*inputs)
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
    parser.add_argument("--forward", nargs="+", default=["fast"], choices=FORWARDS,
                        help="'fast': InferenceNet (the default everywhere on CPU); 'im2col' / 'winograd': InferenceNet "
                             "without / always with its Winograd layers; 'reference': QNetwork.forward")
    parser.add_argument("--rounds", type=int, default=5, help="rounds of repeats/rounds calls per forward")
    args = parser.parse_args(argv)
    if args.repeats < args.rounds or args.rounds < 1:
        parser.error(f"--repeats ({args.repeats}) must be at least --rounds ({args.rounds}), which must be >= 1")
    if min(args.batches) < 1:
        parser.error(f"batch sizes must be >= 1, got {args.batches}")
    path = args.model or default_model_path()
    if args.model is None and not path.is_file():
        print(f"note: {path} absent, timing an untrained network of the same architecture")
        model = QNetwork(NetworkConfig())
    else:
        model = str(path)
    policy = Policy(model, num_threads=args.threads, rule=RULES[args.action_rule])
    # The reference is the path before InferenceNet: QNetwork.forward on channels-last memory (oneDNN's
    # fastest layout for this network here).
    reference = copy.deepcopy(policy.net).to(memory_format=torch.channels_last)
    forwards = {"fast": policy.forward,
                "im2col": InferenceNet(policy.net, winograd_min_batch=None),
                "winograd": InferenceNet(policy.net, winograd_min_batch=1),
                "reference": lambda f, a, p, *s: reference(f.contiguous(memory_format=torch.channels_last), a, p, *s)}
    names = list(dict.fromkeys(args.forward))
    print(f"cpu: {platform.processor() or platform.machine()}, torch {torch.__version__}, threads {torch.get_num_threads()}, "
          f"action rule {args.action_rule} {policy.rule.asdict()}")
    for b in args.batches:
        rng = np.random.default_rng(b)
        inputs = random_inputs(b, rng, policy.cfg)
        ms = {name: [] for name in names}
        for _ in range(args.rounds):
            for name in names:
                policy.forward = forwards[name]
                ms[name].append(time_batch(policy, inputs, args.repeats // args.rounds))
        for name in names:
            t = np.concatenate(ms[name])
            print(f"batch {b:3d}, {name:9s} forward: median {np.median(t):.3f} ms, p90 {np.percentile(t, 90):.3f} ms "
                  f"({t.size} calls)")


if __name__ == "__main__":
    main()
