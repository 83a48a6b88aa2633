"""Training building blocks: transitions, replay ring, demonstration shards, actor episodes, schedules, configs."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from mapf_world.env import MapfEnv
from mapf_world.instances import generate_instance
from mapf_policy.config import TrainConfig
from mapf_policy.network import QNetwork
from mapf_policy.train.__main__ import resolve_config
from mapf_policy.train.actor import epsilon_at, evaluate, run_episode, team_cap_at
from mapf_policy.train.demos import demo_episode, ensure_demos, load_demos
from mapf_policy.train.expert import ShortestPathExpert, plan_actions
from mapf_policy.train.learner import Learner
from mapf_policy.train.log import actor_rule_label
from mapf_policy.train.replay import EpisodeRecorder, ReplayBuffer, to_tensors

SMALL = dict(map_size=10, max_agents=3, curriculum_start_agents=2, expert="shortest_path", demo_instances=3,
             demo_shard_size=2, eval_sizes=(2,), eval_instances=1, max_episode_steps=30, replay_capacity=1000)


@pytest.fixture(autouse=True)
def one_torch_thread():
    """One thread: on the shared 2-core machine more threads only contend (10x slower under load)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _env(seed=0, n=3, size=10):
    inst = generate_instance(seed, size=size, density=0.2, n_agents=n)
    return MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=40)


def test_recorder_stores_compact_transitions_consistent_with_the_env():
    env = _env()
    obs, _ = env.reset()
    rec = EpisodeRecorder()
    acts = np.array([1, 2, 0])
    nxt, rew, term, _, _ = env.step(acts)
    rec.add(obs, acts, rew, nxt, term, expert=np.array([0, 4, 3]))
    arr = rec.arrays()
    assert arr["fov"].dtype == np.uint8 and arr["fov"].shape == (3, 6, 9, 9)
    assert np.array_equal(arr["fov"], obs["fov"]) and np.array_equal(arr["next_fov"], nxt["fov"])
    assert arr["expert"].tolist() == [0, 4, 3] and arr["action"].tolist() == [1, 2, 0]
    t = to_tensors(arr, torch.device("cpu"))
    assert torch.equal(t["next_last_action"], torch.from_numpy(nxt["last_action"]))
    assert torch.equal(t["last_action"], torch.from_numpy(obs["last_action"]))
    bad = dict(obs, fov=obs["fov"] * 0.5)
    with pytest.raises(ValueError, match="0/1"):
        rec.add(bad, acts, rew, nxt, term)


def test_replay_ring_overwrites_oldest_and_checks_fields():
    env = _env()
    obs, _ = env.reset()
    rec = EpisodeRecorder()
    for _ in range(4):
        acts = np.zeros(3, dtype=np.int64)
        nxt, rew, term, _, _ = env.step(acts)
        rec.add(obs, acts, rew, nxt, term)
        obs = nxt
    buf = ReplayBuffer(5, 9)
    buf.add(rec.arrays())  # 12 transitions into 5 slots
    assert len(buf) == 5 and buf.added == 12
    assert sorted(buf.data["reward"].tolist()) == sorted(rec.arrays()["reward"][-5:].tolist())
    buf.add({k: v[:2] for k, v in rec.arrays().items()})  # wraps around: the cursor moves on
    assert buf.cursor == 2 and buf.added == 14
    batch = buf.sample(7, np.random.default_rng(0))
    assert batch["fov"].shape == (7, 6, 9, 9)
    with pytest.raises(ValueError, match="lacks"):
        buf.add({"action": np.zeros(2)})


def test_plan_actions_and_shortest_path_expert():
    plan = np.array([[[0, 0], [2, 2]], [[1, 0], [2, 3]], [[1, 0], [2, 2]]])
    assert plan_actions(plan).tolist() == [[2, 4], [0, 3]]
    with pytest.raises(ValueError, match="not a unit move"):
        plan_actions(np.array([[[0, 0]], [[2, 0]]]))
    env = _env(n=1)
    env.reset()
    expert = ShortestPathExpert(env.grid, env.goals, env.dist)
    a = expert.actions(env.positions)[0]
    d = env.dist[0]
    r, c = env.positions[0]
    step = {1: (-1, 0), 2: (1, 0), 3: (0, -1), 4: (0, 1)}[a]
    assert d[r + step[0], c + step[1]] == d[r, c] - 1


