"""A robot without torch: the policy node starts and answers observations where `import torch` fails.

A directory on PYTHONPATH holds a package `torch` whose import raises, as on a robot that never installed it
(and so does `mapf_policy.train`, the training code). The node runs the exported model with numpy; its
action equals what the torch Policy picks for the same observation, rule and seed.
"""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from fleet_helpers import GraphProbe, fleet_env, robot_model

pytestmark = [pytest.mark.ros, pytest.mark.filterwarnings("ignore::DeprecationWarning")]

BLOCKED = "raise ImportError('blocked: this robot has no {name} (tests/ros/test_policy_without_torch.py)')\n"


def blocking_env(tmp_path, domain: int) -> dict:
    shim = tmp_path / "shim"
    for name in ("torch",):
        (shim / name).mkdir(parents=True)
        (shim / name / "__init__.py").write_text(BLOCKED.format(name=name))
    env = fleet_env(domain)
    env["PYTHONPATH"] = os.pathsep.join([str(shim)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    return env


def test_policy_node_starts_and_answers_where_torch_cannot_be_imported(tmp_path, domain_id, any_model):
    from mapf_msgs.msg import AgentAction, AgentObservation

    from mapf_policy.policy import Policy
    from mapf_world.fleet_launch import ProcessGroup, node_command
    from mapf_world import fleet_msgs
    from mapf_world.fleet_core import FleetCore
    from mapf_world.instances import generate_instance
    from std_msgs.msg import Header
    from mapf_world.observation import ObservationBuilder

    env = blocking_env(tmp_path, domain_id)
    probe = subprocess.run([sys.executable, "-c", "import torch"], env=env, capture_output=True, text=True)
    assert probe.returncode != 0 and "blocked" in probe.stderr, "the shim must make `import torch` fail"

    model = robot_model(any_model, tmp_path)
    group = ProcessGroup(tmp_path / "logs", env)
    group.start("policy", node_command("mapf_policy", "policy_node", namespace="/robot_1",
                                       params=dict(model_path=str(model))))
    graph = GraphProbe(domain_id)
    got = []
    try:
        graph.node.create_subscription(AgentAction, "/robot_1/action", got.append, 10)
        pub = graph.node.create_publisher(AgentObservation, "/robot_1/observation", 10)
        graph.spin_until(lambda: pub.get_subscription_count() > 0 or group.procs["policy"].poll() is not None,
                         timeout=60.0, what="the policy node's observation subscription")
        assert group.procs["policy"].poll() is None, group.log_text("policy")
        inst = generate_instance(3, size=20, density=0.3, n_agents=4)
        # The observation as the world node builds it for this model (its channels and last-action mode).
        policy = Policy(str(any_model), seed=1)
        core = FleetCore(inst.grid, inst.starts, inst.goals, 10, last_action=policy.meta.get("last_action", "requested"))
        obs = core.observe(ObservationBuilder(inst.grid, inst.goals), policy.cfg.extra_channels())
        msg = fleet_msgs.observations(obs, core, Header(), policy.cfg.extra_channels().names)[1]
        graph.spin_until(lambda: got or pub.publish(msg), timeout=20.0, what="an action from the policy node")
    finally:
        graph.close()
        codes = group.stop_all()
    log = group.log_text("policy")
    assert codes["policy"] == 0, log
    assert "ready in" in log and "Traceback" not in log, log
    assert (got[0].step, got[0].robot_id) == (0, 1)
    expected = policy.act_obs({key: v[1:2] for key, v in obs.items()})
    assert got[0].action == int(expected[0])
