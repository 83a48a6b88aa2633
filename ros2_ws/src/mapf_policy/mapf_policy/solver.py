"""Evaluation-harness adapters (mapf_world.solvers registry): `hscl` and its Table III ablations.

Decentralised: every agent's action comes from its own observation row only. All agents go through
the network in one batch for speed; the network has no cross-sample operation (no batch norm), so a
row's Q-values do not depend on the other rows. The action rule (action_selection.py) works per row: its
own Gumbel noise, its own previous cell. The policy resets at each case, the generator restarting from
`seed`, so a case's result does not depend on which cases ran before it.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mapf_policy.action_selection import RULE_FIELDS, make_rule
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
    """Solver protocol: reset(env) plans nothing and resets the policy (generator, memory); act(obs) -> (N,) actions."""

    def __init__(self, name: str, policy: Policy, seed: int, model_path: Path):
        self.name = name
        self.policy = policy
        self.seed = seed
        # The observation's last action the model was trained with (MapfEnv's last_action; models before the
        # second design: "requested"); the harness builds its MapfEnv with it.
        self.last_action = policy.meta.get("last_action", "requested")
        # MapfEnv keyword arguments for the observation channels (and revisit count) the network reads; the
        # harness builds its MapfEnv with them. The paper's six channels: all off.
        self.env_channels = policy.cfg.env_channels()
        # What decides the results, for the evaluation report (options left at their defaults included).
        self.settings = {"model": str(model_path), **policy.rule.asdict(), "seed": seed, "last_action": self.last_action,
                         **({"per_agent_seeds": True} if policy.chooser.per_agent_seeds else {})}

    def reset(self, env) -> None:
        fov = env.fov_size
        if fov != self.policy.cfg.fov_size:
            raise ValueError(f"{self.name}: the environment's fov_size is {fov}, the model expects {self.policy.cfg.fov_size}")
        self.policy.reset(self.seed)

    def act(self, obs: dict) -> np.ndarray:
        return self.policy.act_obs(obs)


# action_rule: a named rule ("default" or "paper"), whose fields the other rule options then replace.
OPTIONS = ("num_threads", "seed", "action_rule", "per_agent_seeds") + RULE_FIELDS


def _check_options(name: str, options: dict) -> None:
    unknown = sorted(set(options) - set(OPTIONS))
    if unknown:
        raise ValueError(f"solver {name}: unknown options {unknown} (known: model, {', '.join(OPTIONS)})")


def _load(name: str, model, expected: dict, options: dict) -> HsclSolver:
    _check_options(name, options)
    seed = options.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"solver {name}: seed must be an integer >= 0, got {seed!r}")
    path = Path(model) if model is not None else default_model_path(name)
    if not path.is_file():
        raise FileNotFoundError(
            f"solver {name}: model file {path} does not exist (train one with scripts/train, or pass model=PATH)"
        )
    try:
        rule = make_rule(options.get("action_rule", "default"), **{k: options[k] for k in RULE_FIELDS if k in options})
    except ValueError as exc:
        raise ValueError(f"solver {name}: {exc}") from exc
    policy = Policy(path, num_threads=int(options.get("num_threads", 1)), rule=rule, seed=int(seed),
                    per_agent_seeds=bool(options.get("per_agent_seeds", False)))
    wrong = {k: getattr(policy.cfg, k) for k, v in expected.items() if getattr(policy.cfg, k) != v}
    if wrong:
        raise ValueError(f"solver {name}: model {path} has {wrong}, but this variant needs {expected}")
    return HsclSolver(name, policy, int(seed), path)


def make_hscl(model=None, **options) -> HsclSolver:
    """The paper's policy; `model` defaults to <repo>/models/hscl.pt.

    Options: action_rule ("default", or "paper": greedy argmax and nothing else), and any ActionRule field
    to replace (action_temperature, backtrack_penalty, mask_obstacle_moves, settled_greedy, goal_stay_bonus);
    seed (of the per-case sampling generator, default 0); per_agent_seeds (agent i samples from its own generator
    seeded with seed + i, as robot i of a fleet does with policy_node seed -1); num_threads (torch, default 1).
    """
    full = {k: getattr(NetworkConfig(), k) for k in ("self_attention", "channel_attention", "spatial_attention")}
    return _load("hscl", model, full, options)


def make_hscl_ablation(variant: str, model=None, **options) -> HsclSolver:
    """A Table III variant (`hscl_no_self_attention`, ...); `model` defaults to <repo>/models/<variant>.pt."""
    if variant not in ABLATIONS:
        raise ValueError(f"unknown ablation {variant!r}; known: {sorted(ABLATIONS)}")
    return _load(variant, model, ABLATIONS[variant], options)
