"""Model files: round trip, and clear errors for missing, corrupt, foreign, old and mismatched files."""
from __future__ import annotations

import pytest
import torch

from mapf_policy.config import NetworkConfig
from mapf_policy.model_io import VERSION, load_model, save_model
from mapf_policy.network import QNetwork
from mapf_policy.solver import make_hscl, make_hscl_ablation


@pytest.fixture
def untrained(tmp_path):
    torch.manual_seed(0)
    cfg = NetworkConfig()
    net = QNetwork(cfg)
    path = save_model(tmp_path / "m.pt", net, cfg, {"steps": 0, "note": "untrained"})
    return path, net


def test_round_trip_keeps_weights_config_and_meta(untrained):
    path, net = untrained
    loaded, cfg, meta = load_model(path)
    assert cfg == NetworkConfig() and meta == {"steps": 0, "note": "untrained"}
    for k, v in net.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k])
    assert path.stat().st_size < 5_000_000  # about 4 MB of float32 weights, no optimizer state
    assert not loaded.training


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_model(tmp_path / "nope.pt")


def test_corrupt_file(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"this is not a torch file")
    with pytest.raises(ValueError, match="not a readable model file"):
        load_model(bad)


def test_not_a_model_file(tmp_path):
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(ValueError, match="not a mapf_policy model file"):
        load_model(other)


def test_wrong_format_version(untrained, tmp_path):
    path, _ = untrained
    payload = torch.load(path, weights_only=True)
    payload["version"] = VERSION + 1
    torch.save(payload, tmp_path / "future.pt")
    with pytest.raises(ValueError, match="version"):
        load_model(tmp_path / "future.pt")


def test_architecture_mismatch_names_keys_and_shapes(untrained, tmp_path):
    path, _ = untrained
    payload = torch.load(path, weights_only=True)
    payload["state_dict"]["hidden_fc.weight"] = torch.zeros(10, 832)
    del payload["state_dict"]["attention.f.weight"]
    payload["state_dict"]["extra.weight"] = torch.zeros(1)
    torch.save(payload, tmp_path / "mismatch.pt")
    with pytest.raises(ValueError) as err:
        load_model(tmp_path / "mismatch.pt")
    msg = str(err.value)
    assert "architecture mismatch" in msg and "attention.f.weight" in msg and "extra.weight" in msg
    assert "hidden_fc.weight" in msg and "(10, 832)" in msg and "(300, 832)" in msg


def test_meta_must_be_plain_data(tmp_path):
    with pytest.raises(ValueError, match="plain data"):
        save_model(tmp_path / "m.pt", QNetwork(), NetworkConfig(), {"obj": object()})


def test_solver_factories_load_and_check_the_variant(untrained, tmp_path):
    path, _ = untrained
    solver = make_hscl(model=str(path))
    assert solver.name == "hscl"
    with pytest.raises(ValueError, match="self_attention"):
        make_hscl_ablation("hscl_no_self_attention", model=str(path))
    with pytest.raises(ValueError, match="unknown options"):
        make_hscl(model=str(path), epsilon=3)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        make_hscl(model=str(tmp_path / "absent.pt"))
