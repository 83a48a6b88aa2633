"""Damaged MCAP logs: what a killed recorder leaves is read up to its last complete chunk, recovered into
a finalised copy, and scripts/replay never shows a traceback for a cut, corrupt or foreign file."""
import subprocess
from pathlib import Path

import numpy as np
import pytest

from mapf_world.fleet_replay import load_run, main as replay_main
from mapf_world.mcap_log import McapRos2Writer
from mapf_world.mcap_recover import recover, scan
from mapf_world.rosbag2_format import QosProfile

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

REPO = Path(__file__).resolve().parents[2]
STEPS = 12


def fleet_log(path: Path, crash_after: int | None = None) -> bytes | None:
    """A 2-robot fleet log, /map then one /fleet/status per step, a chunk per step (flushed as the
    recorder does). With crash_after=k: the bytes on disk right after step k's flush, while the
    writer goes on (what SIGKILL leaves, plus a chunk in progress that never reaches the disk)."""
    from mapf_msgs.msg import FleetStatus
    from nav_msgs.msg import OccupancyGrid
    from rclpy.serialization import serialize_message

    w = McapRos2Writer(path)
    c_map = w.add_channel("/map", "nav_msgs/msg/OccupancyGrid", [QosProfile(durability="transient_local")])
    c_status = w.add_channel("/fleet/status", "mapf_msgs/msg/FleetStatus", [QosProfile()])
    grid = OccupancyGrid()
    grid.info.width, grid.info.height, grid.info.resolution = 4, 1, 0.3
    grid.data = [0, 0, 0, 0]
    w.write(c_map, serialize_message(grid), 1_000)
    snapshot = None
    for step in range(STEPS + 1):
        col = min(step, 3)
        status = FleetStatus(instance="unit", state=1 if step < STEPS else 3, step=step, n_robots=1,
                             cell_size=0.3, positions=[0, col], goals=[0, 3], done=step == STEPS)
        w.write(c_status, serialize_message(status), 2_000 + step)
        w.flush()
        if step == crash_after:
            snapshot = path.read_bytes()
    w.close()
    return snapshot


