"""rosbag2-style MCAP writing (mapf_world.mcap_log): complete schema text, decodable files."""
import pytest

from mapf_world.mcap_log import SEPARATOR, McapRos2Writer, field_types, message_definition, split_type_name
from mapf_world.rosbag2_format import QosProfile

FAKE = {
    ("pkg", "Outer"): "# comment\nHeader header\nint32 A=3  # a constant\npkg/Inner[] inners\nInner[<=2] few\nstring<=5 s\n",
    ("pkg", "Inner"): "other_pkg/Leaf leaf\nfloat64[3] v\n",
    ("other_pkg", "Leaf"): "builtin_interfaces/Time stamp\n",
    ("std_msgs", "Header"): "builtin_interfaces/Time stamp\nstring frame_id\n",
    ("builtin_interfaces", "Time"): "int32 sec\nuint32 nanosec\n",
}


def fake_read(pkg, name):
    return FAKE[(pkg, name)]


def test_field_types_skip_primitives_and_constants_and_resolve_short_names():
    assert field_types(FAKE[("pkg", "Outer")], "pkg") == ["std_msgs/Header", "pkg/Inner", "pkg/Inner"]
    with pytest.raises(ValueError, match="cannot parse"):
        field_types("justonetoken\n", "pkg")


def test_definition_is_built_as_rosbag2_builds_it():
    # Each file's text as it is, then each nested type (sorted by name, depth-first, once) after a
    # newline, 80 '=' and "MSG: pkg/Name".
    sep = "\n" + "=" * 80 + "\nMSG: "
    expected = (FAKE[("pkg", "Outer")]
                + sep + "pkg/Inner\n" + FAKE[("pkg", "Inner")]
                + sep + "other_pkg/Leaf\n" + FAKE[("other_pkg", "Leaf")]
                + sep + "builtin_interfaces/Time\n" + FAKE[("builtin_interfaces", "Time")]
                + sep + "std_msgs/Header\n" + FAKE[("std_msgs", "Header")])
    text = message_definition("pkg/msg/Outer", read=fake_read)
    assert text == expected
    assert text.count("MSG: builtin_interfaces/Time") == 1
    for line in text.splitlines():
        if set(line) == {"="}:
            assert len(line) == 80
    assert message_definition("builtin_interfaces/msg/Time", read=fake_read) == FAKE[("builtin_interfaces", "Time")]


def test_bad_type_names_are_refused():
    for bad in ("Odometry", "a/b/c/d", "nav_msgs/srv/X"):
        with pytest.raises(ValueError, match="not of the form"):
            split_type_name(bad)


def test_installed_definitions_are_complete():
    text = message_definition("nav_msgs/msg/Odometry")
    for dep in ("std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/PoseWithCovariance",
                "geometry_msgs/Pose", "geometry_msgs/Point", "geometry_msgs/Quaternion",
                "geometry_msgs/TwistWithCovariance", "geometry_msgs/Twist", "geometry_msgs/Vector3"):
        assert text.count(f"MSG: {dep}\n") == 1, dep
    assert "MSG: std_msgs/Header" in message_definition("mapf_msgs/msg/AgentObservation")
    with pytest.raises(ValueError, match="not in the ament index"):
        message_definition("no_such_pkg/msg/X")
    with pytest.raises(ValueError, match="no definition file"):
        message_definition("std_msgs/msg/NoSuchType")


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # mcap_ros2.reader warns on import
def test_written_file_decodes_with_mcap_ros2(tmp_path):
    from geometry_msgs.msg import Twist
    from mapf_msgs.msg import AgentObservation
    from mcap.reader import make_reader
    from mcap_ros2.reader import read_ros2_messages
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message

    path = tmp_path / "log.mcap"
    with McapRos2Writer(path) as w:
        c_odom = w.add_channel("/robot_0/odom", "nav_msgs/msg/Odometry", [QosProfile(depth=10)])
        c_obs = w.add_channel("/robot_0/observation", "mapf_msgs/msg/AgentObservation")
        c_tw = w.add_channel("/robot_0/cmd_vel", "geometry_msgs/msg/Twist")
        assert w.add_channel("/robot_0/odom", "nav_msgs/Odometry") == c_odom
        with pytest.raises(ValueError, match="already recorded"):
            w.add_channel("/robot_0/odom", "geometry_msgs/msg/Twist")
        for k in range(5):
            odom = Odometry()
            odom.pose.pose.position.x = 0.1 * k
            odom.header.frame_id = "map"
            w.write(c_odom, serialize_message(odom), log_time_ns=1000 + k)
            obs = AgentObservation(step=k, robot_id=0, fov_size=3, fov=[float(k)] * 54)
            w.write(c_obs, serialize_message(obs), log_time_ns=1000 + k, publish_time_ns=900 + k)
            tw = Twist()
            tw.linear.x = 0.2
            w.write(c_tw, serialize_message(tw), log_time_ns=1000 + k)
        w.flush()
    w.close()  # twice is fine
    with pytest.raises(RuntimeError, match="closed"):
        w.write(c_odom, b"", 0)

    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
    assert header.profile == "ros2"
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    assert summary.statistics.message_count == 15

    got = {}
    for m in read_ros2_messages(str(path)):
        got.setdefault(m.channel.topic, []).append(m.ros_msg)
    assert [round(o.pose.pose.position.x, 3) for o in got["/robot_0/odom"]] == [0.0, 0.1, 0.2, 0.3, 0.4]
    assert got["/robot_0/odom"][0].header.frame_id == "map"
    assert [o.step for o in got["/robot_0/observation"]] == list(range(5))
    assert list(got["/robot_0/observation"][3].fov) == [3.0] * 54
    assert all(t.linear.x == pytest.approx(0.2) for t in got["/robot_0/cmd_vel"])


def test_bad_compression_is_refused(tmp_path):
    with pytest.raises(ValueError, match="compression"):
        McapRos2Writer(tmp_path / "x.mcap", compression="gzip")


def test_a_long_recording_keeps_nothing_in_memory_per_chunk_and_its_summary_indexes_every_chunk(tmp_path):
    import tracemalloc

    from mcap.reader import make_reader

    path = tmp_path / "long.mcap"
    w = McapRos2Writer(path, definition=lambda full: "int32 a\n")
    channels = [w.add_channel(f"/t{k}", "std_msgs/msg/Int32") for k in range(45)]  # a fleet's worth of topics

    def chunk(i):  # one message per topic, then a flush, as the recorder does every flush_period_s
        for c in channels:
            w.write(c, b"\x00\x01\x00\x00" + i.to_bytes(4, "little"), log_time_ns=i * 1000 + c)
        w.flush()

    for i in range(50):
        chunk(i)
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    for i in range(50, 1050):
        chunk(i)
    per_chunk = (tracemalloc.get_traced_memory()[0] - before) / 1000
    tracemalloc.stop()
    w.close()
    # The chunk indexes wait in a temporary file (SpilledChunkIndexes): in memory they were 0.6 KB a chunk.
    assert per_chunk < 16, f"{per_chunk:.0f} bytes kept per chunk"
    assert [p.name for p in tmp_path.iterdir()] == ["long.mcap"]  # the temporary file is gone
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        chunks = summary.chunk_indexes
        assert len(chunks) == 1050 and all(len(c.message_index_offsets) == 45 for c in chunks)
        got = [(m.channel_id, m.log_time) for _, _, m in reader.iter_messages(starting_at=500_000, ending_before=501_000)]
    assert got == [(c, 500_000 + c) for c in channels]  # the indexes still find messages by time
