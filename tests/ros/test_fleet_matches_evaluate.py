"""The fleet runs the benchmark's policy: for the same case, model, action rule and seeds, the grid trajectory in
the fleet's MCAP log equals the one `scripts/evaluate --trajectories` writes (3 robots): the paper's greedy rule,
whose actions depend on nothing but the observations, and the shipped sampled rule, where the harness gives agent
i its own generator seeded with i (--per-agent-seeds) as each robot's node seeds its own with its id. The
64-robot check is documented in docs/FLEET.md."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fleet_helpers import SMALL_MAP, SMALL_SCEN, Fleet

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.filterwarnings("ignore::DeprecationWarning")]

MAX_STEPS = 12


def run_fleet(out, domain_id, model, rule_name: str, case, max_steps: int, n_robots: int = 3, policy=None):
    """The fleet on case 0 of `case` under the paper's rule or the default one (the policy node's defaults, seed =
    robot id); the world's observation parameters come from the model's export (Fleet). (fleet, world code, summary)."""
    from mapf_policy.action_selection import PAPER_RULE
    from mapf_policy.policy_node import RULE_PARAMETERS
    rule = {k: getattr(PAPER_RULE, k) for k in RULE_PARAMETERS} if rule_name == "paper" else {}
    fleet = Fleet(out, domain_id, model, n_robots=n_robots, policy=rule | (policy or {}),
                  world=dict(instance_source="npz", npz_file=str(case), npz_index=0, max_steps=max_steps))
    fleet.start()
    try:
        code = fleet.wait_world(timeout=120)
    finally:
        fleet.stop()
    return fleet, code, json.loads(fleet.summary.read_text())


@pytest.mark.parametrize("rule_name", ["paper", "default"])
def test_fleet_trajectory_equals_the_evaluation_harness_s(tmp_path, domain_id, any_model, rule_name):
    from mapf_world.evaluate import main as evaluate
    from mapf_world.fleet_core import load_fleet_instance
    from mapf_world.fleet_replay import load_run
    from mapf_world.instances import save_npz

    case = tmp_path / "small.npz"
    save_npz(case, [load_fleet_instance("map", map_file=str(SMALL_MAP), scen_file=str(SMALL_SCEN), n_robots=3)])
    traj_file = tmp_path / "traj.npz"
    seeds = ["--per-agent-seeds"] if rule_name == "default" else []
    assert evaluate(["--solver", "hscl", "--model", str(any_model), "--instances", str(case), "--action-rule", rule_name,
                     "--max-steps", str(MAX_STEPS), "--trajectories", str(traj_file), *seeds]) == 0
    with np.load(traj_file) as traj:
        steps = int(traj["steps"][0])
        expected = traj["positions"][0][:steps + 1]

    # The default rule is the policy node's default too (and its seed -1: the robot id).
    fleet, code, summary = run_fleet(tmp_path / "fleet", domain_id, any_model, rule_name, case, MAX_STEPS)
    assert code == 0 and summary["timeouts"] == 0, fleet.group.log_text("world")[-2000:]
    logged = load_run(fleet.mcap).positions()
    assert summary["steps"] == steps
    assert logged.shape == expected.shape, (logged.shape, expected.shape)
    np.testing.assert_array_equal(logged, expected)
    from mapf_world.fleet_check import main as check_fleet
    assert check_fleet([str(fleet.mcap), str(traj_file)]) == 0  # the documented 64-robot check says the same
    assert steps >= 3 and (expected[-1] != expected[0]).any()  # the robots moved: the comparison means something


R108 = Path(__file__).resolve().parents[2] / "models" / "training" / "r108_augment_s1" / "ema.pt"


@pytest.mark.skipif(not R108.is_file(), reason="r108's weights are not in this checkout")
@pytest.mark.parametrize("rule_name", ["paper", "default"])
def test_a_second_design_fleet_follows_the_harness(tmp_path, domain_id, rule_name):
    """r108 (issue 20's second design: heading, priority and goal-direction channels, the executed last action, the
    revisit count) on a crowded generated case: the world node's parameters come from the export, as scripts/demo
    sets them, and the robots' trajectory equals the harness's."""
    import shutil

    from mapf_policy.export import export_model
    from mapf_world.evaluate import main as evaluate
    from mapf_world.fleet_demo import policy_model_params
    from mapf_world.fleet_replay import load_run
    from mapf_world.instances import generate_instance, save_npz

    model = tmp_path / "r108.pt"
    shutil.copyfile(R108, model)
    export_model(model)
    policy_params, observation_params = policy_model_params(model)
    assert observation_params == {"last_action": "executed", "extra_channels": ["heading", "priority", "goal_dirs"]}
    case = tmp_path / "crowded.npz"
    save_npz(case, [generate_instance(np.random.default_rng(4), size=7, density=0.2, n_agents=4)])
    traj_file = tmp_path / "traj.npz"
    seeds = ["--per-agent-seeds"] if rule_name == "default" else []
    assert evaluate(["--solver", "hscl", "--model", str(model), "--instances", str(case), "--action-rule", rule_name,
                     "--max-steps", "30", "--trajectories", str(traj_file), *seeds]) == 0
    with np.load(traj_file) as traj:
        steps = int(traj["steps"][0])
        expected = traj["positions"][0][:steps + 1]
    fleet, code, summary = run_fleet(tmp_path / "fleet", domain_id, model, rule_name, case, 30, n_robots=4,
                                     policy={"source_sha256": policy_params["source_sha256"]})
    assert {k: fleet.world_params[k] for k in observation_params} == observation_params  # as scripts/demo sets them
    assert code == 0 and summary["timeouts"] == 0 and summary["rejected"] == 0, fleet.group.log_text("world")[-2000:]
    log = load_run(fleet.mcap)
    np.testing.assert_array_equal(log.positions(), expected)
    first = log.observations[0][0]
    assert first.fov_channels == 12 and list(first.extra_channels) == ["heading", "priority", "goal_dirs"]
    assert first.last_action_mode == "executed"
    assert steps >= 3 and (expected[-1] != expected[0]).any()
