"""scripts/export_model: a torch model file (.pt) -> the robot's torch-free file (.npz, runtime_net.py).

    scripts/export_model models/hscl.pt                 # writes models/hscl.npz next to it
    scripts/export_model models/hscl.pt --out X.npz
    scripts/export_model models/hscl.pt --check         # does models/hscl.npz belong to it and agree with it?

The export carries the weights, the NetworkConfig, the model's metadata, the SHA-256 of the .pt file and a
fingerprint of the weights (runtime_net.py). `check_export` says whether an export belongs to a model file
(same source hash, same weights) and computes the same Q-values and greedy actions on observations of
generated 40x40 episodes. This side needs torch (it reads .pt files); the robot only reads the .npz.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from mapf_policy.config import NetworkConfig
from mapf_policy.runtime_net import (EXPORT_FORMAT, EXPORT_VERSION, HEADER_KEY, RuntimeNet, file_sha256,
                                     read_export, weights_fingerprint)

# Agreement required of an export (issue 21): Q-values within this of torch's, and identical greedy actions.
Q_TOLERANCE = 1e-4


def default_export_path(model_path) -> Path:
    """models/hscl.pt -> models/hscl.npz."""
    return Path(model_path).with_suffix(".npz")


def export_model(model_path, out_path=None) -> Path:
    """Write the export of `model_path` (atomically: temp file + rename) and return its path."""
    from mapf_policy.model_io import load_model
    model_path = Path(model_path)
    out = Path(out_path) if out_path is not None else default_export_path(model_path)
    net, cfg, meta = load_model(model_path)
    if cfg.recurrent:
        raise ValueError(f"{model_path} is a recurrent network (NetworkConfig.recurrent, a training experiment beyond "
                         "the paper): the robot runtime is feed-forward and has no export for it")
    arrays = {k: v.detach().cpu().float().numpy() for k, v in net.state_dict().items()}
    header = {"format": EXPORT_FORMAT, "version": EXPORT_VERSION, "network_config": cfg.asdict(), "meta": meta,
              "source": {"file": model_path.name, "sha256": file_sha256(model_path)},
              "weights_sha256": weights_fingerprint(arrays)}
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp.npz")
    np.savez(tmp, **arrays, **{HEADER_KEY: np.array(json.dumps(header, sort_keys=True))})
    os.replace(tmp, out)
    return out


def check_belongs(model_path, export_path) -> dict:
    """The export's header, after checking that it was made from `model_path` (the .pt file's SHA-256) and holds
    its weights; ValueError saying how they differ and how to fix it."""
    model_path, export_path = Path(model_path), Path(export_path)
    header, arrays = read_export(export_path)
    fix = f"export it again: scripts/export_model {model_path} --out {export_path}"
    sha = file_sha256(model_path)
    if header["source"].get("sha256") != sha:
        raise ValueError(f"{export_path} does not belong to {model_path}: it was exported from a file "
                         f"{header['source'].get('file')!r} with SHA-256 {str(header['source'].get('sha256'))[:12]}..., "
                         f"{model_path} has {sha[:12]}...; {fix}")
    from mapf_policy.model_io import load_model
    net, cfg, _ = load_model(model_path)
    if NetworkConfig.from_dict(header["network_config"]) != cfg:
        raise ValueError(f"{export_path}: network config differs from {model_path}'s; {fix}")
    state = {k: v.detach().cpu().float().numpy() for k, v in net.state_dict().items()}
    differ = sorted(k for k in state if k not in arrays or not np.array_equal(state[k], arrays[k]))
    if differ:
        raise ValueError(f"{export_path}: weights {differ[:4]} differ from {model_path}'s; {fix}")
    return header


def episode_observations(n: int, seed: int = 0, size: int = 40, agents=(4, 16, 64), steps: int = 24,
                         cfg: NetworkConfig | None = None) -> tuple:
    """(fov, last_action, position, still) of at least `n` agent-steps from generated size x size episodes (density
    0.3), the agents moving at random, so the observations hold crowds, walls and every last action. With `cfg`, the
    fov holds the channels that network reads and `still` is its one-hot still input (None for a network without
    one, and without `cfg`)."""
    from mapf_world.env import MapfEnv
    from mapf_world.instances import generate_instance
    from mapf_policy.config import STILL_KEYS
    from mapf_policy.runtime_net import still_onehot
    cfg = cfg or NetworkConfig()
    rng = np.random.default_rng(seed)
    parts, total, k = [], 0, 0
    while total < n:
        inst = generate_instance(rng, size=size, density=0.3, n_agents=agents[k % len(agents)])
        k += 1
        env = MapfEnv(inst.grid, inst.starts, inst.goals, **cfg.env_channels())
        obs, _ = env.reset()
        for _ in range(steps):
            row = tuple(np.asarray(obs[key], dtype=np.float32) for key in ("fov", "last_action", "position"))
            still = still_onehot(obs[STILL_KEYS[cfg.still_count]], cfg.still_bins) if cfg.still_bins else None
            parts.append(row + (still,))
            total += len(parts[-1][0])
            # Random moves with a bias to staying, so that the revisit and still counts reach their last bins.
            obs = env.step(np.where(rng.random(inst.n_agents) < 0.3, 0, rng.integers(0, 5, inst.n_agents)))[0]
    out = tuple(np.concatenate([p[i] for p in parts])[:n] for i in range(3))
    return out + ((np.concatenate([p[3] for p in parts])[:n] if cfg.still_bins else None),)


def compare_q(model_path, export_path, n: int = 3000, seed: int = 0) -> dict:
    """Q-values of the torch network (QNetwork.forward) and of the export on `n` episode observations built with the
    network's channels and still input: {"observations", "max_abs_diff", "greedy_disagreements"}."""
    import torch
    from mapf_policy.model_io import load_model
    net, cfg, _ = load_model(model_path)
    runtime = RuntimeNet.load(export_path)
    fov, last, pos, still = episode_observations(n, seed, cfg=cfg)
    with torch.inference_mode():
        inputs = [torch.from_numpy(x) for x in (fov, last, pos) + ((still,) if still is not None else ())]
        ref = net(*inputs).numpy()
    got = np.concatenate([runtime(fov[i:i + 256], last[i:i + 256], pos[i:i + 256],
                                  None if still is None else still[i:i + 256]) for i in range(0, n, 256)])
    return {"observations": n, "max_abs_diff": float(np.abs(got - ref).max()),
            "greedy_disagreements": int((got.argmax(1) != ref.argmax(1)).sum())}


