"""QNetwork: the paper's parameter count, ablation switches, shapes, shape errors, decentralisation."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from mapf_policy.config import ABLATIONS, NetworkConfig
from mapf_policy.network import QNetwork, SelfAttention, count_parameters
from mapf_policy.policy import Policy


def _inputs(b: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    fov = (torch.rand(b, 6, 9, 9, generator=g) > 0.5).float()
    last = torch.nn.functional.one_hot(torch.randint(0, 5, (b,), generator=g), 5).float()
    pos = torch.randint(0, 40, (b, 2), generator=g).float()
    return fov, last, pos


def test_parameter_count_matches_the_paper():
    assert count_parameters(QNetwork(NetworkConfig())) == 1_004_443


@pytest.mark.parametrize(
    "variant, removed",
    [("hscl_no_self_attention", 108), ("hscl_no_channel_attention", 8192), ("hscl_no_spatial_attention", 98)],
)
def test_ablation_switches_remove_their_module(variant, removed):
    net = QNetwork(NetworkConfig(**ABLATIONS[variant]))
    assert count_parameters(net) == 1_004_443 - removed
    q = net(*_inputs(3))
    assert q.shape == (3, 5)


def test_forward_shape_and_finite():
    torch.manual_seed(0)
    q = QNetwork()(*_inputs(7))
    assert q.shape == (7, 5) and torch.isfinite(q).all()


def test_self_attention_matches_the_equations():
    torch.manual_seed(0)
    att = SelfAttention(6, eta=1.0)
    x = torch.randn(2, 6, 3, 3)
    y = att(x)
    # Direct loop over eqs. (1)-(4) for batch element 0.
    xs = x[0].reshape(6, 9).T  # (N, C): x_i
    f, g, h = (xs @ m.weight[:, :, 0].T for m in (att.f, att.g, att.h))
    s = f @ g.T  # s[i, j] = f(x_i) . g(x_j)
    expected = torch.empty(9, 6)
    for j in range(9):
        beta = torch.softmax(s[:, j], dim=0)  # beta_{j, i} over i
        expected[j] = xs[j] + (beta[:, None] * h).sum(0)
    assert torch.allclose(y[0].reshape(6, 9).T, expected, atol=1e-5)


@pytest.mark.parametrize(
    "fov_shape, last_shape, pos_shape, word",
    [
        ((2, 6, 7, 7), (2, 5), (2, 2), "fov"),
        ((2, 5, 9, 9), (2, 5), (2, 2), "fov"),
        ((2, 6, 9, 9), (2, 4), (2, 2), "last_action"),
        ((2, 6, 9, 9), (3, 5), (2, 2), "last_action"),
        ((2, 6, 9, 9), (2, 5), (2, 3), "position"),
    ],
)
def test_wrong_shapes_raise_naming_the_input(fov_shape, last_shape, pos_shape, word):
    with pytest.raises(ValueError, match=word):
        QNetwork()(torch.zeros(fov_shape), torch.zeros(last_shape), torch.zeros(pos_shape))


def test_rows_are_independent_so_batching_keeps_agents_decentralised():
    torch.manual_seed(1)
    net = QNetwork().eval()
    fov, last, pos = _inputs(5, seed=3)
    with torch.no_grad():
        batched = net(fov, last, pos)
        alone = torch.cat([net(fov[i : i + 1], last[i : i + 1], pos[i : i + 1]) for i in range(5)])
        fov2 = fov.clone()
        fov2[1:] = 1 - fov2[1:]  # change every other agent's observation
        changed = net(fov2, last, pos)
    assert torch.allclose(batched, alone, atol=1e-5)
    assert torch.allclose(batched[0], changed[0], atol=1e-6)


def test_position_is_normalised_by_the_configured_scale():
    torch.manual_seed(2)
    a = QNetwork(NetworkConfig(position_scale=40.0)).eval()
    b = QNetwork(NetworkConfig(position_scale=20.0)).eval()
    b.load_state_dict(a.state_dict())
    fov, last, pos = _inputs(4)
    with torch.no_grad():
        assert torch.allclose(a(fov, last, pos), b(fov, last, pos / 2), atol=1e-6)


def test_policy_acts_on_batches_and_single_agents():
    torch.manual_seed(0)
    policy = Policy(QNetwork())
    fov, last, pos = (t.numpy() for t in _inputs(6))
    acts = policy.act(fov, last, pos)
    assert acts.shape == (6,) and acts.dtype == np.int64 and ((acts >= 0) & (acts < 5)).all()
    one = policy.act(fov[2], last[2], pos[2])
    assert one.shape == (1,) and one[0] == acts[2]
    with pytest.raises(ValueError, match="fov"):
        policy.act(fov[:, :, :5], last, pos)
    with pytest.raises(ValueError, match="lacks"):
        policy.act_obs({"fov": fov})


def test_bad_network_configs_raise():
    with pytest.raises(ValueError, match="fov_size"):
        NetworkConfig(fov_size=7).validate()
    with pytest.raises(ValueError, match="cbam_reduction"):
        NetworkConfig(cbam_reduction=3).validate()
    with pytest.raises(ValueError, match="unknown fields"):
        NetworkConfig.from_dict({"fov_size": 9, "widht": 3})
