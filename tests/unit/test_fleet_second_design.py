"""The fleet serves the second design: the world node's observations (FleetCore.observe, fleet_msgs.observations)
equal the training environment's (MapfEnv.observe) with the channels beyond the paper's six and the revisit count,
and a robot running the export (RuntimePolicy.message_inputs + act) chooses what the evaluation harness's torch
Policy chooses on MapfEnv, step by step."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from mapf_msgs.msg import AgentObservation
from mapf_policy.action_selection import PAPER_RULE
from mapf_policy.config import NetworkConfig
from mapf_policy.export import export_model
from mapf_policy.model_io import save_model
from mapf_policy.network import QNetwork
from mapf_policy.policy import Policy
from mapf_policy.runtime_net import still_onehot
from mapf_policy.runtime_policy import RuntimePolicy
from mapf_policy.train.demos import COMPARE_STREAM, generated_cases
from mapf_world import fleet_msgs
from mapf_world.env import MapfEnv, revisit_counts
from mapf_world.fleet_core import FleetCore
from mapf_world.observation import ExtraChannels, ObservationBuilder
from std_msgs.msg import Header

ROOT = Path(__file__).resolve().parents[2]
R108 = ROOT / "models" / "training" / "r108_augment_s1" / "ema.pt"


def fleet_step(core: FleetCore, actions) -> None:
    core.begin_step()
    for i, a in enumerate(actions):
        assert core.offer_action(i, core.step, i, int(a)).accepted
    core.close_step()
    core.settle()


@pytest.mark.parametrize("extra", [ExtraChannels(), ExtraChannels(heading=True, priority=True, goal_dirs=True),
                                   ExtraChannels(heading=True, heading_refused=True), ExtraChannels(goal_dirs=True)])
@pytest.mark.parametrize("mode", ["requested", "executed"])
def test_world_observations_equal_the_training_environments(extra, mode):
    inst = generated_cases(5, COMPARE_STREAM, [12], 1, 12, 0.3)[0]  # crowded: refused moves, loops and revisits
    env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=200, last_action=mode, heading=extra.heading,
                  heading_refused=extra.heading_refused, priority=extra.priority, goal_dirs=extra.goal_dirs)
    core = FleetCore(inst.grid, inst.starts, inst.goals, 200, last_action=mode)
    builder = ObservationBuilder(inst.grid, inst.goals)
    rng = np.random.default_rng(0)
    obs, _ = env.reset()
    seen_revisits, refused = set(), 0
    for _ in range(60):
        got = core.observe(builder, extra)
        assert got["fov"].shape[1] == 6 + extra.count
        for key in ("fov", "last_action", "position", "revisits"):
            np.testing.assert_array_equal(got[key], obs[key], err_msg=key)
        seen_revisits |= set(got["revisits"].tolist())
        actions = np.where(rng.random(inst.n_agents) < 0.3, 0, rng.integers(0, 5, inst.n_agents))
        obs, _, _, _, info = env.step(actions)
        refused += int(info["failed"].sum())
        fleet_step(core, actions)
    assert max(seen_revisits) >= 3 and refused > 0  # the counts and the refused-move paths were exercised


def test_revisit_counts_window_and_errors():
    stay = np.zeros((30, 1, 2), np.int64)
    assert revisit_counts(stay[:1]).tolist() == [0]  # the start: nothing before it
    assert revisit_counts(stay[:5]).tolist() == [4]
    assert revisit_counts(stay).tolist() == [16]  # only the last 16 positions count
    with pytest.raises(ValueError, match=r"\(T\+1, N, 2\)"):
        revisit_counts(np.zeros((3, 2)))


def test_extra_channel_names_round_trip_and_bad_sets_are_named():
    for extra in (ExtraChannels(), ExtraChannels(True, True, True, True), ExtraChannels(priority=True)):
        assert ExtraChannels.from_names(extra.names) == extra
    assert ExtraChannels(True, False, True, True).names == ("heading", "priority", "goal_dirs")
    assert ExtraChannels(True, False, True, True).count == 6
    with pytest.raises(ValueError, match="unknown extra channels"):
        ExtraChannels.from_names(["heading", "colour"])
    with pytest.raises(ValueError, match="fov order"):
        ExtraChannels.from_names(["priority", "heading"])
    with pytest.raises(ValueError, match="needs heading=True"):
        ExtraChannels(heading_refused=True)


def robot_play(model_pt: Path, export: Path, inst, steps: int):
    """Greedy play of one instance twice: the harness (MapfEnv + torch Policy on the .pt) and the fleet (FleetCore
    + AgentObservation messages + one RuntimePolicy per robot on the export). Returns both action sequences."""
    probe = RuntimePolicy(export)
    cfg, mode = probe.cfg, probe.last_action_mode
    env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=steps, last_action=mode, **cfg.env_channels())
    policy = Policy(model_pt, rule=PAPER_RULE)
    core = FleetCore(inst.grid, inst.starts, inst.goals, steps, last_action=mode)
    builder = ObservationBuilder(inst.grid, inst.goals)
    robots = [RuntimePolicy(export, rule=PAPER_RULE, seed=i) for i in range(inst.n_agents)]
    obs, _ = env.reset()
    harness, fleet = [], []
    for _ in range(steps):
        a_env = policy.act_obs(obs)
        msgs = fleet_msgs.observations(core.observe(builder, cfg.extra_channels()), core, Header(),
                                       cfg.extra_channels().names)
        a_fleet = np.array([int(r.act(*r.message_inputs(m))[0]) for r, m in zip(robots, msgs)])
        harness.append(a_env)
        fleet.append(a_fleet)
        obs, _, terminated, truncated, _ = env.step(a_env)
        fleet_step(core, a_fleet)
        if terminated or truncated:
            break
    return np.array(harness), np.array(fleet), env, core


@pytest.fixture
def random_second(tmp_path):
    cfg = NetworkConfig(heading=True, priority=True, goal_dirs=True, still_bins=4, still_count="revisit", dueling=True)
    torch.manual_seed(5)
    path = save_model(tmp_path / "second.pt", QNetwork(cfg), cfg, {"last_action": "executed"})
    return path, export_model(path, tmp_path / "second.npz")


def test_a_robot_running_the_export_acts_as_the_harness_on_a_random_second_design_network(random_second):
    pt, npz = random_second
    inst = generated_cases(1, COMPARE_STREAM, [8], 1, 14, 0.3)[0]
    harness, fleet, env, core = robot_play(pt, npz, inst, 40)
    np.testing.assert_array_equal(fleet, harness)
    np.testing.assert_array_equal(core.positions, env.positions)


@pytest.mark.skipif(not R108.is_file(), reason="r108's weights are not in this checkout")
def test_r108_on_the_fleet_acts_as_in_the_harness(tmp_path):
    """r108 (issue 20's best second-design model) greedy on a 16-robot 40x40 case, a whole episode."""
    pt = tmp_path / "r108.pt"
    pt.write_bytes(R108.read_bytes())
    npz = export_model(pt, tmp_path / "r108.npz")
    inst = generated_cases(2, COMPARE_STREAM, [16], 1, 40, 0.3)[0]
    harness, fleet, env, core = robot_play(pt, npz, inst, 256)
    np.testing.assert_array_equal(fleet, harness)
    np.testing.assert_array_equal(core.positions, env.positions)
    assert len(harness) > 20  # a real episode, not one step


def test_a_robot_refuses_an_observation_that_does_not_fit_its_model(random_second):
    _, npz = random_second
    robot = RuntimePolicy(npz, rule=PAPER_RULE)
    cfg = robot.cfg
    good = dict(fov_size=9, fov_channels=12, extra_channels=["heading", "priority", "goal_dirs"],
                fov=[0.0] * (12 * 81), last_action=[1.0, 0, 0, 0, 0], last_action_mode="executed", revisits=7,
                position=[3, 4])
    fov, last, pos, still = robot.message_inputs(AgentObservation(**good))
    assert fov.shape == (1, 12, 9, 9) and still.tolist() == still_onehot(np.array([3]), 4).tolist()
    for change, match in ((dict(fov_channels=6, fov=[0.0] * 486, extra_channels=[]), "the model reads fov_size 9, 12"),
                          (dict(extra_channels=["heading", "goal_dirs", "priority"]), "extra channels"),
                          (dict(fov=[0.0] * 10), "holds 10 values"),
                          (dict(last_action_mode="requested"), "trained with 'executed'"),
                          (dict(last_action_mode=""), "unnamed mode")):
        with pytest.raises(ValueError, match=match):
            robot.message_inputs(SimpleNamespace(**(good | change)))
    assert cfg.fov_channels == 12


def test_a_still_input_counting_anything_but_revisits_cannot_be_served(tmp_path):
    cfg = NetworkConfig(still_bins=4, still_count="cell")
    path = save_model(tmp_path / "cell.pt", QNetwork(cfg), cfg, {})
    robot = RuntimePolicy(export_model(path, tmp_path / "cell.npz"))
    with pytest.raises(ValueError, match="carries the 'revisit' count only"):
        robot.check_servable()
