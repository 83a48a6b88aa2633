"""The recorder process alone, fed by this test: nothing lost on any fleet topic of a 3-robot run (at the
fleet's rate and in a burst far above it), SIGTERM finalises the file, SIGKILL keeps every flushed chunk.

The test process publishes on every topic a 3-robot fleet records, with the types and QoS the fleet's
nodes use (mapf_world.fleet_qos: reliable; odometry and cmd_vel 2 s of samples at factor 10, i.e. depth 200;
/fleet/status depth 100; /map and initialpose latched, depth 1; the rest depth 10). Each
message carries its index (a step field, a header stamp, ...) so the log can be checked message by
message: exactly the published number, in order, with their stamps.
"""
from __future__ import annotations

import re
import signal
import time

import pytest

from fleet_helpers import GraphProbe, fleet_env

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.filterwarnings("ignore::DeprecationWarning")]

N_ROBOTS = 3
FLEET_RATE = 20       # messages per topic per second in the first phase (the fleet's odometry at factor 10: 100)
FLEET_COUNT = 20
BURST_COUNT = 300     # then this many per topic back to back: every topic at once, as fast as Python publishes


def _stamp(k):
    from builtin_interfaces.msg import Time
    return Time(sec=k, nanosec=7)


def fleet_topics():
    """[(topic, class, qos, make(k), index_of(msg))] of a 3-robot fleet."""
    from geometry_msgs.msg import PoseWithCovarianceStamped, Twist
    from mapf_msgs.msg import AgentAction, AgentObservation, CellMove, FleetStatus
    from nav_msgs.msg import OccupancyGrid, Odometry
    from visualization_msgs.msg import Marker, MarkerArray

    from mapf_world.fleet_qos import DEFAULT_DEPTH, LATCHED as latched, STATUS_DEPTH, history_depth
    drive = history_depth(100.0)          # the drive executor's ticks at rate_hz 10 x real_time_factor 10
    markers = history_depth(1.0 / 0.2)    # the world node's marker_period_s

    def stamped(cls):
        def make(k):
            m = cls()
            m.header.stamp = _stamp(k)
            return m
        return make

    def twist(k):
        m = Twist()
        m.linear.x = float(k)
        return m

    out = []
    for i in range(N_ROBOTS):
        ns = f"/robot_{i}"
        out += [
            (f"{ns}/observation", AgentObservation, DEFAULT_DEPTH, lambda k, i=i: AgentObservation(step=k, robot_id=i), lambda m: m.step),
            (f"{ns}/action", AgentAction, DEFAULT_DEPTH, lambda k, i=i: AgentAction(step=k, robot_id=i), lambda m: m.step),
            (f"{ns}/cell_move", CellMove, DEFAULT_DEPTH, lambda k, i=i: CellMove(step=k, robot_id=i), lambda m: m.step),
            (f"{ns}/cmd_vel", Twist, drive, twist, lambda m: int(m.linear.x)),
            (f"{ns}/odom", Odometry, drive, stamped(Odometry), lambda m: m.header.stamp.sec),
            (f"{ns}/initialpose", PoseWithCovarianceStamped, latched, stamped(PoseWithCovarianceStamped),
             lambda m: m.header.stamp.sec),
        ]
    out += [
        ("/fleet/status", FleetStatus, STATUS_DEPTH, lambda k: FleetStatus(step=k), lambda m: m.step),
        ("/map", OccupancyGrid, latched, stamped(OccupancyGrid), lambda m: m.header.stamp.sec),
        ("/fleet/markers", MarkerArray, markers, lambda k: MarkerArray(markers=[Marker(id=k)]), lambda m: m.markers[0].id),
    ]
    return out


def start_recorder(tmp_path, domain, name="recorder", **params):
    from mapf_world.fleet_launch import ProcessGroup, node_command
    group = ProcessGroup(tmp_path / "logs", fleet_env(domain))
    mcap = tmp_path / f"{name}.mcap"
    group.start(name, node_command("mapf_world", "recorder", params=dict(output=str(mcap)) | params))
    return group, mcap


def advertise(probe, topics, group, name):
    pubs = [probe.node.create_publisher(cls, topic, qos) for topic, cls, qos, _, _ in topics]
    probe.spin_until(lambda: all(p.get_subscription_count() >= 1 for p in pubs), timeout=30.0,
                     what="the recorder subscribing to every topic; its log:\n" + group.log_text(name)[-2000:])
    return pubs


def read_log(path, topics):
    """{topic: [(index, log_time, publish_time, msg)]} in log order, from the finalised file."""
    from mcap.reader import make_reader
    from rclpy.serialization import deserialize_message
    classes = {t: (cls, index) for t, cls, _, _, index in topics}
    out = {t: [] for t in classes}
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None, f"{path} was not finalised"
        for _, channel, message in reader.iter_messages(log_time_order=False):
            if channel.topic in classes:
                cls, index = classes[channel.topic]
                msg = deserialize_message(message.data, cls)
                out[channel.topic].append((index(msg), message.log_time, message.publish_time, msg))
    return out


