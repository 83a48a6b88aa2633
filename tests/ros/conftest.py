"""Fixtures of the headless ROS 2 fleet tests (helpers live in fleet_helpers.py).

Every test gets its own ROS_DOMAIN_ID, claimed with a lock file so concurrent sessions never share one.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from fleet_helpers import SMALL_MAP, SMALL_SCEN, TRAINED_MODEL, claim_domain_id


@pytest.fixture
def domain_id():
    domain, lock = claim_domain_id()
    yield domain
    lock.close()


@pytest.fixture(scope="module")
def module_domain_id():
    domain, lock = claim_domain_id()
    yield domain
    lock.close()


@pytest.fixture(scope="session")
def any_model(tmp_path_factory) -> Path:
    """A model file of the right architecture: the shipped one if present, else an untrained one.

    The untrained one is the first seeded initialisation under which, on the small test map, every
    robot makes at least one successful move within 6 steps (offline, in MapfEnv), so the fleet tests
    see real motion rather than a policy that only ever stays.
    """
    if TRAINED_MODEL.is_file():
        return TRAINED_MODEL
    import numpy as np
    import torch
    from mapf_policy.config import NetworkConfig
    from mapf_policy.model_io import save_model
    from mapf_policy.network import QNetwork
    from mapf_policy.policy import Policy
    from mapf_world.env import MapfEnv
    from mapf_world.fleet_core import load_fleet_instance

    inst = load_fleet_instance("map", map_file=str(SMALL_MAP), scen_file=str(SMALL_SCEN), n_robots=3)
    cfg = NetworkConfig()
    for seed in range(200):
        torch.manual_seed(seed)
        net = QNetwork(cfg)
        policy = Policy(net, num_threads=None)
        env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=6)
        obs, _ = env.reset()
        moved = np.zeros(3, dtype=bool)
        for _ in range(6):
            before = env.positions
            obs, _, terminated, truncated, _ = env.step(policy.act_obs(obs))
            moved |= np.any(env.positions != before, axis=1)
            if terminated or truncated:
                break
        if moved.all():
            return save_model(tmp_path_factory.mktemp("model") / f"untrained_seed{seed}.pt", net, cfg,
                              {"note": f"untrained, torch seed {seed}: moves every robot on the small map"})
    raise RuntimeError("no seed in 0..199 gives an untrained model that moves every robot")
