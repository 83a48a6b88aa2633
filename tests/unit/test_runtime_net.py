"""The robot's torch-free runtime: an exported file (.npz) computes the torch network's Q-values and actions,
and refuses to load, or to pass as the export of a model file, when it does not belong to it."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from mapf_policy.action_selection import ActionRule
from mapf_policy.config import ABLATIONS, NetworkConfig
from mapf_policy.export import (Q_TOLERANCE, check_belongs, check_export, compare_q, default_export_path,
                                episode_observations, export_model)
from mapf_policy.model_io import save_model
from mapf_policy.network import QNetwork
from mapf_policy.policy import Policy
from mapf_policy.runtime_net import HEADER_KEY, RuntimeNet, read_export
from mapf_policy.runtime_policy import RuntimePolicy
from mapf_policy.solver import default_model_path


def _spread_model(path, cfg: NetworkConfig, seed: int):
    """A model file with random weights of unit-order activations (default init gives Q-values near 0)."""
    net = QNetwork(cfg)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            fan_in = p[0].numel() if p.dim() > 1 else 1
            p.copy_(torch.randn(p.shape, generator=g) * (2.0 / fan_in) ** 0.5)
    return save_model(path, net, cfg, {"note": f"random, seed {seed}"})


@pytest.fixture(scope="module")
def observations():
    return episode_observations(600, seed=1)


@pytest.mark.skipif(not default_model_path().is_file(), reason="no shipped model")
def test_the_shipped_export_belongs_to_the_shipped_model_and_agrees_on_3000_episode_observations():
    model = default_model_path()
    export = default_export_path(model)
    assert export.is_file(), f"{export} is missing: run scripts/export_model {model}"
    # Raises, naming the fix, when models/hscl.npz was exported from another model file or disagrees with it.
    result = check_export(model, export, n=3000)
    assert result["observations"] == 3000
    assert result["max_abs_diff"] <= Q_TOLERANCE and result["greedy_disagreements"] == 0


# The second design (issue 20): channels beyond the paper's six and the one-hot still input counting revisits.
SECOND = {"dueling": True, "heading": True, "priority": True, "goal_dirs": True, "still_bins": 4, "still_count": "revisit"}


@pytest.mark.parametrize("variant", ["paper", "dueling", "fov11", "second"] + sorted(ABLATIONS))
def test_numpy_forward_equals_torch_for_every_architecture(tmp_path, observations, variant):
    overrides = ({"paper": {}, "dueling": {"dueling": True}, "fov11": {"fov_size": 11}, "second": SECOND}
                 | ABLATIONS)[variant]
    cfg = NetworkConfig(**overrides)
    model = _spread_model(tmp_path / "m.pt", cfg, seed=len(variant))
    export = export_model(model, tmp_path / "m.npz")
    net = RuntimeNet.load(export)
    assert net.cfg == cfg and ("value_fc" in net.fc) == cfg.dueling
    if cfg.fov_size == 9:
        result = check_export(model, export, n=600)
    else:  # the generated episodes observe 9x9; a wider view gets random 0/1 observations
        rng = np.random.default_rng(0)
        fov = (rng.random((200, 6, 11, 11)) < 0.3).astype(np.float32)
        last = np.eye(5, dtype=np.float32)[rng.integers(0, 5, 200)]
        pos = rng.integers(0, 40, (200, 2)).astype(np.float32)
        from mapf_policy.model_io import load_model
        ref = load_model(model)[0](*map(torch.from_numpy, (fov, last, pos))).detach().numpy()
        got = net(fov, last, pos)
        result = {"max_abs_diff": float(np.abs(got - ref).max()), "greedy_disagreements": int((got.argmax(1) != ref.argmax(1)).sum())}
    assert result["max_abs_diff"] <= Q_TOLERANCE and result["greedy_disagreements"] == 0, result


def test_q_values_are_not_trivially_small(tmp_path):
    # The comparison above means something only if the Q-values spread over more than the tolerance.
    model = _spread_model(tmp_path / "m.pt", NetworkConfig(), seed=3)
    q = RuntimeNet.load(export_model(model, tmp_path / "m.npz"))(*episode_observations(200))
    assert q.std() > 1000 * Q_TOLERANCE


def test_runtime_policy_acts_as_the_torch_policy_under_the_sampled_rule(tmp_path, observations):
    model = _spread_model(tmp_path / "m.pt", NetworkConfig(dueling=True), seed=5)
    export = export_model(model, tmp_path / "m.npz")
    rule = ActionRule(action_temperature=0.5)  # wide sampling: the draws matter for most rows
    torch_policy, runtime = Policy(str(model), rule=rule, seed=7), RuntimePolicy(export, rule=rule, seed=7)
    fov, last, pos = observations[:3]
    for k in range(0, 600, 100):  # consecutive calls: the generator and the previous cells carry over
        batch = (fov[k:k + 100], last[k:k + 100], pos[k:k + 100])
        np.testing.assert_array_equal(runtime.act(*batch), torch_policy.act(*batch))
    single = runtime.act(fov[0], last[0], pos[0])  # one agent without the batch dimension
    assert single.shape == (1,)


def test_an_export_of_another_model_does_not_pass_as_this_model_s(tmp_path):
    a = _spread_model(tmp_path / "a.pt", NetworkConfig(), seed=1)
    b = _spread_model(tmp_path / "b.pt", NetworkConfig(), seed=2)
    export_a = export_model(a, tmp_path / "a.npz")
    with pytest.raises(ValueError, match=r"does not belong to .*b\.pt.*scripts/export_model"):
        check_belongs(b, export_a)
    # The same file name does not help: the tie is the model file's SHA-256.
    b.replace(a)
    with pytest.raises(ValueError, match="does not belong"):
        check_export(a, export_a)


def test_a_damaged_or_edited_export_is_refused(tmp_path):
    model = _spread_model(tmp_path / "m.pt", NetworkConfig(), seed=1)
    export = export_model(model, tmp_path / "m.npz")
    with np.load(export) as data:
        arrays = {k: data[k] for k in data.files}
    edited = dict(arrays)
    edited["q_fc.bias"] = arrays["q_fc.bias"] + np.float32(0.5)
    np.savez(tmp_path / "edited.npz", **edited)
    with pytest.raises(ValueError, match="do not match the fingerprint"):
        RuntimeNet.load(tmp_path / "edited.npz")
    missing = {k: v for k, v in arrays.items() if k != "value_fc.bias" and k != "q_fc.weight"}
    np.savez(tmp_path / "missing.npz", **missing)
    with pytest.raises(ValueError, match=r"missing tensors \['q_fc.weight'\]"):
        RuntimeNet.load(tmp_path / "missing.npz")
    header = json.loads(str(arrays[HEADER_KEY]))
    header["network_config"]["dueling"] = True
    np.savez(tmp_path / "config.npz", **(arrays | {HEADER_KEY: np.array(json.dumps(header))}))
    with pytest.raises(ValueError, match=r"missing tensors \['value_fc.bias', 'value_fc.weight'\]"):
        RuntimeNet.load(tmp_path / "config.npz")
    with pytest.raises(ValueError, match="is not an exported model"):
        RuntimeNet.load(model)  # the torch file itself (a zip, as .npz files are)
    (tmp_path / "text.npz").write_text("not a model\n")
    with pytest.raises(ValueError, match="not a readable exported model"):
        RuntimeNet.load(tmp_path / "text.npz")
    with pytest.raises(FileNotFoundError, match="scripts/export_model"):
        read_export(tmp_path / "absent.npz")


def test_compare_q_reports_a_disagreement(tmp_path):
    model = _spread_model(tmp_path / "m.pt", NetworkConfig(), seed=1)
    other = _spread_model(tmp_path / "o.pt", NetworkConfig(), seed=2)
    export_other = export_model(other, tmp_path / "o.npz")
    result = compare_q(model, export_other, n=200)
    assert result["max_abs_diff"] > 1e-2 and result["greedy_disagreements"] > 0


def test_the_runtime_imports_neither_torch_nor_training_code():
    code = ("import sys; import mapf_policy.runtime_policy; "
            "bad = sorted(m for m in sys.modules if m == 'torch' or m.startswith(('torch.', 'mapf_policy.train'))); "
            "print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_a_recurrent_model_is_refused_by_the_robot_runtime_with_a_reason(tmp_path):
    cfg = NetworkConfig(dueling=True, recurrent=True)
    net = QNetwork(cfg)
    with pytest.raises(ValueError, match="feed-forward"):
        RuntimeNet(cfg, {k: v.numpy() for k, v in net.state_dict().items()})
