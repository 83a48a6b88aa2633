"""Faults: a policy node killed mid-run and restarted, an invalid action, SIGINT/SIGTERM to nodes."""
from __future__ import annotations

import json
import os
import signal
import time
import warnings

import pytest

from fleet_helpers import DATA, Fleet, GraphProbe

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.filterwarnings("ignore::DeprecationWarning")]

OK, BLOCKED, TIMEOUT, REJECTED = 0, 1, 2, 3


def test_world_stall_while_robots_answer_is_not_a_timeout(tmp_path, domain_id, any_model):
    """The world process freezes for 0.6 s, more than the action timeout, right after it published a step's
    observations; the policy nodes answer in time meanwhile. When it wakes, the deadline has passed and the
    actions wait in its queue: they must be taken, not counted as timeouts. (rclpy runs the ready timers of a
    wait before its ready subscriptions, so a deadline check on the first timer tick would see none of them.)"""
    from mapf_msgs.msg import AgentObservation

    # Drives at 5x real time: 150 odometry messages/s into the world, not the 600 of 20x; and freezes of
    # 0.6 s, not 1 s. With 1 s freezes 5 of 44 runs had one robot's actions held back by the middleware
    # for 0.1 to 1.5 s after the freeze (consecutive timeouts of that robot, then normal; likely a lost sample of
    # a reliable, in-order stream waiting for its resend), which is not what this test is about.
    fleet = Fleet(tmp_path, domain_id, any_model, world=dict(action_timeout_s=0.4, settle_timeout_s=20.0),
                  real_time_factor=5.0)
    probe = GraphProbe(domain_id)
    stalled = []

    def freeze_world(msg):
        # Robot 0's observation arrives here as it does at its policy node: the world is collecting actions.
        # The first two steps from 1 on that the probe sees (not step 0: the probe may match the world's
        # publisher only after that step has closed; on a loaded machine, after later steps too: one CI run
        # saw neither step 1 nor step 2 when only those two were frozen).
        if msg.step >= 1 and len(stalled) < 2 and msg.step not in stalled:
            pid = fleet.group.procs["world"].pid
            os.kill(pid, signal.SIGSTOP)
            time.sleep(0.6)
            os.kill(pid, signal.SIGCONT)
            stalled.append(msg.step)

    probe.node.create_subscription(AgentObservation, "/robot_0/observation", freeze_world, 10)
    fleet.start()
    try:
        # The probe spins from the start (not after wait_running) so that it sees the earliest steps it can.
        probe.spin_until(lambda: fleet.group.procs["world"].poll() is not None, 90, "the world to finish")
        code = fleet.wait_world()
    finally:
        fleet.stop()
        probe.close()
    assert code == 0, fleet.group.log_text("world")[-3000:]
    s = json.loads(fleet.summary.read_text())
    assert len(stalled) == 2, f"the probe saw robot 0's observation at steps {stalled} only (of {s['steps']})"
    # A freeze that landed while the world collected actions makes that step take about the freeze to
    # close. One must have (a loaded test process may see an observation only after its step closed).
    assert any(s["action_wall_s"][k] >= 0.5 for k in stalled), s["action_wall_s"]
    assert s["timeouts"] == 0 and s["state"] == "success", {k: s[k] for k in ("state", "detail", "timeouts")}


