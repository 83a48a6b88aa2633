"""Expert demonstrations: generated training instances solved by the expert, cached as .npz shards.

Cache layout: <cache_dir>/demos/<key>/shard_<k>.npz holds instances k*S .. (k+1)*S-1 (S = demo_shard_size),
where <key> names everything that changes the data (world, team sizes, expert, fov, seed). A shard is
written atomically once complete, so generation is resumable: an interrupted run redoes at most the
shards in flight. Instance i is drawn from SeedSequence([seed, DEMO_STREAM, i]) with mapf_world's
generator: training instances never come from the benchmark files.

Each solved instance is replayed through MapfEnv with the expert's moves, giving every agent's
transitions (s, a*, r, s') with expert label a* = a; an instance whose plan the env does not reproduce
(a rule mismatch) is dropped and counted.
"""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mapf_world.env import MapfEnv
from mapf_world.instances import generate_instance
from mapf_policy.action_selection import on_goal
from mapf_policy.config import TrainConfig
from mapf_policy.train.expert import ExpertFailed, plan_actions, solve
from mapf_policy.train.replay import EpisodeRecorder, concat, field_specs

DEMO_STREAM, ACTOR_STREAM, VALID_STREAM, COMPARE_STREAM = 1, 2, 3, 4
MINE_STREAM = 5  # dqn_hscl's mined greedy episodes (Args.mine_episodes)


def instance_rng(seed: int, stream: int, index: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, stream, index]))


def generated_cases(seed: int, stream: int, sizes, cases: int, map_size: int, density: float) -> list:
    """`cases` generated instances per team size in `sizes`, fixed by (seed, stream); never benchmark cases."""
    return [generate_instance(instance_rng(seed, stream, int(n) * 100_000 + k), size=map_size, density=density,
                              n_agents=int(n)) for n in sizes for k in range(cases)]


def demo_dir(cfg: TrainConfig, root: Path) -> Path:
    key = (f"m{cfg.map_size}_d{cfg.density:g}_a{cfg.min_agents}-{cfg.max_agents}_{cfg.expert}"
           f"_e{cfg.expert_epsilon:g}_t{cfg.expert_time_limit:g}_fov{cfg.fov_size}_s{cfg.seed}")
    return (root / cfg.cache_dir / "demos" / key).resolve()


def demo_team_size(cfg: TrainConfig, rng: np.random.Generator) -> int:
    return int(rng.integers(cfg.min_agents, cfg.max_agents + 1))


def demo_episode(cfg: TrainConfig, index: int) -> tuple[dict | None, str]:
    """Transitions of demonstration instance `index`, or (None, reason) when the expert gives none."""
    rng = instance_rng(cfg.seed, DEMO_STREAM, index)
    n = demo_team_size(cfg, rng)
    inst = generate_instance(rng, size=cfg.map_size, density=cfg.density, n_agents=n)
    env = MapfEnv(inst.grid, inst.starts, inst.goals, fov_size=cfg.fov_size, max_steps=cfg.max_episode_steps)
    try:
        plan = solve(cfg.expert, env, cfg.expert_epsilon, cfg.expert_time_limit)
    except ExpertFailed as exc:
        return None, f"expert_{exc.reason}"
    if len(plan) - 1 > cfg.max_episode_steps:
        return None, "plan_too_long"
    actions = plan_actions(plan)
    obs, info = env.reset()
    if info["success"]:
        return None, "trivial"
    rec = EpisodeRecorder()
    for t, act in enumerate(actions):
        next_obs, rewards, terminated, truncated, _ = env.step(act)
        if not np.array_equal(env.positions, plan[t + 1]):
            return None, "rule_mismatch"
        rec.add(obs, act, rewards, next_obs, terminated, expert=act)
        obs = next_obs
        if terminated or truncated:
            break
    return (rec.arrays(), "ok") if terminated else (None, "plan_not_finished")


def write_shard(cfg: TrainConfig, root: Path, shard: int) -> dict:
    """Generate and atomically write one shard; returns its counts."""
    t0 = time.perf_counter()
    chunks, reasons = [], {}
    first = shard * cfg.demo_shard_size
    per_instance = []  # [index, team size, outcome, seconds]: which team sizes the expert covers
    for index in range(first, min(first + cfg.demo_shard_size, cfg.demo_instances)):
        t1 = time.perf_counter()
        arrays, reason = demo_episode(cfg, index)
        reasons[reason] = reasons.get(reason, 0) + 1
        n = demo_team_size(cfg, instance_rng(cfg.seed, DEMO_STREAM, index))
        per_instance.append([index, n, reason, round(time.perf_counter() - t1, 3)])
        if arrays is not None:
            chunks.append(arrays)
    specs = field_specs(cfg.fov_size)
    data = concat(chunks) if chunks else {k: np.zeros((0,) + s, dtype=d) for k, (d, s) in specs.items()}
    meta = {"shard": shard, "instances": sum(reasons.values()), "outcomes": reasons,
            "transitions": int(len(data["action"])), "seconds": round(time.perf_counter() - t0, 2),
            "per_instance": per_instance}
    out = demo_dir(cfg, root)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".shard_{shard:05d}.tmp.npz"
    np.savez_compressed(tmp, meta=np.array(json.dumps(meta)), **data)
    os.replace(tmp, out / f"shard_{shard:05d}.npz")
    return meta


