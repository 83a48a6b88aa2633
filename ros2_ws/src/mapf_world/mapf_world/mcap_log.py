"""MCAP files the way rosbag2 writes them (no rclpy needed here).

- profile "ros2";
- one schema per message type, named "pkg/msg/Name", encoding "ros2msg", whose text is the complete
  definition: the type's own .msg text, then every nested type once (depth-first, sorted by name at
  each level), each after an empty line, a line of 80 '=' and a line "MSG: pkg/Name";
- one channel per topic, message encoding "cdr" (payloads from rclpy.serialization), with the
  metadata keys "offered_qos_profiles" and "topic_type_hash" (rosbag2_format.py);
- a metadata record "rosbag2" holding the bag metadata (version 9), once at the start and once
  more, with the message counts, when the file is closed;
- message sequence numbers count the messages of each channel from 0 (a gap-free record is 0..n-1).

The .msg files are found through the ament index (share/<pkg>/msg/<Name>.msg), so a type from any
package on AMENT_PREFIX_PATH works, including this project's mapf_msgs.
"""
from __future__ import annotations

import re
import tempfile
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from mcap.data_stream import RecordBuilder
from mcap.records import ChunkIndex
from mcap.writer import CompressionType, Writer

from mapf_world.rosbag2_format import (METADATA_KEY, METADATA_RECORD, QosProfile, TopicRecord, bag_metadata,
                                       offered_qos_profiles)

PRIMITIVES = frozenset("bool byte char float32 float64 int8 uint8 int16 uint16 int32 uint32 int64 uint64 "
                       "string wstring".split())
SEPARATOR = "=" * 80
MAX_NESTING = 50  # rosbag2 gives up at the same depth


def split_type_name(type_name: str) -> Tuple[str, str]:
    """'pkg/msg/Name' or 'pkg/Name' -> ('pkg', 'Name'); ValueError otherwise."""
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise ValueError(f"message type {type_name!r} is not of the form 'pkg/msg/Name' or 'pkg/Name'")


def msg_file(package: str, name: str) -> Path:
    """Path of share/<package>/msg/<name>.msg through the ament index."""
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    try:
        share = Path(get_package_share_directory(package))
    except PackageNotFoundError as exc:
        raise ValueError(f"message package {package!r} is not in the ament index (AMENT_PREFIX_PATH)") from exc
    path = share / "msg" / f"{name}.msg"
    if not path.is_file():
        raise ValueError(f"no definition file {path} for message type {package}/{name}")
    return path


def field_types(text: str, package: str) -> List[str]:
    """The non-primitive field types of a .msg text as 'pkg/Name', in order (constants skipped)."""
    found = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        tokens = line.split()
        if len(tokens) < 2:
            raise ValueError(f"cannot parse message definition line {raw!r} of package {package}")
        if "=" in tokens[1] or (len(tokens) > 2 and tokens[2].startswith("=")):
            continue  # a constant: always a primitive type
        base = re.sub(r"\[.*\]$", "", tokens[0])
        base = re.sub(r"<=\d+$", "", base)
        if base in PRIMITIVES:
            continue
        if base == "Header":
            found.append("std_msgs/Header")
        elif "/" in base:
            pkg, name = split_type_name(base)
            found.append(f"{pkg}/{name}")
        else:
            found.append(f"{package}/{base}")
    return found


def message_definition(type_name: str, read: Optional[Callable[[str, str], str]] = None) -> str:
    """Complete ros2msg definition text of type_name, as rosbag2 stores it in MCAP schemas.

    As rosbag2_storage_mcap builds it: the type's .msg text as in its file, then, for each nested
    type in sorted order (depth-first, each type once), a newline, a line of 80 '=', a line
    "MSG: pkg/Name" and that type's text built the same way.
    read(package, name) -> .msg text; defaults to the installed .msg files (ament index).
    """
    if read is None:
        def read(package: str, name: str) -> str:
            return msg_file(package, name).read_text()
    seen = set()

    def full_text(pkg: str, name: str, depth: int) -> str:
        if depth > MAX_NESTING:
            raise ValueError(f"message type {type_name} nests more than {MAX_NESTING} levels deep")
        text = read(pkg, name)
        for dep in sorted(set(field_types(text, pkg))):
            if dep in seen:
                continue
            seen.add(dep)
            text += f"\n{SEPARATOR}\nMSG: {dep}\n" + full_text(*split_type_name(dep), depth + 1)
        return text

    return full_text(*split_type_name(type_name), 0)


class SpilledChunkIndexes:
    """The MCAP writer's list of chunk indexes, kept in an unnamed temporary file until the summary.

    The writer keeps one ChunkIndex per chunk for the summary at the end of the file. A recorder writes a
    chunk every flush_period_s, so kept in memory they grow with the recording's length: as Python objects
    (a dict of the message index offset of every channel) about 4 KB per chunk, 14 MB an hour; as their
    serialised records about 0.6 KB per chunk, still 2 MB an hour (the soaks in docs/FLEET.md). Here each
    is appended to the file as its record, and read back once when the summary is written; nothing stays
    in memory per chunk. The file lies beside the MCAP file and disappears when closed (or the process dies).
    """

    def __init__(self, directory: Path):
        self._file = tempfile.TemporaryFile(dir=directory, prefix=".chunk_indexes.")
        self._count = 0

    def append(self, index: ChunkIndex) -> None:
        builder = RecordBuilder()
        index.write(builder)
        self._file.write(builder.end())
        self._count += 1

    def __len__(self) -> int:
        return self._count

    def __iter__(self):
        """One item whose write() copies every record, in order (what Writer.finish needs)."""
        self._file.flush()
        self._file.seek(0)
        yield _RawRecords(self._file.read())
        self._file.seek(0, 2)

    def close(self) -> None:
        self._file.close()