def test_killed_policy_node_stays_others_go_on_restarted_it_rejoins(tmp_path, domain_id, any_model):
    from mapf_msgs.msg import AgentAction, FleetStatus

    # Robot 1 goes corner to corner (8 steps): on fleet_small.scen every robot is home after 3 steps, and one run
    # (session 35) finished there before the kill after step 2 could take effect, so no step came after it.
    fleet = Fleet(tmp_path, domain_id, any_model,
                  world=dict(max_steps=200, action_timeout_s=0.4, settle_timeout_s=20.0,
                             scen_file=str(DATA / "fleet_small_long.scen")))
    probe = GraphProbe(domain_id)
    statuses = []
    probe.node.create_subscription(FleetStatus, "/fleet/status", statuses.append, 100)

    def logs():
        return "\n".join(f"--- {name} log ---\n{fleet.group.log_text(name)[-2500:]}"
                         for name in ("world", "drive_1", "policy_0"))

    bogus = probe.node.create_publisher(AgentAction, "/robot_1/action", 10)
    fleet.start()
    g = fleet.group
    try:
        fleet.wait_running()
        probe.spin_until(lambda: any(s.step >= 2 for s in statuses), 30, "two steps", context=logs)
        g.stop("policy_1", sig=signal.SIGKILL)
        killed_at = statuses[-1].step

        # While robot 1 has no policy, an invalid action on its topic is rejected and it stays.
        # One CI run saw no step for 20 s after the kill (here, one of 34 runs failed after 26 s, output lost). In
        # a two-node check on this machine, Fast DDS blocked a publisher for about 0.3 s after 5 of 30 SIGKILLs of a
        # subscriber and for 2 s after 1 of 20 (docs/FLEET.md, "Faults"). The fleet must go on: within 60 s; a wait
        # over 5 s is reported as a warning.
        t_kill = time.monotonic()
        probe.spin_until(lambda: statuses[-1].step >= killed_at + 2, 60, "steps after the kill", context=logs)
        if time.monotonic() - t_kill > 5.0:
            warnings.warn(f"two steps took {time.monotonic() - t_kill:.1f} s after the kill of policy_1\n{logs()}")
        # A step in which every robot timed out was a stall of the whole machine (seen 1 run in 11 on a loaded
        # 2-core machine): the bad action may not have been read in time either. It is sent again, at most 3 times.
        tried = []
        while len(tried) < 3:
            target = statuses[-1].step   # the world is collecting this step now
            bogus.publish(AgentAction(step=target, robot_id=1, action=9))
            closed = probe.spin_until(
                lambda: next((s for s in statuses if s.step == target + 1 and len(s.outcomes) == 3), None),
                10, "the step with the bad action", context=logs)
            tried.append(target)
            if list(closed.outcomes) != [TIMEOUT] * 3:
                break

        g.start("policy_1", fleet.policy_command(1))
        restarted_at = statuses[-1].step
        probe.spin_until(lambda: any(s.step > restarted_at and s.outcomes[1] in (OK, BLOCKED) for s in statuses)
                         or fleet.group.procs["world"].poll() is not None, 60, "robot 1 to answer again")

        # SIGINT to the recorder mid-run: it finalises the file; the run goes on without it.
        rec_code = g.stop("recorder", sig=signal.SIGINT)
        probe.spin(0.5)
        world_alive = g.procs["world"].poll() is None
        # SIGTERM to the world and the drive executors, SIGINT to the policy nodes: all end cleanly.
        codes = {name: g.stop(name, sig=signal.SIGTERM) for name in ["world"] + [f"drive_{i}" for i in range(3)]}
        codes |= {f"policy_{i}": g.stop(f"policy_{i}", sig=signal.SIGINT) for i in range(3)}
    finally:
        fleet.stop()
        probe.close()

    by_step = {}
    for s in statuses:
        if s.step > 0 and s.state != 0 and len(s.outcomes) == 3:
            by_step[s.step] = list(s.outcomes)   # outcomes of step s - 1
    outcomes = [by_step[k] for k in sorted(by_step)]
    timeouts_1 = [k for k in sorted(by_step) if by_step[k][1] == TIMEOUT]
    assert len(timeouts_1) >= 3, f"robot 1 should have timed out while its policy was dead: {outcomes}"
    # Robots 0 and 2 go on. A stall of the world itself no longer times anyone out (the test above), but on
    # a loaded 2-core machine the surviving policy nodes can miss the 0.4 s limit once or twice when the
    # graph changes (the kill, the restarted node's start-up): seen about 1 run in 10. So they may time
    # out in at most two steps, and must answer in every other one.
    others_out = [k for k in sorted(by_step) if by_step[k][0] == TIMEOUT or by_step[k][2] == TIMEOUT]
    # The world's and the surviving policy nodes' logs go with a failure (pytest keeps only its last few tmp dirs).
    assert len(others_out) <= 2, (f"robots 0 and 2 must go on: {outcomes}\n--- world log ---\n"
                                  f"{fleet.group.log_text('world')[-3000:]}\n--- policy_0 log ---\n"
                                  f"{fleet.group.log_text('policy_0')[-1500:]}")
    assert by_step.get(target + 1, [None, None])[1] == REJECTED, f"bad action at steps {tried}: {outcomes}"
    rejoined = [k for k in sorted(by_step) if k > max(timeouts_1) and by_step[k][1] in (OK, BLOCKED)]
    assert rejoined or not world_alive, f"robot 1 never answered after the restart: {outcomes}"
    world_log = g.log_text("world")
    assert "no valid action from robots [1]" in world_log
    assert "action 9 outside 0..4" in world_log

    assert rec_code == 0
    assert all(c == 0 for c in codes.values()), codes
    # The MCAP file was finalised by SIGINT: it has a summary and every message decodes.
    from mcap.reader import make_reader
    from mcap_ros2.reader import read_ros2_messages
    with open(fleet.mcap, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count > 0
    topics = {m.channel.topic for m in read_ros2_messages(str(fleet.mcap))}
    assert {"/fleet/status", "/robot_1/observation", "/robot_0/odom"} <= topics
    # The interrupted world wrote its summary saying so.
    # (The world can finish on its own between the poll above and the SIGTERM: then its summary is a
    # success, which is also a correct record.)
    if world_alive:
        s = json.loads(fleet.summary.read_text())
        interrupted = s["state"] == "aborted" and "interrupted" in s["detail"]
        assert interrupted or s["state"] == "success", s
