"""The recurrent variant (beyond the paper): a GRU memory per agent, sequence replay from stored memories."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from mapf_policy.config import NetworkConfig
from mapf_policy.export import export_model
from mapf_policy.inference import FastForward, InferenceNet
from mapf_policy.model_io import save_model
from mapf_policy.network import QNetwork, count_parameters, network_inputs
from mapf_policy.train.dqn_hscl import (Args, RecurrentActor, Replay, acting, episode_rows, play_episode,
                                         recurrent_batch)
from mapf_world.env import MapfEnv
from mapf_world.instances import generate_instance


def _net(seed=0, **kw):
    torch.manual_seed(seed)
    return QNetwork(NetworkConfig(dueling=True, recurrent=True, **kw)).eval()


def _obs(n=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    fov = (torch.rand(n, 6, 9, 9, generator=g) < 0.3).float()
    return fov, torch.eye(5)[torch.arange(n) % 5], torch.rand(n, 2, generator=g) * 20


def test_the_memory_adds_one_gru_cell_and_the_feed_forward_call_is_refused():
    plain, rec = QNetwork(NetworkConfig(dueling=True)), _net()
    h = rec.cfg.hidden_features
    assert count_parameters(rec) - count_parameters(plain) == 3 * 2 * (h * h + h)
    with pytest.raises(ValueError, match="recurrent"):
        rec(*_obs())
    with pytest.raises(ValueError, match="no memory"):
        plain.step(*_obs())
    with pytest.raises(ValueError, match="memory h must have shape"):
        rec.step(*_obs(), h=torch.zeros(2, h))


def test_a_step_from_no_memory_is_a_step_from_zeros_and_the_memory_changes_q():
    net, obs = _net(), _obs()
    with torch.no_grad():
        q0, h1 = net.step(*obs)
        qz, hz = net.step(*obs, h=torch.zeros(3, net.cfg.hidden_features))
        q2, _ = net.step(*obs, h=h1)
    assert torch.equal(q0, qz) and torch.equal(h1, hz)
    assert not torch.allclose(q0, q2)  # the same observation, another memory


def test_the_fast_embedding_matches_the_network():
    net, obs = _net(), _obs(n=40)
    with torch.no_grad():
        ref = net.embed(*obs)
    assert torch.allclose(FastForward(net).embed(*obs), ref, atol=1e-4)
    assert torch.allclose(InferenceNet(net).embed(*obs), ref, atol=1e-4)


def test_recurrent_models_have_no_robot_export(tmp_path):
    net = _net()
    save_model(tmp_path / "r.pt", net, net.cfg, {})
    with pytest.raises(ValueError, match="recurrent"):
        export_model(tmp_path / "r.pt")


def _episode(net, seed=3, agents=3, size=8, steps=20):
    inst = generate_instance(np.random.default_rng(seed), size=size, density=0.2, n_agents=agents)
    env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=steps, last_action="executed")
    actor = acting(net)
    assert isinstance(actor, RecurrentActor)
    qs = []

    class Recording(RecurrentActor):  # keeps every step's Q-values
        def __call__(self, *inputs):
            qs.append(super().__call__(*inputs).clone())
            return qs[-1]

    rec = Recording(net)
    out = play_episode(rec, env, 0.3, np.random.default_rng(seed))
    return out, torch.stack(qs)  # (T, N, 5)


def test_play_episode_stores_the_memory_before_each_step():
    net = _net()
    (steps, stats), qs = _episode(net)
    assert len(steps["h_in"]) == stats["steps"] == len(qs)
    assert not np.any(steps["h_in"][0])  # an episode starts with no memory
    with torch.no_grad():  # the stored memory and the observation give the actor's Q-values again
        t = stats["steps"] // 2
        q, _ = net.step(*network_inputs(steps["obs"][t], net.cfg), h=torch.from_numpy(steps["h_in"][t]).float())
    assert torch.allclose(q, qs[t], atol=2e-3)  # the memory is stored in float16


def test_sequences_follow_one_agent_within_its_episode():
    replay = Replay(1000, hidden=4)
    for e, (t_len, n) in enumerate([(5, 2), (3, 3)]):
        rows = {k: np.zeros((t_len * n,) + shape, dt) for k, (dt, shape) in replay.specs.items()}
        rows["position"][:, 0] = np.repeat(np.arange(t_len), n)  # step t
        rows["position"][:, 1] = np.tile(np.arange(n), t_len)  # agent i
        rows["episode"][:], rows["n_agents"][:], rows["m"][:] = e, n, 1
        replay.add(rows)
    batch, valid = replay.sample_sequences(200, 3, 2, np.random.default_rng(0))  # width 3 + 2 - 1 = 4
    pos = batch["position"].view(200, 4, 2)
    for s in range(200):
        k = int(valid[s].sum())
        assert k >= 1 and valid[s, :k].all()
        t0, i = pos[s, 0].tolist()
        assert pos[s, :k, 1].eq(i).all() and pos[s, :k, 0].tolist() == [t0 + j for j in range(k)]
        t_len = 5 if batch["episode"][4 * s] == 0 else 3
        assert k == min(4, t_len - int(t0))  # the sequence ends with its episode


def test_the_learner_unrolls_the_actors_memory_and_bootstraps_with_it():
    """recurrent_batch's Q-values are the actor's at the same steps, and with the target network equal to the
    online one, each row's bootstrap values are the actor's Q-values at t + m (or of the final observation)."""
    net = _net()
    args = dataclasses.replace(Args(), recurrent=True, sequence_length=4, batch_size=32, n_step=2, double_dqn=True)
    (steps, stats), qs = _episode(net, steps=30)
    rows = episode_rows(steps, stats["success"], args.gamma, args.n_step, episode=7)
    replay = Replay(5000, hidden=net.cfg.hidden_features)
    replay.add(rows)
    n = stats["n_agents"]
    with torch.no_grad():
        final = net.step(*network_inputs(steps["obs"][-1], net.cfg), h=torch.from_numpy(steps["h_in"][-1]).float())
        _, h_last = final
        q_end, _ = net.step(*network_inputs(steps["obs"][-1], net.cfg), h=h_last)  # Q of the last observation
    actor_q = torch.cat([qs, q_end[None]])  # (T + 1, N, 5)
    fast = FastForward(net)
    batch, q, next_q, next_online = recurrent_batch(net, net, fast, InferenceNet(net), InferenceNet(net), replay, args,
                                                    np.random.default_rng(1))
    idx = torch.as_tensor(batch["index"])
    step_of, agent_of = idx // n, idx % n
    assert len(idx) > 8
    assert torch.allclose(q.detach(), actor_q[step_of, agent_of], atol=1e-3)
    boot = step_of + batch["m"]
    assert torch.allclose(next_q, actor_q[boot, agent_of], atol=1e-3)
    assert torch.allclose(next_online, next_q, atol=1e-5)


def test_recurrent_args_refuse_prioritised_replay():
    with pytest.raises(ValueError, match="priority_alpha"):
        Args(recurrent=True, priority_alpha=0.6).validate()
    with pytest.raises(ValueError, match="sequence_length"):
        Args(recurrent=True, sequence_length=0).validate()
