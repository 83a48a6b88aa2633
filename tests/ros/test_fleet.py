"""Three robots as separate processes on a small map: the run, its MCAP log and the live ROS graph.

One fleet run (module fixture) feeds all tests here. Goal reaching needs the trained model
(models/hscl.pt); with an untrained model of the same architecture the plumbing is still checked.
"""
from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from fleet_helpers import TRAINED_MODEL, Fleet, GraphProbe

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.filterwarnings("ignore::DeprecationWarning")]

MAX_V, MAX_W = 0.2, 1.57
CELL = 0.3
ROBOT_TOPIC = re.compile(r"^/robot_(\d+)/")


def graph_of(probe: GraphProbe, name: str, ns: str):
    node = probe.node
    try:
        pubs = node.get_publisher_names_and_types_by_node(name, ns)
        subs = node.get_subscriber_names_and_types_by_node(name, ns)
    except Exception:  # not discovered yet
        return None
    return {"pubs": sorted(t for t, _ in pubs), "subs": sorted(t for t, _ in subs)}


# A robot node's own topics (subscribed, published), which the graph must show before a snapshot is taken:
# discovery reports a node's endpoints one by one, so a node seen with /rosout and one of its topics is not
# yet complete (seen once under load in test_fleet_graph_64).
OWN_TOPICS = {"policy_node": ("observation", "action"), "drive_executor": ("cell_move", "odom")}


def node_graph(probe: GraphProbe, name: str, i: int, timeout: float) -> dict:
    """Publishers and subscriptions of robot i's node `name` once its own topics show on the graph."""
    sub, pub = (f"/robot_{i}/{t}" for t in OWN_TOPICS[name])
    return probe.spin_until(
        lambda: (g := graph_of(probe, name, f"/robot_{i}")) and sub in g["subs"] and pub in g["pubs"] and g,
        timeout=timeout, what=f"{name} of robot {i} on the graph with {sub} and {pub}")


@pytest.fixture(scope="module")
def run(tmp_path_factory, module_domain_id, any_model):
    out = tmp_path_factory.mktemp("fleet")
    fleet = Fleet(out, module_domain_id, any_model, world=dict(max_steps=12 if TRAINED_MODEL.is_file() else 6))
    probe = GraphProbe(module_domain_id)
    fleet.start()
    graph = {}
    try:
        fleet.wait_running()
        for i in range(fleet.n):
            for name in OWN_TOPICS:
                graph[(name, i)] = node_graph(probe, name, i, timeout=10.0)
        world_code = fleet.wait_world(timeout=120)
    finally:
        codes = fleet.stop()
        probe.close()
    from mapf_world.fleet_replay import load_run
    return dict(fleet=fleet, graph=graph, world_code=world_code, codes=codes, log=load_run(fleet.mcap),
                summary=json.loads(fleet.summary.read_text()))


def test_every_node_ends_cleanly(run):
    assert run["world_code"] == 0, run["fleet"].group.log_text("world")[-2000:]
    assert all(code == 0 for code in run["codes"].values()), run["codes"]


def test_policy_nodes_use_only_their_own_topics(run):
    for i in range(3):
        g = run["graph"][("policy_node", i)]
        assert f"/robot_{i}/observation" in g["subs"], g
        assert f"/robot_{i}/action" in g["pubs"], g
        for topic in g["pubs"] + g["subs"]:
            m = ROBOT_TOPIC.match(topic)
            assert m is None or int(m.group(1)) == i, f"policy node of robot {i} uses {topic}"
            assert m or topic in ("/rosout", "/parameter_events"), f"policy node of robot {i} uses {topic}"


def test_drive_executors_use_only_their_own_topics(run):
    for i in range(3):
        g = run["graph"][("drive_executor", i)]
        assert {f"/robot_{i}/cmd_vel", f"/robot_{i}/odom"} <= set(g["pubs"]), g
        assert f"/robot_{i}/cell_move" in g["subs"], g
        for topic in g["pubs"] + g["subs"]:
            m = ROBOT_TOPIC.match(topic)
            assert m is None or int(m.group(1)) == i, f"drive executor of robot {i} uses {topic}"


def test_mcap_holds_every_robot_topic(run):
    log, steps = run["log"], run["summary"]["steps"]
    assert steps >= 1
    for i in range(3):
        for kind in ("observation", "action", "cell_move", "cmd_vel", "odom"):
            assert log.counts[f"/robot_{i}/{kind}"] > 0, f"no /robot_{i}/{kind} in the log: {log.counts}"
        assert [o.step for o in log.observations[i]] == list(range(steps))
        assert [a.step for a in log.actions[i]] == list(range(steps))
        assert all(o.robot_id == i for o in log.observations[i])
    assert log.counts["/map"] == 1 and log.counts["/fleet/status"] >= steps + 1


