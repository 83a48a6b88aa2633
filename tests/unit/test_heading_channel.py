"""The heading channel (beyond the paper, issue 20): the cells the other agents face, as a seventh fov channel."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from mapf_policy.config import NetworkConfig
from mapf_policy.export import Q_TOLERANCE, check_export, export_model
from mapf_policy.model_io import save_model
from mapf_policy.network import QNetwork, count_parameters, network_inputs
from mapf_world.env import MapfEnv
from mapf_world.grid import DOWN, LEFT, RIGHT, STAY, UP
from mapf_world.observation import ObservationBuilder

R = 4  # centre of a 9x9 field of view


def test_a_parked_agent_sees_the_neighbour_that_pushes_into_it():
    grid = np.zeros((6, 6), np.uint8)
    env = MapfEnv(grid, np.array([[2, 1], [2, 2]]), np.array([[2, 4], [2, 2]]), heading=True, last_action="executed")
    obs, _ = env.reset()
    assert obs["fov"].shape == (2, 7, 9, 9) and not obs["fov"][:, 6].any()  # nobody has asked for a move yet
    obs, _, _, _, info = env.step([RIGHT, STAY])  # agent 0 pushes into agent 1, which stands on its goal
    assert info["failed"].tolist() == [True, False]
    facing = obs["fov"][:, 6]
    assert facing[1, R, R] == 1 and facing[1].sum() == 1  # agent 1: its own cell is wanted
    assert facing[0].sum() == 0  # agent 0 does not see its own heading; agent 1 stays and faces nothing
    assert obs["last_action"][0].argmax() == STAY  # the executed last action alone would not tell it


def test_the_refused_heading_marks_a_push_and_not_a_neighbour_that_just_arrived():
    grid = np.zeros((6, 6), np.uint8)
    # Agent 0 steps from (2, 0) to (2, 1), beside agent 1 parked on its goal (2, 2): its heading faces (2, 2) too.
    plain = MapfEnv(grid, np.array([[2, 0], [2, 2]]), np.array([[2, 4], [2, 2]]), heading=True, last_action="executed")
    refused = MapfEnv(grid, np.array([[2, 0], [2, 2]]), np.array([[2, 4], [2, 2]]), heading=True, heading_refused=True,
                      last_action="executed")
    for env in (plain, refused):
        env.reset()
    arrived = [env.step([RIGHT, STAY])[0]["fov"][1, 6] for env in (plain, refused)]
    assert arrived[0][R, R] == 1 and not arrived[1].any()  # an arrival: only the requested heading marks it
    pushed = [env.step([RIGHT, STAY])[0]["fov"][1, 6] for env in (plain, refused)]  # now refused: (2, 2) is held
    assert pushed[0][R, R] == 1 and pushed[1][R, R] == 1 and pushed[1].sum() == 1
    moved_on = refused.step([UP, STAY])[0]["fov"][1, 6]
    assert not moved_on.any()  # the push is over


def test_the_refused_heading_needs_the_heading_channel():
    grid = np.zeros((5, 5), np.uint8)
    with pytest.raises(ValueError, match="heading_refused"):
        MapfEnv(grid, np.array([[0, 0]]), np.array([[4, 4]]), heading_refused=True)
    with pytest.raises(ValueError, match="heading_refused"):
        NetworkConfig(heading_refused=True).validate()


def test_headings_mark_each_facing_cell_once_and_skip_stays_and_the_own_heading():
    grid = np.zeros((7, 7), np.uint8)
    builder = ObservationBuilder(grid, np.array([[0, 0], [0, 1], [0, 2], [6, 6]]))
    pos = np.array([[3, 3], [3, 5], [1, 3], [0, 0]])
    out = builder.headings(pos, [UP, LEFT, DOWN, UP])  # 1 and 2 both face (3, 4) and (2, 3): 0 faces (2, 3)
    # Agent 0 at (3, 3): agent 1 faces (3, 4), agent 2 faces (2, 3), agent 3 faces (-1, 0), off the map: unmarked.
    want = np.zeros((9, 9), np.float32)
    want[R, R + 1] = want[R - 1, R] = 1
    assert np.array_equal(out[0], want)
    # Agent 2 at (1, 3): agent 0 faces (2, 3) (one below it); agent 1's (3, 4) is 2 rows down, 1 right.
    want = np.zeros((9, 9), np.float32)
    want[R + 1, R] = want[R + 2, R + 1] = 1
    assert np.array_equal(out[2], want)
    assert out.max() == 1 and out.min() == 0
    assert not builder.headings(pos, [STAY] * 4).any()


def test_default_observation_keeps_the_papers_six_channels():
    grid = np.zeros((5, 5), np.uint8)
    env = MapfEnv(grid, np.array([[0, 0]]), np.array([[4, 4]]))
    obs, _ = env.reset()
    assert obs["fov"].shape == (1, 6, 9, 9)


def test_network_with_heading_reads_seven_channels_and_names_a_wrong_input():
    cfg = NetworkConfig(dueling=True, heading=True)
    net, paper = QNetwork(cfg), QNetwork(NetworkConfig(dueling=True))
    # One more input channel: 64 x 3 x 3 weights of the first conv, and the 1x1 self-attention maps 6x6 -> 7x7 (x3).
    assert count_parameters(net) - count_parameters(paper) == 64 * 9 + 3 * (49 - 36)
    grid = np.zeros((8, 8), np.uint8)
    env = MapfEnv(grid, np.array([[0, 0], [7, 7]]), np.array([[7, 0], [0, 7]]), heading=True)
    obs, _ = env.reset()
    q = net(*network_inputs(obs, cfg))
    assert q.shape == (2, 5) and torch.isfinite(q).all()
    with pytest.raises(ValueError, match="fov"):
        net(torch.zeros(2, 6, 9, 9), torch.zeros(2, 5), torch.zeros(2, 2))


def test_heading_models_have_a_robot_export_that_agrees(tmp_path):
    net = QNetwork(NetworkConfig(dueling=True, heading=True))
    save_model(tmp_path / "h.pt", net, net.cfg, {})
    result = check_export(tmp_path / "h.pt", export_model(tmp_path / "h.pt"), n=300)
    assert result["max_abs_diff"] <= Q_TOLERANCE and result["greedy_disagreements"] == 0
