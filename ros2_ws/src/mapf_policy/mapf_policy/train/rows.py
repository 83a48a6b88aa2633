"""Expert-labelled states on disk, for offline fitting: `scripts/collect_rows`.

A model plays generated episodes as the training actors do (softmax(Q / T), settled agents greedy, no
epsilon; agreement.play) and ODrM* labels every visited state until its time budget is spent. The
labelled rows (observation, last action, position, expert action, team size) go to OUT/shard_<k>.npz,
`--shard-episodes` episodes per shard, each written atomically once complete: an interrupted collection
resumes at the first missing shard, and the same command gives the same rows.

Instances come from their own seed stream ROWS_STREAM, apart from the demonstration, actor, validation
and comparison streams; `--held-out` draws them from COMPARE_STREAM instead, for rows to evaluate on
(never fit on those). Never benchmark cases.
  scripts/collect_rows models/hscl.pt runs/rows_train --sizes 16 32 48 64 --cases 20
  scripts/collect_rows models/hscl.pt runs/rows_heldout --held-out --sizes 64 --cases 4 --seed 23
The model's actions do not depend on the labels, so the same command with another --expert-order visits
the same states and labels them otherwise.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from mapf_policy.train.agreement import Setup, add_setup_arguments, load_forward, play, setup_from_args
from mapf_policy.train.demos import COMPARE_STREAM, generated_cases

ROWS_STREAM = 5
ROW_FIELDS = ("fov", "last_action", "position", "expert", "n_agents")
MANIFEST = "rows.json"


def labelled_rows(rows: dict, n_agents: int) -> dict:
    """The labelled rows of one episode (expert >= 0) with the fields an offline fit needs."""
    keep = rows["expert"] >= 0
    out = {k: rows[k][keep] for k in ("fov", "last_action", "position", "expert")}
    out["n_agents"] = np.full(int(keep.sum()), n_agents, dtype=np.int16)
    return out


def _shard_path(out: Path, k: int) -> Path:
    return out / f"shard_{k:05d}.npz"


def _check_manifest(out: Path, manifest: dict) -> None:
    """A directory holds the rows of one collection: refuse to mix in rows of other settings."""
    path = out / MANIFEST
    if path.is_file():
        old = json.loads(path.read_text())
        if old != manifest:
            diff = sorted(k for k in set(old) | set(manifest) if old.get(k) != manifest.get(k))
            raise ValueError(f"{out} holds rows of other settings (differs in {diff}); use another directory")
    else:
        out.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(manifest, indent=1))


def collect(model, out: Path, sizes, cases: int, seed: int, setup: Setup, held_out: bool = False,
            shard_episodes: int = 4, map_size: int = 40, density: float = 0.3, progress: bool = False) -> dict:
    """Play and label `cases` episodes per team size into shards under `out`; returns a summary.

    Episode k (in the order of `sizes`, then case) samples with default_rng(k), as agreement.play does."""
    if shard_episodes < 1:
        raise ValueError(f"shard_episodes must be >= 1, got {shard_episodes}")
    stream = COMPARE_STREAM if held_out else ROWS_STREAM
    manifest = {"model": str(model), "sizes": [int(n) for n in sizes], "cases": int(cases), "seed": int(seed),
                "stream": stream, "setup": asdict(setup), "shard_episodes": int(shard_episodes),
                "map_size": int(map_size), "density": float(density)}
    forward, ncfg = load_forward(model)
    _check_manifest(out, manifest)
    instances = generated_cases(seed, stream, sizes, cases, map_size, density)
    n_shards = -(-len(instances) // shard_episodes)
    todo = [k for k in range(n_shards) if not _shard_path(out, k).is_file()]
    solved = 0
    bar = tqdm(total=len(todo) * shard_episodes, desc=f"rows -> {out.name}", unit="episode", disable=not progress)
    for k in todo:
        chunks = []
        for e in range(k * shard_episodes, min(len(instances), (k + 1) * shard_episodes)):
            rows, success = play(forward, ncfg.fov_size, instances[e], e, setup)
            chunks.append(labelled_rows(rows, instances[e].n_agents))
            solved += int(success)
            bar.update(1)
        shard = {f: np.concatenate([c[f] for c in chunks]) for f in ROW_FIELDS}
        tmp = _shard_path(out, k).with_suffix(".tmp.npz")
        np.savez(tmp, **shard)
        os.replace(tmp, _shard_path(out, k))
    bar.close()
    return {"shards": n_shards, "new_shards": len(todo), "episodes": len(instances), "rows": row_count(out),
            "solved_in_new_shards": solved}


def row_count(directory: Path) -> int:
    return sum(len(np.load(p)["expert"]) for p in sorted(Path(directory).glob("shard_*.npz")))


def load_rows(directories) -> dict:
    """All rows of the shards in `directories`, concatenated; a clear error when there are none."""
    paths = []
    for d in directories:
        found = sorted(Path(d).glob("shard_*.npz"))
        if not found:
            raise ValueError(f"{d} holds no row shards (shard_*.npz); collect them with scripts/collect_rows")
        paths += found
    parts = []
    for p in paths:
        with np.load(p) as z:
            missing = set(ROW_FIELDS) - set(z.files)
            if missing:
                raise ValueError(f"{p} lacks the fields {sorted(missing)}")
            parts.append({f: z[f] for f in ROW_FIELDS})
    return {f: np.concatenate([c[f] for c in parts]) for f in ROW_FIELDS}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/collect_rows", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", type=Path, help="the model that plays the episodes")
    p.add_argument("out", type=Path, help="directory of the row shards (created; resumed when it exists)")
    p.add_argument("--sizes", type=int, nargs="+", default=[16, 32, 48, 64], help="team sizes (default 16 32 48 64)")
    p.add_argument("--cases", type=int, default=10, help="episodes per team size (default 10)")
    p.add_argument("--seed", type=int, default=0, help="seed of the generated instances (default 0)")
    p.add_argument("--held-out", action="store_true",
                   help="draw the instances from the comparison stream (rows to evaluate on, never to fit on)")
    add_setup_arguments(p)
    p.add_argument("--shard-episodes", type=int, default=4, help="episodes per shard file (default 4)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    bad = [n for n in args.sizes + [args.cases, args.shard_episodes] if n < 1]
    if bad:
        p.error(f"--sizes, --cases and --shard-episodes must be positive, got {bad}")
    setup = setup_from_args(p, args)
    if not args.model.is_file():
        p.error(f"no such model file: {args.model}")
    torch.set_num_threads(1)
    try:
        summary = collect(args.model, args.out, args.sizes, args.cases, args.seed, setup, args.held_out,
                          args.shard_episodes, args.map_size, args.density, not args.no_progress)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
