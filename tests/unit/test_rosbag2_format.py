"""rosbag2 (Jazzy) metadata in the MCAP files the recorder writes, checked against `rosbags` (pinned)."""
from pathlib import Path

import pytest
import yaml

from mapf_world.mcap_log import McapRos2Writer
from mapf_world.rosbag2_format import (INFINITE_NS, METADATA_KEY, METADATA_RECORD, QosProfile, bag_metadata,
                                       duration, offered_qos_profiles)

# Written out by hand from rosbag2's serialisation (qos.cpp, metadata version 9): every field in rmw
# order, enums by name, durations as {sec, nsec}, infinity as RMW_DURATION_INFINITE.
EXPECTED_ODOM_QOS = """\
- history: unknown
  depth: 0
  reliability: reliable
  durability: volatile
  deadline:
    sec: 9223372036
    nsec: 854775807
  lifespan:
    sec: 9223372036
    nsec: 854775807
  liveliness: automatic
  liveliness_lease_duration:
    sec: 9223372036
    nsec: 854775807
  avoid_ros_namespace_conventions: false"""

ROSOUT = QosProfile(durability="transient_local", lifespan_ns=10_000_000_000)
MAP = QosProfile(durability="transient_local")


def test_durations_and_infinity_are_rmw_times():
    assert duration(INFINITE_NS) == {"sec": 9223372036, "nsec": 854775807}
    assert duration(10_000_000_000) == {"sec": 10, "nsec": 0}
    assert duration(1_500_000_001) == {"sec": 1, "nsec": 500_000_001}


def test_offered_qos_profiles_text_is_rosbag2_s():
    assert offered_qos_profiles([QosProfile()]) == EXPECTED_ODOM_QOS
    assert offered_qos_profiles([]) == "[]"


def test_identical_profiles_are_listed_once_in_first_seen_order():
    text = offered_qos_profiles([ROSOUT] * 8 + [MAP, ROSOUT])
    parsed = yaml.safe_load(text)
    assert len(parsed) == 2
    assert parsed[0]["lifespan"] == {"sec": 10, "nsec": 0} and parsed[1]["lifespan"]["sec"] == 9223372036
    assert parsed[0]["durability"] == "transient_local"


def test_bad_profiles_are_refused():
    with pytest.raises(ValueError, match="history 'keep_some' is not one of"):
        QosProfile(history="keep_some")
    with pytest.raises(ValueError, match="depth must be in"):
        QosProfile(depth=-1)


def test_bag_metadata_is_version_9_yaml_with_every_field():
    from mapf_world.rosbag2_format import TopicRecord
    text = bag_metadata("fleet.mcap", [TopicRecord("/map", "nav_msgs/msg/OccupancyGrid", [MAP, MAP], "RIHS01_ab", 1),
                                       TopicRecord("/a: b", "std_msgs/msg/String", [], "", 0)],
                        starting_time_ns=5, duration_ns=7, message_count=1)
    meta = yaml.safe_load(text)
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap" and meta["ros_distro"] == "jazzy"
    assert meta["duration"] == {"nanoseconds": 7} and meta["starting_time"] == {"nanoseconds_since_epoch": 5}
    first, second = meta["topics_with_message_count"]
    assert first["message_count"] == 1
    assert first["topic_metadata"]["offered_qos_profiles"] == [MAP.as_dict()]
    assert first["topic_metadata"]["type_description_hash"] == "RIHS01_ab"
    assert second["topic_metadata"]["name"] == "/a: b" and second["topic_metadata"]["offered_qos_profiles"] == []
    assert meta["relative_file_paths"] == ["fleet.mcap"] and meta["files"][0]["message_count"] == 1
    assert meta["custom_data"] is None and meta["compression_mode"] == ""