def test_demo_shards_are_cached_and_resumable(tmp_path):
    cfg = TrainConfig(cache_dir=str(tmp_path / "cache"), **SMALL)
    paths = ensure_demos(cfg, tmp_path, progress=False)
    assert len(paths) == 2 and all(p.is_file() for p in paths)
    stamp = paths[0].stat().st_mtime_ns
    paths[1].unlink()  # an interrupted generation: only the missing shard is redone
    ensure_demos(cfg, tmp_path, progress=False)
    assert paths[0].stat().st_mtime_ns == stamp and paths[1].is_file()
    demos, stats = load_demos(paths, 10_000, 9)
    assert stats["instances"] == 3 and demos is not None
    assert (demos["expert"] == demos["action"]).all()  # demonstrations carry a* = a
    with pytest.raises(ValueError, match="demo_shard_size"):
        ensure_demos(TrainConfig(cache_dir=str(tmp_path / "cache"), **dict(SMALL, demo_shard_size=3)), tmp_path)
    arrays, reason = demo_episode(cfg, 0)
    assert reason == "ok" or reason.startswith("expert_")
    small, _ = load_demos(paths, 10, 9)
    assert len(small["action"]) <= 10


def test_actor_episode_relabels_and_evaluation_reports_per_size():
    torch.manual_seed(0)
    net = QNetwork().eval()
    env = _env(n=2)
    expert = ShortestPathExpert(env.grid, env.goals, env.dist)
    rec, stats = run_episode(net, env, 0.5, np.random.default_rng(0), expert, oracle_budget=10.0)
    arr = rec.arrays()
    assert len(arr["action"]) == 2 * stats["steps"] if not stats["success"] else len(arr["action"]) % 2 == 0
    assert (arr["expert"] >= 0).all() and stats["labelled"] == len(arr["action"])
    cfg = TrainConfig(**SMALL)
    result = evaluate(net, cfg, [generate_instance(1, size=10, density=0.2, n_agents=2)])
    assert 1 <= result["sizes"]["2"]["average_step"] <= 30
    assert set(result["sizes"]) == {"2"} and 0.0 <= result["sizes"]["2"]["success_rate"] <= 1.0


def test_actor_episode_can_sample_actions_like_the_evaluated_policy():
    torch.manual_seed(0)
    net = QNetwork().eval()
    runs = {}
    for t in (0.0, 100.0):
        env = _env(n=2)
        rec, _ = run_episode(net, env, 0.0, np.random.default_rng(0), action_temperature=t)
        runs[t] = rec.arrays()["action"]
    # epsilon 0: argmax actions are one fixed function of the state, near-uniform draws are not.
    assert len(set(runs[100.0].tolist())) >= 4 and not np.array_equal(runs[0.0][: len(runs[100.0])], runs[100.0][: len(runs[0.0])])
    with pytest.raises(ValueError, match="actor_action_temperature must be a finite number >= 0"):
        TrainConfig(actor_action_temperature=-0.1).validate()


def test_training_plot_names_the_actors_rule(tmp_path):
    assert actor_rule_label(tmp_path) == "eps-greedy"            # no config.json
    (tmp_path / "config.json").write_text(json.dumps(TrainConfig().asdict()))
    assert actor_rule_label(tmp_path) == "eps-greedy"            # the default: temperature 0
    cfg = TrainConfig(actor_action_temperature=0.04)
    (tmp_path / "config.json").write_text(json.dumps(cfg.asdict()))
    assert actor_rule_label(tmp_path) == "softmax(Q/0.04) + eps"


def test_schedules():
    cfg = TrainConfig(eps_start=0.3, eps_end=0.1, eps_decay_steps=100, curriculum_start_agents=8,
                      max_agents=64, curriculum_steps=100)
    assert epsilon_at(cfg, 0) == pytest.approx(0.3) and epsilon_at(cfg, 50) == pytest.approx(0.2)
    assert epsilon_at(cfg, 1000) == pytest.approx(0.1)
    assert team_cap_at(cfg, 0) == 8 and team_cap_at(cfg, 50) == 36 and team_cap_at(cfg, 500) == 64


