"""The priority channel (beyond the paper, issue 20): the other agents ahead in the instance's agent order."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from mapf_policy.config import NetworkConfig
from mapf_policy.export import Q_TOLERANCE, check_export, export_model
from mapf_policy.model_io import save_model
from mapf_policy.network import QNetwork, count_parameters, network_inputs
from mapf_world.env import MapfEnv
from mapf_world.grid import RIGHT, STAY, UP
from mapf_world.observation import ObservationBuilder

R = 4  # centre of a 9x9 field of view


def test_each_agent_sees_only_the_agents_ahead_of_it():
    grid = np.zeros((7, 7), np.uint8)
    builder = ObservationBuilder(grid, np.array([[0, 0], [0, 1], [0, 2], [6, 6]]))
    pos = np.array([[3, 3], [3, 4], [2, 3], [6, 6]])
    out = builder.priorities(pos)
    assert out.shape == (4, 9, 9) and out.dtype == np.float32
    assert not out[0].any()  # agent 0 comes first: nobody is ahead of it
    want = np.zeros((9, 9), np.float32)
    want[R, R - 1] = 1  # agent 1 at (3, 4) sees agent 0 at (3, 3), one to its left
    assert np.array_equal(out[1], want)
    want = np.zeros((9, 9), np.float32)
    want[R + 1, R] = want[R + 1, R + 1] = 1  # agent 2 at (2, 3): agents 0 (3, 3) and 1 (3, 4) below it
    assert np.array_equal(out[2], want)
    want = np.zeros((9, 9), np.float32)
    want[R - 3, R - 3] = want[R - 3, R - 2] = want[R - 4, R - 3] = 1  # agent 3 at (6, 6): all three, up-left
    assert np.array_equal(out[3], want)
    # the agent channel shows every other agent; the priority channel is the part of it that is ahead
    fov = builder.build(pos, [STAY] * 4)["fov"]
    assert np.all(out <= fov[:, 1])


def test_the_env_appends_the_channel_after_the_heading_channel_and_follows_the_moves():
    grid = np.zeros((6, 6), np.uint8)
    starts, goals = np.array([[2, 1], [2, 2]]), np.array([[2, 4], [0, 2]])
    env = MapfEnv(grid, starts, goals, heading=True, priority=True, last_action="executed")
    obs, _ = env.reset()
    assert obs["fov"].shape == (2, 8, 9, 9)
    assert obs["fov"][1, 7, R, R - 1] == 1 and obs["fov"][1, 7].sum() == 1 and not obs["fov"][0, 7].any()
    obs, _, _, _, _ = env.step([STAY, UP])  # agent 1 moves to (1, 2): agent 0 is now one down, one left of it
    assert obs["fov"][1, 7, R + 1, R - 1] == 1 and obs["fov"][1, 7].sum() == 1
    plain = MapfEnv(grid, starts, goals, priority=True)
    assert plain.reset()[0]["fov"].shape == (2, 7, 9, 9)
    assert np.array_equal(plain.reset()[0]["fov"][:, 6], env.reset()[0]["fov"][:, 7])
    assert MapfEnv(grid, starts, goals).reset()[0]["fov"].shape == (2, 6, 9, 9)  # the paper's six by default
    env.step([RIGHT, STAY])  # still plays


def test_a_priority_network_reads_one_more_channel_and_its_export_agrees(tmp_path):
    cfg = NetworkConfig(dueling=True, heading=True, priority=True)
    assert cfg.fov_channels == 8 and NetworkConfig(priority=True).fov_channels == 7
    net, heading_only = QNetwork(cfg), QNetwork(NetworkConfig(dueling=True, heading=True))
    # One more input channel: 64 x 3 x 3 weights of the first conv, and the 1x1 self-attention maps 7x7 -> 8x8 (x3).
    assert count_parameters(net) - count_parameters(heading_only) == 64 * 9 + 3 * (64 - 49)
    env = MapfEnv(np.zeros((8, 8), np.uint8), np.array([[0, 0], [7, 7]]), np.array([[7, 0], [0, 7]]), heading=True,
                  priority=True)
    q = net(*network_inputs(env.reset()[0], cfg))
    assert q.shape == (2, 5) and torch.isfinite(q).all()
    save_model(tmp_path / "p.pt", QNetwork(NetworkConfig(priority=True)), NetworkConfig(priority=True), {})
    result = check_export(tmp_path / "p.pt", export_model(tmp_path / "p.pt"), n=300)
    assert result["max_abs_diff"] <= Q_TOLERANCE and result["greedy_disagreements"] == 0