def _write_log(path: Path, n: int = 6) -> dict:
    """A small log with the fleet's kinds of topic; returns topic -> payload count."""
    from geometry_msgs.msg import Twist
    from mapf_msgs.msg import AgentObservation
    from nav_msgs.msg import OccupancyGrid
    from rcl_interfaces.msg import Log
    from rclpy.serialization import serialize_message

    with McapRos2Writer(path) as w:
        c_obs = w.add_channel("/robot_0/observation", "mapf_msgs/msg/AgentObservation", [QosProfile()], "RIHS01_x")
        c_tw = w.add_channel("/robot_0/cmd_vel", "geometry_msgs/msg/Twist", [QosProfile()])
        c_map = w.add_channel("/map", "nav_msgs/msg/OccupancyGrid", [MAP])
        c_log = w.add_channel("/rosout", "rcl_interfaces/msg/Log", [ROSOUT] * 8)
        for k in range(n):
            w.write(c_obs, serialize_message(AgentObservation(step=k, fov_size=1, fov=[float(k)] * 6)), 1000 + k)
            tw = Twist()
            tw.linear.x = 0.1 * k
            w.write(c_tw, serialize_message(tw), 1000 + k, publish_time_ns=900 + k)
        grid = OccupancyGrid()
        grid.info.width, grid.info.height = 2, 1
        grid.data = [0, 100]
        w.write(c_map, serialize_message(grid), 2000)
        w.write(c_log, serialize_message(Log(level=30, name="world", msg="hello")), 2001)
    return {"/robot_0/observation": n, "/robot_0/cmd_vel": n, "/map": 1, "/rosout": 1}


def test_rosbags_opens_the_log_and_decodes_every_message(tmp_path):
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import QosDurability, QosHistory, QosLiveliness, QosReliability

    path = tmp_path / "fleet.mcap"
    expected = _write_log(path)
    with AnyReader([path]) as reader:
        conns = {c.topic: c for c in reader.connections}
        assert set(conns) == set(expected)
        (obs_qos,) = conns["/robot_0/observation"].ext.offered_qos_profiles
        assert obs_qos.history == QosHistory.UNKNOWN and obs_qos.reliability == QosReliability.RELIABLE
        assert obs_qos.durability == QosDurability.VOLATILE and obs_qos.liveliness == QosLiveliness.AUTOMATIC
        assert (obs_qos.deadline.sec, obs_qos.deadline.nsec) == (9223372036, 854775807)
        (rosout_qos,) = conns["/rosout"].ext.offered_qos_profiles     # eight publishers, one profile
        assert rosout_qos.lifespan.sec == 10 and rosout_qos.durability == QosDurability.TRANSIENT_LOCAL
        got = {}
        for conn, stamp, raw in reader.messages():
            got.setdefault(conn.topic, []).append((stamp, reader.deserialize(raw, conn.msgtype)))
    assert {t: len(v) for t, v in got.items()} == expected
    assert [m.step for _, m in got["/robot_0/observation"]] == list(range(6))
    assert [t for t, _ in got["/robot_0/observation"]] == [1000 + k for k in range(6)]
    assert list(got["/robot_0/observation"][5][1].fov) == [5.0] * 6
    assert got["/rosout"][0][1].msg == "hello" and list(got["/map"][0][1].data) == [0, 100]


def test_channel_and_bag_metadata_records(tmp_path):
    from mcap.reader import make_reader

    path = tmp_path / "fleet.mcap"
    _write_log(path)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        records = [m for m in reader.iter_metadata() if m.name == METADATA_RECORD]
    for channel in summary.channels.values():
        assert set(channel.metadata) == {"offered_qos_profiles", "topic_type_hash"}
        assert channel.message_encoding == "cdr"
    by_topic = {c.topic: c for c in summary.channels.values()}
    assert by_topic["/robot_0/observation"].metadata["offered_qos_profiles"] == EXPECTED_ODOM_QOS
    assert by_topic["/robot_0/observation"].metadata["topic_type_hash"] == "RIHS01_x"
    assert by_topic["/map"].metadata["topic_type_hash"] == ""
    assert {s.name for s in summary.schemas.values()} >= {"mapf_msgs/msg/AgentObservation", "rcl_interfaces/msg/Log"}
    # One at the start (no topics yet), the last one, written at close, with every count.
    assert len(records) == 2
    first, last = (yaml.safe_load(r.metadata[METADATA_KEY]) for r in records)
    assert first["message_count"] == 0 and first["topics_with_message_count"] == []
    assert last["version"] == 9 and last["message_count"] == 14
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in last["topics_with_message_count"]}
    assert counts == {"/robot_0/observation": 6, "/robot_0/cmd_vel": 6, "/map": 1, "/rosout": 1}
    assert last["starting_time"]["nanoseconds_since_epoch"] == 1000 and last["duration"]["nanoseconds"] == 1001
