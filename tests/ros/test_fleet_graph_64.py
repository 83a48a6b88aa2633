"""64 robots on a 40x40 benchmark case, their nodes in robot containers of 32 (policy nodes in two processes,
drive executors in two): on the live graph every robot's policy node and drive executor use their own
topics only, and a few grid steps run with every robot answering (no timeouts)."""
from __future__ import annotations

import json

import pytest

from fleet_helpers import GraphProbe, fleet_env, robot_model
from test_fleet import OWN_TOPICS, ROBOT_TOPIC, node_graph

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.filterwarnings("ignore::DeprecationWarning")]

N, PER_PROCESS, STEPS = 64, 32, 3


def test_64_robots_in_containers_use_only_their_own_topics(tmp_path, domain_id, any_model, benchmark_dir):
    from mapf_world.fleet_demo import policy_model_params
    from mapf_world.fleet_launch import ProcessGroup, executable, node_command
    model = robot_model(any_model, tmp_path)
    group = ProcessGroup(tmp_path / "logs", fleet_env(domain_id))
    for lo in range(0, N, PER_PROCESS):
        span = f"{lo}-{lo + PER_PROCESS - 1}"
        group.start(f"policy_{span}", [str(executable("mapf_policy", "robot_container")), "--robots", span,
                                        "--nodes", "policy", "--policy-param", f"model_path:={model}"])
        group.start(f"drive_{span}", [str(executable("mapf_policy", "robot_container")), "--robots", span,
                                       "--nodes", "drive", "--drive-param", "real_time_factor:=20.0",
                                       "--drive-param", "idle_rate_hz:=1.0"])
    summary = tmp_path / "summary.json"
    group.start("world", node_command("mapf_world", "world_node", params=dict(
        instance_source="npz", npz_file=str(benchmark_dir / "dhc_40x40_d0.3" / "agents_64.npz"), npz_index=0,
        n_robots=N, max_steps=STEPS, action_timeout_s=5.0, startup_timeout_s=120.0, summary_path=str(summary))
        | policy_model_params(model)[1]))  # the observation the model reads
    probe = GraphProbe(domain_id)
    graph = {}
    try:
        for i in range(N):
            for name in OWN_TOPICS:
                graph[(name, i)] = node_graph(probe, name, i, timeout=60.0)
        code = group.procs["world"].wait(timeout=180)
    finally:
        probe.close()
        codes = group.stop_all()
    result = json.loads(summary.read_text())
    assert code == 0 and result["steps"] == STEPS and result["timeouts"] == 0, group.log_text("world")[-3000:]
    failed = {n: c for n, c in codes.items() if n != "world" and c != 0}
    assert not failed, (codes, {n: group.log_text(n)[-4000:] for n in failed})
    for i in range(N):
        policy, drive = graph[("policy_node", i)], graph[("drive_executor", i)]
        assert f"/robot_{i}/observation" in policy["subs"] and f"/robot_{i}/action" in policy["pubs"], policy
        assert f"/robot_{i}/cell_move" in drive["subs"] and f"/robot_{i}/odom" in drive["pubs"], drive
        for name, g in (("policy node", policy), ("drive executor", drive)):
            for topic in g["pubs"] + g["subs"]:
                m = ROBOT_TOPIC.match(topic)
                assert m is None or int(m.group(1)) == i, f"{name} of robot {i} uses {topic}"
                assert m or topic in ("/rosout", "/parameter_events"), f"{name} of robot {i} uses {topic}"
