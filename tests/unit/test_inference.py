"""FastForward and InferenceNet (the fast CPU forwards) compute QNetwork's function and gradients;
Toom-Cook matrices are exact."""
from __future__ import annotations

import platform
from fractions import Fraction

import numpy as np
import pytest
import torch
from torch.nn import functional as F

from mapf_policy.config import ABLATIONS, NetworkConfig
from mapf_policy.inference import (WINOGRAD_MIN_BATCH, WINOGRAD_POINTS, FastForward, InferenceNet, _Layer,
                                   keep_freed_memory)
from mapf_policy.model_io import load_model
from mapf_policy.network import QNetwork
from mapf_policy.policy import Policy
from mapf_policy.solver import default_model_path
from mapf_policy.winograd import toom_cook


def _inputs(b: int, fov_size: int = 9, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    fov = (torch.rand(b, 6, fov_size, fov_size, generator=g) < 0.3).float()
    last = F.one_hot(torch.randint(0, 5, (b,), generator=g), 5).float()
    pos = torch.randint(0, 40, (b, 2), generator=g).float()
    return fov, last, pos


def _spread_weights(net: QNetwork, seed: int) -> QNetwork:
    """Random weights of unit-order activations (default init gives Q-values near 0, a weak test)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            fan_in = p[0].numel() if p.dim() > 1 else 1
            p.copy_(torch.randn(p.shape, generator=g) * (2.0 / fan_in) ** 0.5)
    return net.eval()


def _assert_close(fast: torch.Tensor, ref: torch.Tensor):
    scale = ref.abs().max().item()
    assert scale > 1e-3, "the test needs Q-values away from 0"
    assert (fast - ref).abs().max().item() <= 1e-5 * max(1.0, scale)


@pytest.mark.parametrize("batch", [1, WINOGRAD_MIN_BATCH - 1, WINOGRAD_MIN_BATCH, 64])
def test_fast_forward_equals_the_network_for_every_batch_path(batch):
    net = _spread_weights(QNetwork(), seed=batch)
    inputs = _inputs(batch, seed=batch)
    with torch.inference_mode():
        _assert_close(InferenceNet(net)(*inputs), net(*inputs))


@pytest.mark.parametrize("variant", sorted(ABLATIONS))
def test_fast_forward_equals_the_network_for_every_ablation(variant):
    net = _spread_weights(QNetwork(NetworkConfig(**ABLATIONS[variant])), seed=1)
    for batch in (3, 16):
        inputs = _inputs(batch, seed=batch)
        with torch.inference_mode():
            _assert_close(InferenceNet(net)(*inputs), net(*inputs))


def test_fast_forward_with_a_wider_field_of_view_keeps_the_trunk_spatial():
    # fov 11: the trunk ends at 3x3 (CBAM then pools over space), and sides 9 and 7 use im2col.
    net = _spread_weights(QNetwork(NetworkConfig(fov_size=11)), seed=2)
    inputs = _inputs(16, fov_size=11)
    with torch.inference_mode():
        _assert_close(InferenceNet(net)(*inputs), net(*inputs))


@pytest.mark.skipif(not default_model_path().is_file(), reason="no shipped model")
def test_fast_forward_equals_the_shipped_model_and_picks_the_same_greedy_actions():
    from mapf_policy.export import episode_observations
    net, cfg, _ = load_model(default_model_path())
    # Observations of generated episodes with the channels and still input the shipped network reads.
    inputs = tuple(torch.from_numpy(x) for x in episode_observations(256, seed=3, cfg=cfg) if x is not None)
    with torch.inference_mode():
        fast, ref = InferenceNet(net)(*inputs), net(*inputs)
    assert (fast - ref).abs().max().item() < 1e-5
    top2 = ref.topk(2, dim=1).values
    clear = (top2[:, 0] - top2[:, 1]) > 1e-4  # rows whose best action is not a near tie
    assert clear.sum() > 200
    assert torch.equal(fast.argmax(1)[clear], ref.argmax(1)[clear])


@pytest.mark.parametrize("batch", [WINOGRAD_MIN_BATCH - 1, 32])
def test_fast_forward_gives_the_networks_gradients(batch):
    """The learner trains through FastForward: same loss gradient for every parameter, both layer paths."""
    ref_net = _spread_weights(QNetwork(), seed=7)
    fast_net = _spread_weights(QNetwork(), seed=7)
    inputs = _inputs(batch, seed=8)
    target = torch.randn(batch, 5, generator=torch.Generator().manual_seed(9))
    for net, q_fn in ((ref_net, ref_net), (fast_net, FastForward(fast_net))):
        ((q_fn(*inputs) - target) ** 2).mean().backward()
    for (name, p), q in zip(ref_net.named_parameters(), fast_net.parameters()):
        scale = p.grad.abs().max().item()
        assert scale > 0, name
        assert (q.grad - p.grad).abs().max().item() <= 1e-4 * scale, name


def test_fast_forward_follows_weights_loaded_later():
    """An actor loads new weights into its QNetwork; the InferenceNet around it must not keep the old ones."""
    net = _spread_weights(QNetwork(), seed=4)
    fast = InferenceNet(net)
    inputs = _inputs(16)
    before = fast(*inputs).clone()
    net.load_state_dict(_spread_weights(QNetwork(), seed=5).state_dict())
    with torch.inference_mode():
        after, ref = fast(*inputs), net(*inputs)
    assert (after - before).abs().max().item() > 1e-2
    _assert_close(after, ref)


def test_fast_forward_rejects_bad_shapes_and_non_networks():
    fast = InferenceNet(QNetwork())
    fov, last, pos = _inputs(2)
    with pytest.raises(ValueError, match="fov must have shape"):
        fast(fov[:, :5], last, pos)
    with pytest.raises(ValueError, match="position must have shape"):
        fast(fov, last, pos[:1])
    with pytest.raises(ValueError, match="wraps a QNetwork"):
        InferenceNet(torch.nn.Linear(2, 2))
    with pytest.raises(ValueError, match="winograd_min_batch"):
        FastForward(QNetwork(), winograd_min_batch=0)


def test_policy_uses_the_fast_forward_on_cpu():
    net = _spread_weights(QNetwork(), seed=6)
    policy = Policy(net, num_threads=None)
    assert isinstance(policy.forward, InferenceNet)
    inputs = _inputs(12)
    with torch.inference_mode():
        _assert_close(policy.q_values(*inputs), net(*inputs))


@pytest.mark.parametrize("m", sorted(WINOGRAD_POINTS))
def test_winograd_layer_equals_a_direct_convolution(m):
    torch.manual_seed(m)
    conv = torch.nn.Conv2d(16, 24, 3)
    x = torch.randn(10, m + 2, m + 2, 16)  # channels-last input
    ref = F.relu(conv(x.permute(0, 3, 1, 2))).permute(0, 2, 3, 1)
    with torch.no_grad():
        layer = _Layer(conv, m)
        for winograd in (True, False):
            out = layer(x, winograd)
            assert out.shape == ref.shape
            assert (out - ref).abs().max().item() < 1e-4


@pytest.mark.parametrize("m, points", [(2, (0, 1, -1)), (3, (0, 1, -1, 2)), (4, (0, 1, -1, 2, -2)),
                                       (5, (0, 1, -1, 2, -2, Fraction(1, 2)))])
def test_toom_cook_computes_the_correlation(m, points):
    at, g, bt = toom_cook(m, 3, points)
    rng = np.random.default_rng(m)
    for _ in range(5):
        w, d = rng.normal(size=3), rng.normal(size=m + 2)
        expected = np.array([w @ d[i:i + 3] for i in range(m)])
        np.testing.assert_allclose(at @ ((g @ w) * (bt @ d)), expected, atol=1e-10)


def test_toom_cook_rejects_wrong_or_repeated_points():
    with pytest.raises(ValueError, match="distinct finite points"):
        toom_cook(3, 3, (0, 1, -1))
    with pytest.raises(ValueError, match="distinct finite points"):
        toom_cook(3, 3, (0, 1, 1, 2))


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="the malloc settings exist only in glibc")
def test_malloc_settings_take_on_glibc():
    assert keep_freed_memory() is True