def test_mcap_is_rosbag2_style(run):
    from mcap.reader import make_reader
    from mcap_ros2.reader import read_ros2_messages
    with open(run["fleet"].mcap, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    n = sum(1 for _ in read_ros2_messages(str(run["fleet"].mcap)))
    assert n == summary.statistics.message_count


def test_mcap_opens_in_rosbags_with_full_qos_and_every_message_decodes(run):
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import QosHistory, QosReliability
    decoded = 0
    with AnyReader([run["fleet"].mcap]) as reader:
        conns = {c.topic: c for c in reader.connections}
        for kind in ("observation", "action", "cell_move", "cmd_vel", "odom"):
            (qos,) = conns[f"/robot_0/{kind}"].ext.offered_qos_profiles
            # The graph does not report a remote publisher's history (rosbag2 writes the same).
            assert qos.history == QosHistory.UNKNOWN and qos.reliability == QosReliability.RELIABLE
            assert qos.deadline.sec == 9223372036 and qos.liveliness_lease_duration.nsec == 854775807
        # /rosout has one publisher per node (world, recorder, 2 per robot), all with one profile.
        assert len(conns["/rosout"].ext.offered_qos_profiles) == 1
        for conn, _, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            decoded += 1
    assert decoded == sum(run["log"].counts.values()) > 0


def test_velocities_never_exceed_the_limits(run):
    log = run["log"]
    for i in range(3):
        cmds = np.array([(v, w) for _, v, w in log.cmd_vel[i]])
        assert np.abs(cmds[:, 0]).max() <= MAX_V + 1e-9 and np.abs(cmds[:, 1]).max() <= MAX_W + 1e-9
        od = np.array(log.odom[i])   # t, x, y, yaw, v, w
        assert np.abs(od[:, 4]).max() <= MAX_V + 1e-9 and np.abs(od[:, 5]).max() <= MAX_W + 1e-9
        # The poses themselves, against their (simulated) stamps: physical speeds.
        dt = np.diff(od[:, 0])
        assert (dt > 0).all(), "odom stamps must increase"
        speed = np.hypot(np.diff(od[:, 1]), np.diff(od[:, 2])) / dt
        turn = np.abs((np.diff(od[:, 3]) + np.pi) % (2 * np.pi) - np.pi) / dt
        assert speed.max() <= MAX_V * 1.001 and turn.max() <= MAX_W * 1.001
        moved = any(a != "stay" for a in np.array(run["summary"]["actions"])[:, i])
        assert moved, f"robot {i} never moved: nothing checked (the model should make every robot move)"
        assert speed.max() > 0.5 * MAX_V, "a moving robot drives near its top speed"


def test_odometry_ends_on_the_final_cells(run):
    log, summary = run["log"], run["summary"]
    final = summary["positions"][-1]
    for i in range(3):
        _, x, y, *_ = log.odom[i][-1]
        r, c = final[i]
        assert math.hypot(x - c * CELL, y + r * CELL) < 1e-6, f"robot {i} odom ({x}, {y}) vs cell {(r, c)}"


def test_logged_cells_match_the_world_summary(run):
    assert run["log"].positions().tolist() == run["summary"]["positions"]


@pytest.mark.skipif(not TRAINED_MODEL.is_file(), reason=f"no trained model at {TRAINED_MODEL} (the policy issue ships it)")
def test_all_robots_reach_their_goals_without_failed_moves(run):
    s = run["summary"]
    assert s["success"], s["detail"]
    assert s["failed_moves"] == 0 and s["timeouts"] == 0 and s["rejected"] == 0
    assert s["positions"][-1] == s["goals"]
    log = run["log"]
    for i, (r, c) in enumerate(s["goals"]):
        _, x, y, *_ = log.odom[i][-1]
        assert math.hypot(x - c * CELL, y + r * CELL) < 1e-6


def test_observations_are_mapf_env_observations_and_actions_the_policy_s(run, any_model):
    """The world builds observations with MapfEnv's code; each policy node answers as the Policy would.

    The nodes run with the default action temperature (sampled actions) and seed = robot id, so a Policy
    per robot with the same seed, asked the same observations in the same order, draws the same actions.
    """
    from mapf_policy.policy import Policy
    from mapf_world.env import MapfEnv
    from mapf_world.fleet_core import load_fleet_instance

    fleet, log, s = run["fleet"], run["log"], run["summary"]
    p = fleet.world_params
    inst = load_fleet_instance("map", map_file=p["map_file"], scen_file=p["scen_file"], n_robots=3)
    policies = [Policy(str(any_model), seed=i) for i in range(3)]
    # The observation the model reads: its last-action mode and channels, as the world was told (Fleet).
    env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=1000, last_action=p["last_action"],
                  **policies[0].cfg.env_channels())
    obs, _ = env.reset()
    for k in range(s["steps"]):
        requested = [log.moves[k][i].requested_action for i in range(3)]
        for i in range(3):
            msg = log.observations[i][k]
            assert np.array_equal(np.asarray(msg.fov, np.float32).reshape(obs["fov"][i].shape), obs["fov"][i]), (k, i)
            assert np.array_equal(np.asarray(msg.last_action, np.float32), obs["last_action"][i]), (k, i)
            assert list(msg.position) == obs["position"][i].astype(int).tolist()
            assert msg.revisits == obs["revisits"][i], (k, i)
            expected = int(policies[i].act_obs({key: v[i:i + 1] for key, v in obs.items()})[0])
            assert log.actions[i][k].action == expected == requested[i], (k, i)
        obs, *_ = env.step(requested)
        assert env.positions.tolist() == s["positions"][k + 1]
