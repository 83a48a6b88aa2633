"""The grid's eight symmetries (training augmentation): a turned observation is the observation of the turned
instance, and the rules give the turned step."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from mapf_policy.config import NetworkConfig
from mapf_policy.train.dqn_hscl import Args
from mapf_policy.train.symmetry import (SYMMETRIES, Augmenter, action_map, direction_blocks, transform_cells,
                                        transform_plane)
from mapf_world.env import MapfEnv
from mapf_world.grid import DELTAS
from mapf_world.instances import generate_instance

CFG = NetworkConfig(heading=True, priority=True, goal_dirs=True)


def _batch(obs: dict, actions, shape) -> dict:
    n = len(actions)
    return {"fov": torch.from_numpy(obs["fov"].astype(np.float32)), "last_action": torch.from_numpy(obs["last_action"]),
            "position": torch.from_numpy(obs["position"].astype(np.float32)),
            "next_fov": torch.from_numpy(obs["fov"].astype(np.float32)),
            "next_last_action": torch.from_numpy(obs["last_action"]),
            "next_position": torch.from_numpy(obs["position"].astype(np.float32)),
            "map_shape": torch.tensor([shape] * n), "action": torch.as_tensor(actions, dtype=torch.long),
            "expert": torch.as_tensor(actions, dtype=torch.long), "still": torch.zeros(n, dtype=torch.long)}


def test_the_eight_symmetries_are_distinct_and_their_action_maps_turn_the_moves():
    assert len(set(SYMMETRIES)) == 8 and SYMMETRIES[0] == (False, False, False)
    cells = np.arange(20).reshape(4, 5)
    pictures = {transform_plane(cells, g).tobytes() + bytes(transform_plane(cells, g).shape) for g in SYMMETRIES}
    assert len(pictures) == 8
    for g in SYMMETRIES:
        perm = action_map(g)
        assert sorted(perm) == [0, 1, 2, 3, 4] and perm[0] == 0
        # the cell one move away, turned, is one turned move away from the turned cell
        centre, shape = np.array([2, 2]), (5, 5)
        for a in range(5):
            moved, _ = transform_cells(centre + DELTAS[a], shape, g)
            base, _ = transform_cells(centre, shape, g)
            assert (moved - base).tolist() == DELTAS[perm[a]].tolist()


@pytest.mark.parametrize("g_index", range(8))
def test_a_turned_observation_is_the_observation_of_the_turned_instance(g_index):
    g = SYMMETRIES[g_index]
    inst = generate_instance(np.random.default_rng(3), size=11, density=0.3, n_agents=6, height=9)  # not square
    grid = np.asarray(inst.grid)
    turned_grid = np.ascontiguousarray(transform_plane(grid, g))
    t_starts, t_shape = transform_cells(inst.starts, grid.shape, g)
    t_goals, _ = transform_cells(inst.goals, grid.shape, g)
    assert t_shape == turned_grid.shape
    kw = CFG.env_channels()
    env = MapfEnv(grid, inst.starts, inst.goals, last_action="executed", **kw)
    turned = MapfEnv(turned_grid, t_starts, t_goals, last_action="executed", **kw)
    obs, _ = env.reset()
    t_obs, _ = turned.reset()
    aug = Augmenter(CFG.fov_size, CFG.fov_channels, direction_blocks(CFG))
    g_rows = torch.full((inst.starts.shape[0],), g_index)
    rng = np.random.default_rng(g_index)
    perm = action_map(g)
    for _ in range(12):
        actions = rng.integers(0, 5, len(inst.starts))
        got = aug(_batch(obs, actions, grid.shape), g_rows)
        assert torch.equal(got["fov"], torch.from_numpy(t_obs["fov"].astype(np.float32)))
        assert torch.equal(got["last_action"], torch.from_numpy(t_obs["last_action"]))
        assert torch.equal(got["position"], torch.from_numpy(t_obs["position"].astype(np.float32)))
        assert got["action"].tolist() == perm[actions].tolist()
        obs, reward, *_ = env.step(actions)
        t_obs, t_reward, *_ = turned.step(perm[actions])
        # the rules do not look at directions: the turned joint action gives the turned step and the same rewards
        np.testing.assert_array_equal(transform_cells(env.positions, grid.shape, g)[0], turned.positions)
        np.testing.assert_array_equal(reward, t_reward)
        np.testing.assert_array_equal(obs["revisits"], t_obs["revisits"])


def test_the_identity_leaves_a_batch_alone_and_an_unlabelled_row_stays_unlabelled():
    inst = generate_instance(np.random.default_rng(0), size=10, density=0.3, n_agents=3)
    obs, _ = MapfEnv(inst.grid, inst.starts, inst.goals, **CFG.env_channels()).reset()
    batch = _batch(obs, [1, 3, 4], (10, 10))
    batch["expert"] = torch.tensor([-1, 2, -1])
    aug = Augmenter(CFG.fov_size, CFG.fov_channels, direction_blocks(CFG))
    same = aug(batch, torch.zeros(3, dtype=torch.long))
    for key in batch:
        assert torch.equal(same[key], batch[key]), key
    turned = aug(batch, torch.full((3,), SYMMETRIES.index((True, False, False))))  # transpose: down -> right
    assert turned["expert"].tolist() == [-1, 4, -1]


def test_bad_input_is_refused_with_a_reason():
    aug = Augmenter(9, 12, direction_blocks(CFG))
    inst = generate_instance(np.random.default_rng(0), size=10, density=0.3, n_agents=2)
    obs, _ = MapfEnv(inst.grid, inst.starts, inst.goals, **CFG.env_channels()).reset()
    with pytest.raises(ValueError, match="map_shape 0"):
        aug(_batch(obs, [0, 0], (0, 0)), torch.tensor([1, 2]))
    with pytest.raises(ValueError, match="augmenter was built for"):
        Augmenter(9, 6, (2,))(_batch(obs, [0, 0], (10, 10)), torch.tensor([1, 2]))
    with pytest.raises(ValueError, match="does not fit"):
        Augmenter(9, 6, (4,))
    with pytest.raises(ValueError, match="augment turns single rows"):
        Args(augment=True, recurrent=True).validate()
