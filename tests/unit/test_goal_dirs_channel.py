"""The goal-direction channels (beyond the paper, issue 20): which way each other agent in view has to go."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from mapf_policy.config import NetworkConfig
from mapf_policy.export import Q_TOLERANCE, check_export, export_model
from mapf_policy.model_io import save_model
from mapf_policy.network import QNetwork, count_parameters, network_inputs
from mapf_world.env import MapfEnv
from mapf_world.grid import RIGHT, STAY
from mapf_world.observation import ObservationBuilder

R = 4  # centre of a 9x9 field of view; the four channels are up, down, left, right, as the heuristic channels 2-5


def test_each_agent_sees_which_way_the_others_goals_lie():
    grid = np.zeros((7, 7), np.uint8)
    grid[3, 5] = 1  # an obstacle right of agent 1: its goal (3, 6) is still to the right, round it
    goals = np.array([[0, 3], [3, 6], [6, 0]])
    builder = ObservationBuilder(grid, goals)
    pos = np.array([[3, 3], [3, 4], [0, 0]])
    out = builder.goal_directions(pos)
    assert out.shape == (3, 4, 9, 9) and out.dtype == np.float32
    # agent 0 at (3, 3) sees agent 1 one to its right; agent 1 must go round the obstacle: up or down
    assert out[0, :, R, R + 1].tolist() == [1, 1, 0, 0]
    # agent 1 sees agent 0 one to its left, whose goal (0, 3) is straight up
    assert out[1, :, R, R - 1].tolist() == [1, 0, 0, 0]
    # agent 2 at (0, 0), 3 rows up and 4 columns left of agent 1, is in its view; its goal (6, 0) is straight down
    assert out[1, :, R - 3, R - 4].tolist() == [0, 1, 0, 0]
    # nothing at an agent's own cell, nothing where no agent stands, every mark on an agent of the agent channel
    assert not out[:, :, R, R].any()
    fov = builder.build(pos, [STAY] * 3)["fov"]
    assert np.all(out.max(axis=1) <= fov[:, 1])
    # the marks are exactly the heuristic channels (2-5) the other agent itself reads at its own centre
    assert np.array_equal(out[0, :, R, R + 1], fov[1, 2:, R, R])
    assert np.array_equal(out[1, :, R, R - 1], fov[0, 2:, R, R])


def test_an_agent_on_its_goal_shows_no_direction():
    grid = np.zeros((5, 5), np.uint8)
    builder = ObservationBuilder(grid, np.array([[2, 2], [2, 3]]))
    out = builder.goal_directions(np.array([[2, 2], [2, 4]]))
    assert not out[1].any()  # agent 0 stands on its goal: no move brings it closer
    assert out[0, :, R, R + 2].tolist() == [0, 0, 1, 0]  # agent 1 must go left


def test_the_env_appends_four_channels_last_and_follows_the_moves():
    grid = np.zeros((6, 6), np.uint8)
    starts, goals = np.array([[2, 1], [2, 2]]), np.array([[2, 4], [0, 2]])
    env = MapfEnv(grid, starts, goals, heading=True, priority=True, goal_dirs=True, last_action="executed")
    obs, _ = env.reset()
    assert obs["fov"].shape == (2, 12, 9, 9)
    assert obs["fov"][0, 8:, R, R + 1].tolist() == [1, 0, 0, 0]  # agent 1 at (2, 2) goes up to (0, 2)
    assert obs["fov"][1, 8:, R, R - 1].tolist() == [0, 0, 0, 1]  # agent 0 at (2, 1) goes right to (2, 4)
    obs, _, _, _, _ = env.step([STAY, RIGHT])  # agent 1 to (2, 3): its goal is now up and left
    assert obs["fov"][0, 8:, R, R + 2].tolist() == [1, 0, 1, 0] and obs["fov"][0, 8:].sum() == 2
    plain = MapfEnv(grid, starts, goals, goal_dirs=True)
    assert plain.reset()[0]["fov"].shape == (2, 10, 9, 9)
    assert np.array_equal(plain.reset()[0]["fov"][:, 6:], env.reset()[0]["fov"][:, 8:])


def test_a_goal_dirs_network_reads_four_more_channels_and_its_export_agrees(tmp_path):
    cfg = NetworkConfig(dueling=True, heading=True, priority=True, goal_dirs=True)
    assert cfg.fov_channels == 12 and NetworkConfig(goal_dirs=True).fov_channels == 10
    assert cfg.env_channels() == {"heading": True, "heading_refused": False, "priority": True, "goal_dirs": True,
                                  "revisit_cap": 0}
    revisit = NetworkConfig(goal_dirs=True, still_bins=4, still_count="revisit")
    assert revisit.env_channels()["revisit_cap"] == 3  # the counts the network tells apart: 0, 1, 2, 3 or more
    net, without = QNetwork(cfg), QNetwork(NetworkConfig(dueling=True, heading=True, priority=True))
    # Four more input channels: 4 x 64 x 3 x 3 weights of the first conv, and the 1x1 self-attention maps 8x8 -> 12x12.
    assert count_parameters(net) - count_parameters(without) == 4 * 64 * 9 + 3 * (144 - 64)
    env = MapfEnv(np.zeros((8, 8), np.uint8), np.array([[0, 0], [7, 7]]), np.array([[7, 0], [0, 7]]),
                  **cfg.env_channels())
    q = net(*network_inputs(env.reset()[0], cfg))
    assert q.shape == (2, 5) and torch.isfinite(q).all()
    save_model(tmp_path / "g.pt", QNetwork(NetworkConfig(goal_dirs=True)), NetworkConfig(goal_dirs=True), {})
    result = check_export(tmp_path / "g.pt", export_model(tmp_path / "g.pt"), n=300)  # the robot runtime serves it
    assert result["max_abs_diff"] <= Q_TOLERANCE and result["greedy_disagreements"] == 0
