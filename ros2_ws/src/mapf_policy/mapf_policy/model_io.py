"""Model files: weights (float32 state_dict) + the NetworkConfig that built them + metadata.

A model file is `torch.save` of a plain dict
    {"format": "mapf_policy.qnetwork", "version": 1, "network_config": {...}, "state_dict": {...}, "meta": {...}}
loaded with `torch.load(weights_only=True)`, so loading never unpickles arbitrary objects. `meta` must
hold only plain data (str, int, float, bool, None, lists and dicts of them). No optimizer state: shipped
models stay small (about 4 MB).
"""
from __future__ import annotations

import os
from pathlib import Path

import torch

from mapf_policy.config import NetworkConfig
from mapf_policy.network import QNetwork

FORMAT = "mapf_policy.qnetwork"
VERSION = 1


def _check_plain(value, where: str) -> None:
    if value is None or isinstance(value, (str, bool, int, float)):
        return
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _check_plain(v, f"{where}[{i}]")
        return
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str):
                raise ValueError(f"meta keys must be strings, got {k!r} at {where}")
            _check_plain(v, f"{where}.{k}")
        return
    raise ValueError(f"meta must hold plain data only; {where} is a {type(value).__name__}")


def model_payload(net: QNetwork, cfg: NetworkConfig, meta: dict | None = None) -> dict:
    """The plain dict that `save_model` writes (also embedded in training checkpoints)."""
    meta = dict(meta or {})
    _check_plain(meta, "meta")
    state = {k: v.detach().to("cpu", torch.float32).clone() for k, v in net.state_dict().items()}
    return {"format": FORMAT, "version": VERSION, "network_config": cfg.asdict(), "state_dict": state, "meta": meta}


def save_model(path, net: QNetwork, cfg: NetworkConfig, meta: dict | None = None) -> Path:
    """Write the model atomically (temp file + rename), so a crash never leaves half a model file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = model_payload(net, cfg, meta)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)
    return path


def network_from_payload(payload, source: str) -> tuple[QNetwork, NetworkConfig, dict]:
    """Check a loaded payload and build the network; ValueError naming what is wrong with `source`."""
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"{source} is not a mapf_policy model file (no '{FORMAT}' format tag)")
    if payload.get("version") != VERSION:
        raise ValueError(f"{source} has model format version {payload.get('version')!r}; this code reads version {VERSION}")
    for key in ("network_config", "state_dict", "meta"):
        if key not in payload:
            raise ValueError(f"{source} lacks the '{key}' entry")
    try:
        cfg = NetworkConfig.from_dict(payload["network_config"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{source}: bad network_config: {exc}") from exc
    net = QNetwork(cfg)
    check_state_dict(net, payload["state_dict"], source)
    net.load_state_dict(payload["state_dict"])
    net.eval()
    return net, cfg, payload["meta"]


def check_state_dict(net: QNetwork, state: dict, source: str) -> None:
    """ValueError listing missing keys, unexpected keys and shape mismatches against `net`."""
    if not isinstance(state, dict):
        raise ValueError(f"{source}: state_dict is a {type(state).__name__}, not a dict")
    expected = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    got = {k: tuple(v.shape) if isinstance(v, torch.Tensor) else None for k, v in state.items()}
    problems = []
    missing = sorted(set(expected) - set(got))
    unexpected = sorted(set(got) - set(expected))
    if missing:
        problems.append(f"missing keys {missing}")
    if unexpected:
        problems.append(f"unexpected keys {unexpected}")
    for k in sorted(set(expected) & set(got)):
        if got[k] != expected[k]:
            problems.append(f"{k}: file has shape {got[k]}, network expects {expected[k]}")
    if problems:
        raise ValueError(f"{source}: architecture mismatch: " + "; ".join(problems))


def load_model(path) -> tuple[QNetwork, NetworkConfig, dict]:
    """Load a model file -> (net in eval mode, its NetworkConfig, meta); ValueError/FileNotFoundError on problems."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model file {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt or foreign files
        raise ValueError(f"{path} is not a readable model file (corrupt or not a torch file): {exc}") from exc
    return network_from_payload(payload, str(path))