def test_learner_update_and_checkpoint_round_trip(tmp_path):
    cfg = TrainConfig(batch_size=8, learning_starts=1, **SMALL)
    env = _env(n=2)
    rec, _ = run_episode(QNetwork().eval(), env, 1.0, np.random.default_rng(0))
    learner = Learner(cfg, tmp_path, rec.arrays())
    for _ in range(3):
        out = learner.update()
    assert np.isfinite(out["loss"]) and learner.step == 3
    learner.save_checkpoint()
    assert learner.online_drawn == 0  # demonstrations only: nothing drawn from the (empty) online replay
    learner.add_online(rec.arrays())
    learner.update()
    assert learner.online_drawn == 8 - round(8 * cfg.demo_fraction)  # counted for the max_replay_ratio cap
    other = Learner(cfg, tmp_path, rec.arrays())
    other.load_checkpoint(tmp_path / "checkpoint.pt")
    assert other.step == 3 and other.online_drawn == 0
    learner.load_checkpoint(tmp_path / "checkpoint.pt")
    for k, v in learner.net.state_dict().items():
        assert torch.equal(v, other.net.state_dict()[k])
    assert other.rng.bit_generator.state == learner.rng.bit_generator.state


def test_learner_target_q_follows_the_target_network(tmp_path):
    """The bootstrap targets come from the fast inference forward; it must track each target update."""
    cfg = TrainConfig(batch_size=8, learning_starts=1, target_update_every=2, **SMALL)
    rec, _ = run_episode(QNetwork().eval(), _env(n=2), 1.0, np.random.default_rng(0))
    learner = Learner(cfg, tmp_path, rec.arrays())
    batch = learner.sample()
    inputs = (batch["next_fov"], batch["next_last_action"], batch["next_position"])
    before = learner.target_q(*inputs).clone()
    learner.update()
    learner.update()  # the second step copies the online weights into the target
    with torch.no_grad():
        ref, online = learner.target(*inputs), learner.net(*inputs)
    after = learner.target_q(*inputs)
    assert (after - before).abs().max().item() > 0
    assert torch.allclose(after, ref, atol=1e-5) and torch.allclose(after, online, atol=1e-5)


def test_configs_validate_and_existing_runs_refuse_other_settings(tmp_path):
    with pytest.raises(ValueError, match="tau_h"):
        TrainConfig(tau_h=0.3).validate()
    with pytest.raises(ValueError, match="variant"):
        TrainConfig(variant="bogus").validate()
    cfg, run_dir = resolve_config({"runs_dir": str(tmp_path), "lr": 1e-3}, tmp_path, resume=False)
    run_dir.mkdir(parents=True)
    (run_dir / "config.json").write_text(json.dumps(cfg.asdict()))
    same, _ = resolve_config({"runs_dir": str(tmp_path), "lr": 1e-3, "total_steps": 7}, tmp_path, resume=True)
    assert same.total_steps == 7 and same.lr == 1e-3
    with pytest.raises(ValueError, match="lr"):
        resolve_config({"runs_dir": str(tmp_path), "lr": 5e-4}, tmp_path, resume=False)
    with pytest.raises(ValueError, match="no run"):
        resolve_config({"runs_dir": str(tmp_path / "elsewhere")}, tmp_path, resume=True)


@pytest.mark.parametrize("start,n_actors", [(0, 1), (0, 3), (7, 3), (5, 4)])
def test_actors_split_episode_indices_without_overlap(start, n_actors):
    from mapf_policy.train.actor import first_episode

    played = []
    for k in range(n_actors):
        first = first_episode(start, k, n_actors)
        assert start <= first < start + n_actors and first % n_actors == k % n_actors
        played += range(first, start + 40, n_actors)
    assert sorted(played) == list(range(start, start + 40))


