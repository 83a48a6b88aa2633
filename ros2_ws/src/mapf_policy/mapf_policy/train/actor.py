"""Actor process: epsilon-greedy (or sampled) episodes in generated worlds, expert relabelling, greedy validation.

Each actor runs in its own process (spawn) beside the learner, so that data generation and learning
overlap: one thread each (on this 2-core machine one actor; on a many-core GPU machine, one per spare
core). All agents of an episode go through the network in one batch. Actor k of N plays the episodes
whose index is k modulo N, so every episode index (and its generated world) is played once.
Protocol with the learner (multiprocessing queues):
  weights_q  learner -> actor (one queue per actor): {"step", "state_dict" (numpy arrays)}; the newest wins;
  data_q     actors -> learner: {"kind": "episode", "episode", "transitions", "stats"} or {"kind": "eval", ...};
  shared     learner_step (the learner's step, for epsilon and curriculum), stop (an Event).
An actor waits while the actors together are ahead of the learner by more than the replay ratio allows
(each keeps its 1/N share), which leaves the CPU to the learner instead of filling the replay with
samples that will never be drawn. Only actor 0 runs the greedy validation.
"""
from __future__ import annotations

import json
import queue
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from mapf_world.env import MapfEnv
from mapf_world.instances import generate_instance
from mapf_policy.action_selection import select_actions, settled
from mapf_policy.config import TrainConfig
from mapf_policy.inference import InferenceNet
from mapf_policy.model_io import save_model
from mapf_policy.network import QNetwork
from mapf_policy.train.demos import ACTOR_STREAM, VALID_STREAM, generated_cases, instance_rng
from mapf_policy.train.expert import ExpertFailed, make_oracle
from mapf_policy.train.replay import EpisodeRecorder


def epsilon_at(cfg: TrainConfig, step: int) -> float:
    frac = min(1.0, step / cfg.eps_decay_steps) if cfg.eps_decay_steps else 1.0
    return cfg.eps_start + frac * (cfg.eps_end - cfg.eps_start)


def team_cap_at(cfg: TrainConfig, step: int) -> int:
    """Largest team size drawn at `step` (linear curriculum from curriculum_start_agents to max_agents)."""
    start = min(cfg.curriculum_start_agents, cfg.max_agents)
    frac = min(1.0, step / cfg.curriculum_steps) if cfg.curriculum_steps else 1.0
    return max(cfg.min_agents, int(round(start + frac * (cfg.max_agents - start))))


def greedy_q(net: QNetwork | InferenceNet, obs: dict) -> np.ndarray:
    """(n_agents, 5) Q-values, all agents in one batch; an InferenceNet computes them faster on CPU."""
    with torch.inference_mode():
        return net(torch.from_numpy(obs["fov"]), torch.from_numpy(obs["last_action"]),
                   torch.from_numpy(obs["position"])).numpy()


def run_episode(net: QNetwork | InferenceNet, env: MapfEnv, epsilon: float, rng: np.random.Generator,
                oracle=None, oracle_budget: float = 0.0, record: bool = True,
                action_temperature: float = 0.0) -> tuple[EpisodeRecorder, dict]:
    """One episode; with `oracle`, states get expert labels until it fails or its time budget is spent.

    Each agent takes a uniformly random action with probability `epsilon`, else the argmax of its
    Q-values (action_temperature 0) or a draw from softmax(Q / T) with settled agents greedy (T > 0).
    """
    obs, _ = env.reset()
    rec = EpisodeRecorder()
    labelled = oracle_time = 0.0
    oracle_failure = ""
    terminated = truncated = False
    while not (terminated or truncated):
        rows = settled(obs["fov"]) if action_temperature > 0 else None
        actions = select_actions(greedy_q(net, obs), action_temperature, rng, greedy_rows=rows)
        explore = rng.random(env.n_agents) < epsilon
        actions[explore] = rng.integers(0, 5, int(explore.sum()))
        expert = None
        if oracle is not None and oracle_time < oracle_budget:
            t0 = time.perf_counter()
            try:
                expert = oracle.actions(env.positions)
                labelled += env.n_agents
            except ExpertFailed as exc:
                oracle, oracle_failure = None, exc.reason
            oracle_time += time.perf_counter() - t0
        next_obs, rewards, terminated, truncated, _ = env.step(actions)
        if record:
            rec.add(obs, actions, rewards, next_obs, terminated, expert)
        obs = next_obs
    stats = {"success": bool(terminated), "steps": env.step_count if terminated else env.max_steps,
             "n_agents": env.n_agents, "labelled": labelled, "oracle_seconds": oracle_time,
             "oracle_failure": oracle_failure, "transitions": len(rec)}
    return rec, stats


def validation_instances(cfg: TrainConfig) -> list:
    """Fixed generated validation cases (own seed stream; never benchmark cases)."""
    return generated_cases(cfg.seed, VALID_STREAM, cfg.eval_sizes, cfg.eval_instances, cfg.map_size, cfg.density)


def evaluate_by_size(net: QNetwork | InferenceNet, instances: list, fov_size: int, max_steps: int, progress: bool = False,
                     desc: str = "", last_action: str = "requested") -> dict:
    """Greedy runs: {team size (str): success_rate, average_step (a failure counts max_steps), successes, cases}.
    `last_action`: the observation's last-action mode the model was trained with (MapfEnv)."""
    outcomes = []
    for inst in tqdm(instances, desc=desc, unit="case", disable=not progress):
        env = MapfEnv(inst.grid, inst.starts, inst.goals, fov_size=fov_size, max_steps=max_steps, last_action=last_action)
        _, stats = run_episode(net, env, 0.0, np.random.default_rng(0), record=False)
        outcomes.append((inst.n_agents, stats["success"], stats["steps"]))
    return summarize_by_size(outcomes)


