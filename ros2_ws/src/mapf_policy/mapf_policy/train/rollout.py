"""The rollout search of the second design (beyond the paper; issue 20): where a greedy team loops, which single step
of one agent gets it out, and the screen that finds the episodes worth searching.

dqn_hscl uses it for Args.stuck_rollout (the search's move is played and labels its agent's row) and for mining
(Args.mine_episodes: greedy episodes of their own seed stream whose only rows are the search's labels)."""
from __future__ import annotations

import copy

import numpy as np
import torch

from mapf_policy.config import NetworkConfig
from mapf_policy.network import network_inputs
from mapf_policy.train.demos import MINE_STREAM, instance_rng
from mapf_world.env import MapfEnv
from mapf_world.instances import generate_instance


def greedy_gets_stuck(forward, envs: list[MapfEnv]) -> np.ndarray:
    """(len(envs),) bool: whether each fresh episode's greedy team reaches a joint state it was in before (a cycle)
    before it ends, i.e. whether play_episode(greedy_until_stuck=1, stuck_cycles=True) would search a deviation
    there. All teams play in lockstep, one network call a step for all of them: mining (Args.mine_episodes) screens
    its episodes so, and plays again, one by one with the search, only those that get stuck, about one in twenty of
    a trained policy's on 4x20. The envs are played to their end (reset them, or build new ones, to play again)."""
    cfg = getattr(forward, "cfg", NetworkConfig())
    obs = [env.reset()[0] for env in envs]
    seen = [{env.joint_state()} for env in envs]
    stuck, active = np.zeros(len(envs), dtype=bool), list(range(len(envs)))
    while active:
        parts = [network_inputs(obs[i], cfg) for i in active]
        with torch.inference_mode():
            q = forward(*(torch.cat(column) for column in zip(*parts))).numpy()
        actions = np.split(q.argmax(axis=1), np.cumsum([envs[i].n_agents for i in active])[:-1])
        still_active = []
        for i, a in zip(active, actions):
            obs[i], _, terminated, truncated, _ = envs[i].step(a)
            state_now = envs[i].joint_state()
            if terminated or truncated:
                continue
            if state_now in seen[i]:
                stuck[i] = True
                continue
            seen[i].add(state_now)
            still_active.append(i)
        active = still_active
    return stuck


def mining_envs(seed: int, first: int, count: int, agents: int, size: int, density: float, max_steps: int,
                last_action: str, cfg: NetworkConfig) -> list[MapfEnv]:
    """Episodes first .. first + count - 1 of the mining seed stream (MINE_STREAM), as fresh environments with the
    observation channels network `cfg` reads."""
    envs = []
    for e in range(first, first + count):
        inst = generate_instance(instance_rng(seed, MINE_STREAM, e), size=size, density=density, n_agents=agents)
        envs.append(MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=max_steps, last_action=last_action,
                            **cfg.env_channels()))
    return envs


def best_deviation(forward, env: MapfEnv, actions: np.ndarray, horizon: int, stuck_steps: int,
                   cycles: bool = False) -> tuple[int, int] | None:
    """(agent, action) that gets a greedy team out of a fixed point, or None.

    For each agent i and each action a other than its greedy one (actions), a copy of the episode plays the joint
    actions with a in place of agent i's, then greedy play for up to `horizon` steps, stopping early where the copy
    stands still `stuck_steps` steps again (with `cycles`: where its joint state repeats, so it loops for ever). A deviation refused at once is skipped. Best: solved in the fewest steps;
    else the lowest sum over agents of the distance to the goal at the copy's end, if below the sum now."""
    dist = env.dist
    idx = np.arange(env.n_agents)
    sum_dist = lambda pos: int(dist[idx, pos[:, 0], pos[:, 1]].sum())  # noqa: E731
    cfg = getattr(forward, "cfg", NetworkConfig())
    best, best_key = None, (1, sum_dist(env.positions))  # (0, steps) solved; (1, sum of distances) not
    for i in range(env.n_agents):
        for a in range(5):
            if a == actions[i]:
                continue
            sim = copy.deepcopy(env)
            joint = actions.copy()
            joint[i] = a
            obs, _, done, truncated, info = sim.step(joint)
            if info["failed"][i]:
                continue
            still, steps, visited, looped = 0, 1, {sim.joint_state()}, False
            while not (done or truncated) and steps <= horizon and not looped and (cycles or still < stuck_steps):
                with torch.inference_mode():
                    greedy = forward(*network_inputs(obs, cfg)).numpy().argmax(axis=1)
                before = sim.positions
                obs, _, done, truncated, _ = sim.step(greedy)
                still = still + 1 if np.array_equal(before, sim.positions) else 0
                steps += 1
                if cycles:
                    looped = sim.joint_state() in visited
                    visited.add(sim.joint_state())
            key = (0, steps) if done else (1, sum_dist(sim.positions))
            if key < best_key:
                best, best_key = (i, a), key
    return best