def check_export(model_path, export_path, n: int = 3000, seed: int = 0) -> dict:
    """check_belongs, then compare_q within Q_TOLERANCE and without a greedy disagreement; ValueError if not."""
    check_belongs(model_path, export_path)
    result = compare_q(model_path, export_path, n, seed)
    if result["max_abs_diff"] > Q_TOLERANCE or result["greedy_disagreements"]:
        raise ValueError(f"{export_path} and {model_path} disagree on {n} observations: max |dQ| "
                         f"{result['max_abs_diff']:.2e} (allowed {Q_TOLERANCE:g}), {result['greedy_disagreements']} "
                         f"different greedy actions")
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scripts/export_model", description=__doc__.split("\n\n")[0])
    ap.add_argument("model", type=Path, help="model file (.pt) to export")
    ap.add_argument("--out", type=Path, default=None, help="exported file (default: the model's path with .npz)")
    ap.add_argument("--check", action="store_true", help="do not write: check that the export belongs to the "
                                                         "model and computes the same Q-values")
    ap.add_argument("--observations", type=int, default=3000, help="observations compared (default 3000)")
    args = ap.parse_args(argv)
    out = args.out or default_export_path(args.model)
    try:
        if not args.check:
            export_model(args.model, out)
            print(f"export_model: wrote {out} ({out.stat().st_size / 1e6:.1f} MB) from {args.model}")
        r = check_export(args.model, out, args.observations)
    except (ValueError, OSError) as exc:
        print(f"export_model: error: {exc}", file=sys.stderr)
        return 1 if args.check else 2
    print(f"export_model: {out} belongs to {args.model}; on {r['observations']} observations of generated 40x40 "
          f"episodes max |Q_numpy - Q_torch| = {r['max_abs_diff']:.2e}, greedy actions identical")
    return 0


if __name__ == "__main__":
    sys.exit(main())