def _write_shard_job(args) -> dict:
    cfg_dict, root, shard = args
    return write_shard(TrainConfig.from_dict(cfg_dict), Path(root), shard)


def n_shards(cfg: TrainConfig) -> int:
    return -(-cfg.demo_instances // cfg.demo_shard_size)


def check_manifest(cfg: TrainConfig, out: Path) -> None:
    """The shard size fixes which instances a shard holds; a cache made with another one is refused."""
    out.mkdir(parents=True, exist_ok=True)
    manifest = out / "manifest.json"
    if not manifest.is_file():
        manifest.write_text(json.dumps({"demo_shard_size": cfg.demo_shard_size}))
    made_with = json.loads(manifest.read_text())["demo_shard_size"]
    if made_with != cfg.demo_shard_size:
        raise ValueError(f"demo cache {out} was made with demo_shard_size {made_with}, this run asks for "
                         f"{cfg.demo_shard_size}; use the same value or another cache_dir")


def ensure_demos(cfg: TrainConfig, root: Path, progress: bool = True) -> list[Path]:
    """Generate the shards that are missing (resumable); returns all shard paths."""
    out = demo_dir(cfg, root)
    check_manifest(cfg, out)
    paths = [out / f"shard_{k:05d}.npz" for k in range(n_shards(cfg))]
    missing = [k for k, p in enumerate(paths) if not p.is_file()]
    if missing:
        bar = tqdm(total=len(missing), desc=f"expert demos ({cfg.expert})", unit="shard", disable=not progress)
        jobs = [(cfg.asdict(), str(root), k) for k in missing]
        if cfg.data_workers > 1:
            with mp.get_context("spawn").Pool(cfg.data_workers) as pool:
                for meta in pool.imap_unordered(_write_shard_job, jobs):
                    bar.update(1)
                    bar.set_postfix(transitions=meta["transitions"])
        else:
            for job in jobs:
                meta = _write_shard_job(job)
                bar.update(1)
                bar.set_postfix(transitions=meta["transitions"])
        bar.close()
    return paths


def on_goal_stays(chunk: dict) -> np.ndarray:
    """Rows where the agent stands on its goal (action_selection.on_goal) and the expert says stay."""
    return on_goal(chunk["fov"]) & (chunk["expert"] == 0)


def load_demos(paths: list[Path], capacity: int, fov_size: int, goal_keep: float = 1.0,
               seed: int = 0) -> tuple[dict | None, dict]:
    """The shards' transitions, evenly subsampled to at most `capacity`; (None, stats) if there are none.

    About two thirds of raw demonstration rows are agents waiting on their goals for the rest of the
    team; only a share `goal_keep` of them is kept (drawn with `seed`), the informative rows all are.
    """
    rng = np.random.default_rng(np.random.SeedSequence([seed, 4]))
    specs = field_specs(fov_size)
    stride, chunks, stats = 1, [], {"shards": len(paths), "instances": 0, "solved": 0, "transitions_cached": 0}
    for p in paths:
        with np.load(p, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            stats["instances"] += meta["instances"]
            stats["solved"] += meta["outcomes"].get("ok", 0)
            stats["transitions_cached"] += meta["transitions"]
            if meta["transitions"] == 0:
                continue
            chunk = {k: data[k] for k in specs}
        keep = ~on_goal_stays(chunk) | (rng.random(len(chunk["action"])) < goal_keep)
        chunks.append({k: v[keep][::stride] for k, v in chunk.items()})
        # Streaming even subsample: past 2x capacity, keep every other row (now and from here on),
        # so memory stays near 2x capacity however large the cache grows.
        if sum(len(c["action"]) for c in chunks) > 2 * capacity:
            chunks = [{k: v[::2] for k, v in c.items()} for c in chunks]
            stride *= 2
    if not chunks or sum(len(c["action"]) for c in chunks) == 0:
        return None, stats
    demos = concat(chunks)
    total = len(demos["action"])
    if total > capacity:
        idx = np.linspace(0, total - 1, capacity).astype(np.int64)
        demos = {k: v[idx] for k, v in demos.items()}
    stats["transitions_loaded"] = int(len(demos["action"]))
    stats["expert_action_shares"] = np.round(np.bincount(demos["expert"], minlength=5) / len(demos["expert"]), 3).tolist()
    return demos, stats
