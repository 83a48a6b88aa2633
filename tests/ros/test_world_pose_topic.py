"""The world node with pose_source pose_topic (real robots under motion capture).

The test process stands in for the motion-capture system and the robots: it publishes each robot's
geometry_msgs/PoseStamped, answers observations with a scripted action and "moves" a robot by
publishing its new pose once the world approves the move.
"""
from __future__ import annotations

import json

import pytest

from fleet_helpers import SMALL_MAP, SMALL_SCEN, GraphProbe, fleet_env

pytestmark = [pytest.mark.ros]

CELL = 0.3
SCRIPT = {0: 4, 1: 3, 2: 4}   # right, left, right: straight to the goals of the small map


def test_world_runs_on_motion_capture_poses(tmp_path, domain_id):
    from geometry_msgs.msg import PoseStamped
    from mapf_msgs.msg import AgentAction, AgentObservation, CellMove
    from mapf_world.fleet_launch import ProcessGroup, node_command

    cells = {0: (0, 0), 1: (4, 4), 2: (2, 0)}   # the scenario's starts
    probe = GraphProbe(domain_id)
    node = probe.node
    pose_pubs = {i: node.create_publisher(PoseStamped, f"/robot_{i}/pose", 10) for i in cells}
    action_pubs = {i: node.create_publisher(AgentAction, f"/robot_{i}/action", 10) for i in cells}
    seen = {"obs": [], "moves": []}

    def on_obs(msg):
        seen["obs"].append((msg.robot_id, msg.step))
        action_pubs[msg.robot_id].publish(AgentAction(step=msg.step, robot_id=msg.robot_id, action=SCRIPT[msg.robot_id]))

    def on_move(msg):
        seen["moves"].append((msg.robot_id, msg.step, tuple(msg.to_cell)))
        cells[msg.robot_id] = tuple(int(v) for v in msg.to_cell)

    for i in cells:
        node.create_subscription(AgentObservation, f"/robot_{i}/observation", on_obs, 10)
        node.create_subscription(CellMove, f"/robot_{i}/cell_move", on_move, 10)

    def publish_poses():
        for i, (r, c) in cells.items():
            msg = PoseStamped()
            msg.header.frame_id = "map"
            msg.pose.position.x, msg.pose.position.y = c * CELL, -r * CELL
            msg.pose.orientation.w = 1.0
            pose_pubs[i].publish(msg)

    node.create_timer(0.02, publish_poses)
    group = ProcessGroup(tmp_path / "logs", fleet_env(domain_id))
    summary = tmp_path / "summary.json"
    group.start("world", node_command("mapf_world", "world_node", params=dict(
        instance_source="map", map_file=str(SMALL_MAP), scen_file=str(SMALL_SCEN), pose_source="pose_topic",
        settle_hold_s=0.1, max_steps=8, ready_grace_s=0.2, cell_size=CELL, summary_path=str(summary), linger_s=0.2)))
    try:
        probe.spin_until(lambda: group.procs["world"].poll() is not None, 60, "the world to finish")
    finally:
        code = group.stop("world")
        probe.close()
    s = json.loads(summary.read_text())
    assert code == 0, group.log_text("world")[-2000:]
    assert s["success"] and s["steps"] == 3 and s["failed_moves"] == 0, s
    assert s["positions"][-1] == s["goals"]
    assert sorted(seen["obs"]) == [(i, k) for i in range(3) for k in range(3)]
    assert cells == {0: (0, 3), 1: (4, 1), 2: (2, 3)}