def test_learner_keeps_a_share_of_the_online_goal_waits(tmp_path):
    """online_goal_keep thins the rows where an agent waits on its goal by the expert's word; nothing else."""
    inst = generate_instance(3, size=10, density=0.2, n_agents=3)
    env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=40)
    expert = ShortestPathExpert(env.grid, env.goals, env.dist)
    rec, (obs, _), done = EpisodeRecorder(), env.reset(), False
    while not done:  # the expert plays: agents arrive at different steps and wait on their goals
        actions = expert.actions(env.positions)
        next_obs, rewards, terminated, truncated, _ = env.step(actions)
        rec.add(obs, actions, rewards, next_obs, terminated, actions)
        obs, done = next_obs, terminated or truncated
    chunk = rec.arrays()
    c = chunk["fov"].shape[-1] // 2
    waits = (chunk["fov"][:, 2:, c, c].sum(axis=1) == 0) & (chunk["expert"] == 0) & ~chunk["terminated"]
    assert 5 <= waits.sum() < len(waits)  # the episode has both kinds of rows
    kept = {}
    for share in (1.0, 0.0, 0.5):
        learner = Learner(TrainConfig(batch_size=8, online_goal_keep=share, **SMALL), tmp_path, None)
        kept[share] = learner.add_online(chunk)
        assert len(learner.online) == kept[share]
    assert kept[1.0] == len(waits)
    assert kept[0.0] == int((~waits).sum())  # every other row stays, terminal rows included
    assert kept[0.0] < kept[0.5] < kept[1.0]
    learner = Learner(TrainConfig(batch_size=8, online_goal_keep=0.0, **SMALL), tmp_path, None)
    learner.add_online(chunk)
    stored = learner.online.sample(len(learner.online), np.random.default_rng(0))
    c_fov = stored["fov"][:, 2:, c, c].sum(axis=1) == 0
    assert not (c_fov & (stored["expert"] == 0) & ~stored["terminated"]).any()
    # learning_starts counts what the actors produced, as their own gate does, not what the filter kept:
    # counting kept rows left actor and learner waiting on each other.
    learner = Learner(TrainConfig(batch_size=8, online_goal_keep=0.0, learning_starts=len(waits), **SMALL),
                      tmp_path, None)
    learner.add_online(chunk)
    assert len(learner.online) < len(waits) and learner.online_ready()
    learner.update()
    assert learner.online_drawn == 8
    with pytest.raises(ValueError, match=r"online_goal_keep must lie in \[0, 1\]"):
        TrainConfig(online_goal_keep=1.5).validate()


def test_agent_orders_and_the_ordered_oracle_return_actions_in_instance_order():
    from mapf_policy.train.expert import OrderedOracle, agent_order

    cells = np.array([[3, 1], [0, 5], [3, 0], [0, 2]])
    assert agent_order("index", cells).tolist() == [0, 1, 2, 3]
    assert agent_order("reversed", cells).tolist() == [3, 2, 1, 0]
    assert agent_order("position", cells).tolist() == [3, 1, 2, 0]  # (0,2) (0,5) (3,0) (3,1)
    with pytest.raises(ValueError, match="unknown expert order"):
        agent_order("random", cells)
    with pytest.raises(ValueError, match="unknown expert order"):
        OrderedOracle(None, cells, "random")

    made = []

    class Planner:  # the planner's agent k answers with action k (its own numbering)
        def __init__(self, goals):
            self.goals = goals
            made.append(goals)

        def actions(self, positions):
            return np.arange(len(positions))

    goals = np.array([[9, 9], [8, 8], [7, 7], [6, 6]])
    oracle = OrderedOracle(Planner, goals, "position")
    out = oracle.actions(cells)
    assert out.tolist() == [3, 1, 2, 0]  # instance agent p[k] gets the planner's action k
    assert made[0].tolist() == goals[[3, 1, 2, 0]].tolist()  # goals handed over in the same order
    oracle.actions(cells + 1)  # same order: the same planner
    assert len(made) == 1
    oracle.actions(cells[[1, 0, 2, 3]])  # agents swapped places: a new order, a new plan
    assert len(made) == 2


def test_odrmstar_labels_in_another_agent_order_are_plans_of_the_same_instance():
    from mapf_policy.train.demos import generated_cases
    from mapf_policy.train.expert import make_oracle

    inst = generated_cases(3, 4, [6], 1, 10, 0.2)[0]
    for order in ("index", "reversed", "position"):
        env = MapfEnv(inst.grid, inst.starts, inst.goals, fov_size=9, max_steps=60)
        env.reset()
        oracle = make_oracle("odrmstar", env.grid, env.goals, env.dist, 1.0, 5.0, order)
        terminated = truncated = False
        while not (terminated or truncated):
            _, _, terminated, truncated, info = env.step(oracle.actions(env.positions))
        assert terminated, order  # following the labels brings every agent to its goal
    TrainConfig(expert_order="position").validate()
    with pytest.raises(ValueError, match="expert_order must be one of"):
        TrainConfig(expert_order="random").validate()
