"""The evaluation harness serves the second design's inputs: the channels beyond the paper's six (heading,
priority, goal directions) and the revisit count, as the training code and the ladder build them."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from mapf_policy.config import NetworkConfig
from mapf_policy.model_io import save_model
from mapf_policy.network import QNetwork, network_inputs
from mapf_policy.policy import Policy
from mapf_policy.solver import make_hscl
from mapf_policy.train.compare import compare
from mapf_policy.train.demos import COMPARE_STREAM, generated_cases
from mapf_policy.train.dqn_hscl import acting, greedy_outcomes
from mapf_world.env import MapfEnv
from mapf_world.evaluate import run_case

SECOND = NetworkConfig(heading=True, priority=True, goal_dirs=True, still_bins=4, still_count="revisit")


@pytest.fixture
def second_model(tmp_path):
    torch.manual_seed(3)
    path = tmp_path / "second.pt"
    save_model(path, QNetwork(SECOND), SECOND, {"step": 0, "last_action": "executed"})
    return path


def test_solver_acts_as_the_network_reads_its_inputs(second_model):
    solver = make_hscl(model=second_model, action_rule="paper")
    assert solver.env_channels == SECOND.env_channels() and solver.env_channels["revisit_cap"] == 3
    net = solver.policy.net
    inst = generated_cases(0, COMPARE_STREAM, [6], 1, 12, 0.3)[0]
    env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=40, last_action="executed", **SECOND.env_channels())
    obs, _ = env.reset()
    solver.reset(env)
    assert obs["fov"].shape[1] == SECOND.fov_channels == 12
    stills = set()
    for _ in range(25):
        actions = solver.act(obs)
        with torch.no_grad():
            expected = net(*network_inputs(obs, SECOND)).argmax(1).numpy()
        np.testing.assert_array_equal(actions, expected)
        stills |= set(np.asarray(obs["revisits"]).tolist())
        obs, _, terminated, truncated, _ = env.step(actions)
        if terminated or truncated:
            break
    assert max(stills) >= 1  # the still input took more than one value, so its path was exercised


def test_harness_builds_the_models_observation(second_model):
    solver = make_hscl(model=second_model, action_rule="paper")
    inst = generated_cases(0, COMPARE_STREAM, [4], 1, 10, 0.3)[0]
    result = run_case(solver, inst, 20)  # a six-channel observation would fail the network's shape check
    assert result.steps <= 20


def test_compare_models_matches_the_ladders_greedy_play(second_model):
    cases = generated_cases(0, COMPARE_STREAM, [1, 3], 4, 10, 0.3)
    by_size = compare([second_model], [1, 3], 4, seed=0, map_size=10, density=0.3, max_steps=30,
                      progress=False)[str(second_model)]
    policy = Policy(second_model)
    outcomes = greedy_outcomes(acting(policy.net), cases, "executed", 30)
    for n in (1, 3):
        mine = [o for o, inst in zip(outcomes, cases) if inst.n_agents == n]
        assert by_size[str(n)]["successes"] == sum(s for s, _ in mine)
        assert by_size[str(n)]["average_step"] == pytest.approx(np.mean([t for _, t in mine]))


def test_still_input_is_checked_and_recurrent_refused(second_model, tmp_path):
    policy = Policy(second_model)
    fov, last, pos = np.zeros((2, 12, 9, 9)), np.eye(5)[[0, 0]], np.zeros((2, 2))
    with pytest.raises(ValueError, match="still"):
        policy.q_values(fov, last, pos)
    assert policy.q_values(fov, last, pos, np.eye(4)[[0, 3]]).shape == (2, 5)
    with pytest.raises(ValueError, match="still"):
        Policy(QNetwork(NetworkConfig())).q_values(np.zeros((1, 6, 9, 9)), np.eye(5)[[0]], np.zeros((1, 2)),
                                                   np.eye(4)[[0]])
    with pytest.raises(ValueError, match="recurrent"):
        Policy(QNetwork(NetworkConfig(recurrent=True)))


def test_the_sampled_rule_reads_the_papers_six_channels(second_model):
    # The shipped rule's helpers (settled agents, obstacle moves, the backtrack penalty) read channels 0-5.
    solver = make_hscl(model=second_model, action_rule="default", seed=5)
    inst = generated_cases(1, COMPARE_STREAM, [4], 1, 10, 0.3)[0]
    first = run_case(solver, inst, 20)
    again = run_case(solver, inst, 20)
    assert first.steps == again.steps and (first.positions == again.positions).all()  # one seed, one result