def test_a_killed_recorder_s_file_reads_to_its_last_flushed_chunk_and_recovers(tmp_path):
    path = tmp_path / "killed.mcap"
    path.write_bytes(fleet_log(tmp_path / "full.mcap", crash_after=5))
    found = scan(path)
    assert not found.finalised and "breaks after 7 messages" in found.problem
    assert found.counts() == {"/map": 1, "/fleet/status": 6}
    copy = tmp_path / "killed.recovered.mcap"
    again = recover(path, copy)
    assert again.counts() == found.counts()
    # The copy is finalised: summary, indexes, and it opens in rosbags with every message.
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader
    with open(copy, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count == 7
    assert scan(copy).finalised and scan(copy).problem is None
    with AnyReader([copy]) as reader:
        steps = [reader.deserialize(raw, c.msgtype).step for c, _, raw in reader.messages() if c.topic == "/fleet/status"]
        (qos,) = next(c for c in reader.connections if c.topic == "/map").ext.offered_qos_profiles
    assert steps == list(range(6)) and qos.durability.name == "TRANSIENT_LOCAL"
    run = load_run(path)  # replay reads the killed file itself too, with a warning
    assert [s.step for s in run.statuses] == list(range(6))
    assert any("was not finalised or is damaged" in n for n in run.notes)


def test_replay_recover_writes_a_finalised_copy_and_replays_it(tmp_path, capsys):
    path = tmp_path / "cut.mcap"
    fleet_log(tmp_path / "full.mcap")
    data = (tmp_path / "full.mcap").read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])  # cut inside a chunk or the summary
    assert replay_main([str(path), "--recover", "--no-gif", "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "recovered" in err and "cut.recovered.mcap" in err
    copy = tmp_path / "out" / "cut.recovered.mcap"
    assert scan(copy).finalised and (tmp_path / "out" / "cut.recovered.png").is_file()




def _replay(path: Path):
    return subprocess.run([str(REPO / "scripts" / "replay"), str(path), "--no-gif"], capture_output=True,
                          text=True, timeout=120)


def test_replay_gives_a_clear_error_or_a_warning_never_a_traceback(tmp_path):
    good = tmp_path / "good.mcap"
    fleet_log(good)
    data = good.read_bytes()
    cases = {
        "empty.mcap": (b"", "the file is empty"),
        "text.mcap": (b"this is not a log\n" * 10, "not an MCAP file"),
        "magic_only.mcap": (data[:8], "no /map message"),
        "header_cut.mcap": (data[:40], "no /map message"),
    }
    for name, (content, expected) in cases.items():
        path = tmp_path / name
        path.write_bytes(content)
        proc = _replay(path)
        assert proc.returncode == 2, (name, proc.stdout, proc.stderr)
        assert "Traceback" not in proc.stderr and expected in proc.stderr and str(path) in proc.stderr, (name, proc.stderr)
    # A chunk in the middle corrupted (its compressed bytes flipped): the part before it, with a warning.
    found = scan(good)
    assert found.finalised
    from mcap.reader import make_reader
    with open(good, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    middle = chunks[len(chunks) // 2]
    end = middle.chunk_start_offset + middle.chunk_length
    corrupt = bytearray(data)
    for k in range(end - 12, end - 2):  # the end of the chunk's compressed data
        corrupt[k] ^= 0xFF
    path = tmp_path / "corrupt.mcap"
    path.write_bytes(bytes(corrupt))
    proc = _replay(path)
    assert "Traceback" not in proc.stderr
    assert proc.returncode == 0 and "was not finalised or is damaged" in proc.stderr, proc.stderr
    assert 0 < len(scan(path).messages) < len(found.messages)
    # No file at all.
    proc = _replay(tmp_path / "missing.mcap")
    assert proc.returncode == 2 and "does not exist" in proc.stderr and "Traceback" not in proc.stderr


def test_recover_refuses_to_overwrite_its_input(tmp_path):
    path = tmp_path / "a.mcap"
    fleet_log(path)
    with pytest.raises(ValueError, match="must not overwrite"):
        recover(path, path)
    assert np.all([m.log_time for m in scan(path).messages] == sorted(m.log_time for m in scan(path).messages))


def test_sequence_tracker_counts_gaps_and_publisher_restarts():
    from mapf_world.recorder_core import SequenceTracker
    t = SequenceTracker()
    t.track("/a")
    t.track("/b")
    for seq in (1, 2, 3, 6, 7):          # 4 and 5 never arrived
        t.received("/a", seq)
    for seq in (5, 6, 1, 2):             # joined late (from 5), then a restarted publisher numbers from 1
        t.received("/b", seq)
    t.received("/rosout", 3)             # not tracked: several publishers
    t.received("/a", None)               # a middleware without numbers: ignored
    assert (t.topics["/a"].published, t.topics["/a"].received, t.topics["/a"].lost) == (7, 5, 2)
    assert (t.topics["/b"].published, t.topics["/b"].lost, t.topics["/b"].writers) == (4, 0, 2)
    assert t.published == 11 and t.lost == 2
    assert t.report() == "11 published, 9 received, 2 lost on 2 single-publisher topics (most on /a 2)"
    t.untrack("/a")                      # a second publisher joined: its numbers would interleave
    t.received("/a", 20)
    assert "/a" not in t.topics and t.lost == 0


def test_recover_carries_an_older_log_whose_qos_lists_four_fields(tmp_path):
    from mcap.writer import Writer
    from std_msgs.msg import String
    from rclpy.serialization import serialize_message
    path = tmp_path / "old.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="old")
        sid = w.register_schema("std_msgs/msg/String", "ros2msg", b"string data\n")
        cid = w.register_channel("/chatter", "cdr", sid, {"offered_qos_profiles": "- history: unknown\n  depth: 0\n"})
        for k in range(3):
            w.add_message(cid, log_time=10 + k, data=serialize_message(String(data=str(k))), publish_time=10 + k)
        w.finish()
    found = recover(path, tmp_path / "old.recovered.mcap")
    assert len(found.messages) == 3 and "the copy lists none" in found.notes[0]
    copy = scan(tmp_path / "old.recovered.mcap")
    assert copy.finalised and [m.log_time for m in copy.messages] == [10, 11, 12]