class _RawRecords:
    __slots__ = ("data",)

    def __init__(self, data: bytes):
        self.data = data

    def write(self, stream: RecordBuilder) -> None:
        stream.write(self.data)


class McapRos2Writer:
    """Append-only writer of ROS 2 CDR messages to one MCAP file (rosbag2-compatible layout)."""

    def __init__(self, path, chunk_size: int = 1 << 20, compression: str = "zstd",
                 definition: Callable[[str], str] = message_definition):
        self.path = Path(path)
        try:
            comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
        except KeyError:
            raise ValueError(f"compression must be 'zstd', 'lz4' or 'none', got {compression!r}") from None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._stream = open(self.path, "wb")
        self._writer = Writer(self._stream, chunk_size=chunk_size, compression=comp)
        # Profile "ros2" as rosbag2; the library field names the writer, as the MCAP spec intends.
        self._writer.start(profile="ros2", library="mapf_world.mcap_log")
        self._definition = definition
        self._schemas: Dict[str, int] = {}
        self._channels: Dict[str, Tuple[int, str]] = {}
        self._topics: Dict[int, TopicRecord] = {}   # channel id -> what the bag metadata says of it
        self._first_ns: Optional[int] = None
        self._last_ns = 0
        self.message_count = 0
        self.closed = False
        # The writer's list of chunk indexes (mcap 1.6.0, pinned), replaced by one kept on disk
        # (tests/unit/test_mcap_log.py checks that nothing stays in memory per chunk).
        if not isinstance(getattr(self._writer, "_Writer__chunk_indices", None), list):
            raise RuntimeError("mcap.writer.Writer no longer keeps its chunk indexes in _Writer__chunk_indices; "
                               "see SpilledChunkIndexes in mapf_world/mcap_log.py")
        self._chunk_indexes = SpilledChunkIndexes(self.path.parent)
        setattr(self._writer, "_Writer__chunk_indices", self._chunk_indexes)
        self._write_bag_metadata()
        self._writer.flush()  # header and bag metadata on disk at once: a killed recorder leaves a readable start

    def add_channel(self, topic: str, type_name: str, profiles: Sequence[QosProfile] = (),
                    type_hash: str = "") -> int:
        """Channel id of topic (registered once; the type must not change).

        profiles: the QoS offered by the topic's publishers; type_hash: the type's RIHS01 hash.
        """
        pkg, name = split_type_name(type_name)
        full = f"{pkg}/msg/{name}"
        if topic in self._channels:
            cid, known = self._channels[topic]
            if known != full:
                raise ValueError(f"topic {topic} already recorded as {known}, now offered as {full}")
            return cid
        if full not in self._schemas:
            text = self._definition(full)
            self._schemas[full] = self._writer.register_schema(name=full, encoding="ros2msg", data=text.encode())
        metadata = {"offered_qos_profiles": offered_qos_profiles(profiles), "topic_type_hash": type_hash}
        cid = self._writer.register_channel(topic=topic, message_encoding="cdr",
                                            schema_id=self._schemas[full], metadata=metadata)
        self._channels[topic] = (cid, full)
        self._topics[cid] = TopicRecord(topic, full, tuple(profiles), type_hash)
        return cid

    def write(self, channel_id: int, data: bytes, log_time_ns: int, publish_time_ns: Optional[int] = None) -> None:
        if self.closed:
            raise RuntimeError(f"{self.path} is closed")
        record = self._topics[channel_id]
        log_time_ns = int(log_time_ns)
        self._writer.add_message(channel_id=channel_id, log_time=log_time_ns, data=bytes(data),
                                 publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
                                 sequence=record.message_count)
        record.message_count += 1
        self.message_count += 1
        self._first_ns = log_time_ns if self._first_ns is None else min(self._first_ns, log_time_ns)
        self._last_ns = max(self._last_ns, log_time_ns)

    def _write_bag_metadata(self) -> None:
        start = self._first_ns or 0
        text = bag_metadata(self.path.name, list(self._topics.values()), start,
                            self._last_ns - start if self.message_count else 0, self.message_count)
        self._writer.add_metadata(METADATA_RECORD, {METADATA_KEY: text})

    def flush(self) -> None:
        """Write the chunk in progress to disk (a crash after this loses nothing written so far)."""
        if not self.closed:
            self._writer.flush()

    def close(self) -> None:
        """Finish the file (summary, indexes); safe to call twice."""
        if self.closed:
            return
        self.closed = True
        try:
            self._write_bag_metadata()
            self._writer.finish()
        finally:
            self._stream.close()
            self._chunk_indexes.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