def summarize_by_size(outcomes) -> dict:
    """(team size, success, steps) per case -> {team size (str): success_rate, average_step, successes, cases}."""
    by_size: dict[int, list] = {}
    for n, success, steps in outcomes:
        by_size.setdefault(int(n), []).append((bool(success), steps))
    return {str(n): {"success_rate": float(np.mean([s for s, _ in runs])),
                     "average_step": float(np.mean([t for _, t in runs])),
                     "successes": int(sum(s for s, _ in runs)), "cases": len(runs)}
            for n, runs in sorted(by_size.items())}


def evaluate(net: QNetwork | InferenceNet, cfg: TrainConfig, instances: list) -> dict:
    """Greedy success rate and average step per team size, and one score to pick the best snapshot."""
    sizes = evaluate_by_size(net, instances, cfg.fov_size, cfg.max_episode_steps)
    # Success first; the average step breaks ties (1e-4 per step never outweighs one more success).
    score = np.mean([v["success_rate"] for v in sizes.values()]) - 1e-4 * np.mean([v["average_step"] for v in sizes.values()])
    return {"sizes": sizes, "score": float(score)}


def put_until_stopped(q, item, stop) -> bool:
    """Put on a bounded queue, giving up when `stop` is set (the learner may have ended)."""
    while not stop.is_set():
        try:
            q.put(item, timeout=0.5)
            return True
        except queue.Full:
            continue
    return False


def _load_weights(net: QNetwork, weights_q, current_step: int) -> int:
    latest = None
    while True:
        try:
            latest = weights_q.get_nowait()
        except queue.Empty:
            break
    if latest is None:
        return current_step
    net.load_state_dict({k: torch.from_numpy(v) for k, v in latest["state_dict"].items()})
    return int(latest["step"])


def first_episode(start_episode: int, actor_index: int, n_actors: int) -> int:
    """The first episode index >= start_episode that actor `actor_index` of `n_actors` plays."""
    return start_episode + (actor_index - start_episode) % n_actors


def actor_main(cfg_dict: dict, run_dir: str, start_episode: int, weights_q, data_q, learner_step, stop,
               actor_index: int = 0) -> None:
    cfg = TrainConfig.from_dict(cfg_dict)
    if not 0 <= actor_index < cfg.actors:
        raise ValueError(f"actor_index {actor_index} outside 0..{cfg.actors - 1}")
    torch.set_num_threads(cfg.actor_threads)
    run_dir = Path(run_dir)
    net = QNetwork(cfg.network_config()).eval()
    forward = InferenceNet(net)  # follows the weights loaded into net
    weights_step = _load_weights(net, weights_q, -1)
    while weights_step < 0 and not stop.is_set():  # wait for the learner's first weights
        time.sleep(0.05)
        weights_step = _load_weights(net, weights_q, -1)
    best_path = run_dir / "best.json"
    best = json.loads(best_path.read_text())["score"] if best_path.is_file() else -np.inf
    valid = validation_instances(cfg) if cfg.eval_minutes > 0 and actor_index == 0 else []
    last_eval = time.monotonic()
    episode, produced, first_step = first_episode(start_episode, actor_index, cfg.actors), 0, learner_step.value
    online_share = cfg.batch_size * (1.0 - cfg.demo_fraction)
    while not stop.is_set():
        weights_step = _load_weights(net, weights_q, weights_step)
        step = learner_step.value
        allowance = (cfg.learning_starts + (step - first_step) * online_share / cfg.replay_ratio) / cfg.actors
        if produced > allowance:
            time.sleep(0.02)  # ahead of the learner: let it catch up
            continue
        if valid and time.monotonic() - last_eval > 60.0 * cfg.eval_minutes:
            result = evaluate(forward, cfg, valid)
            result["step"] = weights_step
            if result["score"] > best:
                best = result["score"]
                save_model(run_dir / "best.pt", net, cfg.network_config(),
                           {"step": weights_step, "validation": result, "train_config": cfg.asdict()})
                best_path.write_text(json.dumps(result, indent=1))
            put_until_stopped(data_q, {"kind": "eval", "result": result}, stop)
            last_eval = time.monotonic()
            continue
        rng = instance_rng(cfg.seed, ACTOR_STREAM, episode)
        n = int(rng.integers(cfg.min_agents, team_cap_at(cfg, step) + 1))
        inst = generate_instance(rng, size=cfg.map_size, density=cfg.density, n_agents=n)
        env = MapfEnv(inst.grid, inst.starts, inst.goals, fov_size=cfg.fov_size, max_steps=cfg.max_episode_steps)
        oracle = None
        if rng.random() < cfg.relabel_fraction:
            # One (re)plan may not take more than the episode's whole labelling budget.
            limit = min(cfg.expert_time_limit, cfg.relabel_time_budget)
            oracle = make_oracle(cfg.expert, env.grid, env.goals, env.dist, cfg.expert_epsilon, limit, cfg.expert_order)
        eps = epsilon_at(cfg, step)
        rec, stats = run_episode(forward, env, eps, rng, oracle, cfg.relabel_time_budget,
                                 action_temperature=cfg.actor_action_temperature)
        stats.update(epsilon=eps, weights_step=weights_step)
        transitions = rec.arrays()
        produced += len(transitions["action"])
        # "episode" is the count of episode indices started so far (the learner resumes from the largest).
        put_until_stopped(data_q, {"kind": "episode", "episode": episode + 1, "transitions": transitions, "stats": stats},
                          stop)
        episode += cfg.actors
