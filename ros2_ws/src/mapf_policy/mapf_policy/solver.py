"""Evaluation-harness adapters (mapf_world.solvers registry): `hscl` and its Table III ablations.

Decentralised: every agent's action comes from its own observation row only. All agents go through
the network in one batch for speed; the network has no cross-sample operation (no batch norm), so a
row's Q-values do not depend on the other rows.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mapf_policy.config import ABLATIONS, NetworkConfig
from mapf_policy.policy import Policy


def repo_root() -> Path:
    """$MAPF_ROOT (set by scripts/env), else the checkout that holds this source file."""
    env = os.environ.get("MAPF_ROOT")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[4]  # <root>/ros2_ws/src/mapf_policy/mapf_policy/solver.py


def default_model_path(variant: str = "hscl") -> Path:
    return repo_root() / "models" / f"{variant}.pt"


class HsclSolver:
    """Solver protocol: reset(env) does nothing to plan; act(obs) -> (N,) greedy actions."""

    def __init__(self, name: str, policy: Policy):
        self.name = name
        self.policy = policy

    def reset(self, env) -> None:
        fov = env.fov_size
        if fov != self.policy.cfg.fov_size:
            raise ValueError(f"{self.name}: the environment's fov_size is {fov}, the model expects {self.policy.cfg.fov_size}")

    def act(self, obs: dict) -> np.ndarray:
        return self.policy.act_obs(obs)


def _check_options(name: str, options: dict) -> None:
    unknown = sorted(set(options) - {"num_threads"})
    if unknown:
        raise ValueError(f"solver {name}: unknown options {unknown} (known: model, num_threads)")


def _load(name: str, model, expected: dict, options: dict) -> HsclSolver:
    _check_options(name, options)
    path = Path(model) if model is not None else default_model_path(name)
    if not path.is_file():
        raise FileNotFoundError(
            f"solver {name}: model file {path} does not exist (train one with scripts/train, or pass model=PATH)"
        )
    policy = Policy(path, num_threads=int(options.get("num_threads", 1)))
    wrong = {k: getattr(policy.cfg, k) for k, v in expected.items() if getattr(policy.cfg, k) != v}
    if wrong:
        raise ValueError(f"solver {name}: model {path} has {wrong}, but this variant needs {expected}")
    return HsclSolver(name, policy)


def make_hscl(model=None, **options) -> HsclSolver:
    """The paper's policy; `model` defaults to <repo>/models/hscl.pt."""
    full = {k: getattr(NetworkConfig(), k) for k in ("self_attention", "channel_attention", "spatial_attention")}
    return _load("hscl", model, full, options)


def make_hscl_ablation(variant: str, model=None, **options) -> HsclSolver:
    """A Table III variant (`hscl_no_self_attention`, ...); `model` defaults to <repo>/models/<variant>.pt."""
    if variant not in ABLATIONS:
        raise ValueError(f"unknown ablation {variant!r}; known: {sorted(ABLATIONS)}")
    return _load(variant, model, ABLATIONS[variant], options)