def test_nothing_lost_on_any_fleet_topic_at_fleet_rate_and_in_a_burst(tmp_path, domain_id):
    topics = fleet_topics()
    group, mcap = start_recorder(tmp_path, domain_id)
    probe = GraphProbe(domain_id)
    try:
        pubs = advertise(probe, topics, group, "recorder")
        t0 = time.time_ns()
        for k in range(FLEET_COUNT):
            for pub, (_, _, _, make, _) in zip(pubs, topics):
                pub.publish(make(k))
            probe.spin(1.0 / FLEET_RATE)
        burst_start = time.perf_counter()
        for k in range(FLEET_COUNT, FLEET_COUNT + BURST_COUNT):
            for pub, (_, _, _, make, _) in zip(pubs, topics):
                pub.publish(make(k))
        burst_s = time.perf_counter() - burst_start
        probe.spin(3.0)  # let the reliable streams drain into the recorder
        t1 = time.time_ns()
        code = group.stop("recorder", sig=signal.SIGTERM)
    finally:
        probe.close()
        group.stop_all()
    assert code == 0, group.log_text("recorder")[-2000:]
    total = FLEET_COUNT + BURST_COUNT
    # The recorder's own account, from the writers' sequence numbers, agrees.
    # (/rosout counts too when the recorder was its only publisher at discovery.)
    account = re.search(r"sequence numbers: (\d+) published, (\d+) received, (\d+) lost", group.log_text("recorder"))
    assert account and int(account[1]) == int(account[2]) >= total * len(topics) and account[3] == "0"
    rate = BURST_COUNT * len(topics) / burst_s
    print(f"burst: {BURST_COUNT * len(topics)} messages on {len(topics)} topics in {burst_s:.2f} s ({rate:.0f}/s)")
    logged = read_log(mcap, topics)
    for topic, _, _, _, _ in topics:
        got = logged[topic]
        assert [k for k, *_ in got] == list(range(total)), f"{topic}: {len(got)} of {total} messages, or out of order"
        publish_times = [p for _, _, p, _ in got]
        assert all(t0 <= p <= t1 for p in publish_times), f"{topic}: a publish time outside the run"
        assert publish_times == sorted(publish_times), f"{topic}: publish times out of order"
        log_times = [t for _, t, _, _ in got]
        assert log_times == sorted(log_times) and all(p <= t for p, t in zip(publish_times, log_times))
        if topic.endswith(("/odom", "/initialpose", "/map")):  # the index is the header stamp itself
            assert all(m.header.stamp.sec == k and m.header.stamp.nanosec == 7 for k, _, _, m in got), topic
    # The burst really was far above the fleet's rate (3 robots at factor 10: about 700 messages/s).
    assert rate > 2000, f"burst only {rate:.0f} messages/s"


def test_sigkill_keeps_everything_up_to_the_last_flushed_chunk(tmp_path, domain_id):
    from rosbags.highlevel import AnyReader

    from mapf_world.mcap_recover import recover, scan

    topics = [t for t in fleet_topics() if t[0] in ("/robot_0/odom", "/robot_1/cmd_vel", "/fleet/status")]
    group, mcap = start_recorder(tmp_path, domain_id, flush_period_s=0.5)
    probe = GraphProbe(domain_id)
    rate, killed_at = 100.0, None
    try:
        pubs = advertise(probe, topics, group, "recorder")
        for k in range(400):
            for pub, (_, _, _, make, _) in zip(pubs, topics):
                pub.publish(make(k))
            probe.spin(1.0 / rate)
            if k == 250:
                group.send("recorder", signal.SIGKILL)
                killed_at = k
        code = group.procs["recorder"].wait(timeout=10)
    finally:
        probe.close()
        group.stop_all()
    assert code == -signal.SIGKILL
    found = scan(mcap)
    assert not found.finalised and found.problem
    kept = {}
    for m in found.messages:
        topic = found.channels[m.channel_id].topic
        kept.setdefault(topic, []).append(m)
    assert {t for t, *_ in topics} <= set(kept), f"topics kept: {sorted(kept)}"
    from rclpy.serialization import deserialize_message
    for topic, cls, _, _, index in topics:
        ks = [index(deserialize_message(m.data, cls)) for m in kept[topic]]
        # Every message from the first on, in order, up to the last flushed chunk: the last flush came at
        # most flush_period_s (0.5 s, 50 messages at 100 Hz) before the kill; allow as much again for the
        # load of a shared machine.
        assert ks == list(range(len(ks))), f"{topic}: kept messages are not 0..n-1: {ks[:5]}...{ks[-5:]}"
        assert killed_at - 100 <= len(ks) <= killed_at + 1, f"{topic}: kept {len(ks)}, killed after {killed_at + 1}"
    copy = tmp_path / "recorder.recovered.mcap"
    recover(mcap, copy)
    with AnyReader([copy]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        decoded = sum(1 for c, _, raw in reader.messages() if reader.deserialize(raw, c.msgtype) is not None)
    assert counts == {t: len(v) for t, v in kept.items()} and decoded == len(found.messages)
