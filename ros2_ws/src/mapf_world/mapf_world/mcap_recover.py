"""Read what a damaged MCAP log still holds, and write it again as a finalised file (no rclpy needed).

A recorder killed with SIGKILL (or a file cut short) leaves no summary: everything up to its last
complete chunk is intact, because the recorder writes whole chunks (every `flush_period_s`) and a
chunk's records come out all together or not at all. `scan` reads the file record by record with
CRC checks and stops at the first record it cannot read; `recover` writes the part read to a new,
finalised file (summary, indexes, the rosbag2 metadata record), which every MCAP and rosbag2 reader
opens. Bad input gives a ValueError naming the file and what is wrong.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclass
class Scan:
    """What `scan` found: schemas and channels by id, messages in file order, and how the file ended."""
    path: Path
    schemas: Dict[int, object] = field(default_factory=dict)
    channels: Dict[int, object] = field(default_factory=dict)
    messages: List[object] = field(default_factory=list)
    finalised: bool = False          # the file ends with a summary and the closing magic
    problem: Optional[str] = None    # why reading stopped early (None: the whole file was read)
    notes: List[str] = field(default_factory=list)  # what recover could not carry over

    def counts(self) -> Dict[str, int]:
        out: Dict[str, int] = {}
        for m in self.messages:
            topic = self.channels[m.channel_id].topic
            out[topic] = out.get(topic, 0) + 1
        return out


def check_magic(path: Path) -> None:
    """ValueError unless path is a file that starts like an MCAP file."""
    if not path.is_file():
        raise ValueError(f"{path} does not exist")
    with open(path, "rb") as f:
        head = f.read(len(MCAP_MAGIC))
    if not head:
        raise ValueError(f"{path}: the file is empty")
    if head != MCAP_MAGIC[:len(head)] or len(head) < len(MCAP_MAGIC):
        raise ValueError(f"{path}: not an MCAP file (it does not start with the MCAP magic bytes)")


def scan(path) -> Scan:
    """Every record that can be read, in file order, up to the first broken one."""
    from mcap.records import Channel, DataEnd, Footer, Message, Schema
    from mcap.stream_reader import StreamReader

    path = Path(path)
    check_magic(path)
    out = Scan(path)
    seen_footer = False
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, Schema):
                    out.schemas[record.id] = record
                elif isinstance(record, Channel):
                    out.channels[record.id] = record
                elif isinstance(record, Message):
                    if record.channel_id not in out.channels:
                        raise ValueError(f"message on unknown channel {record.channel_id}")
                    out.messages.append(record)
                elif isinstance(record, (DataEnd, Footer)):
                    seen_footer = seen_footer or isinstance(record, Footer)
        except Exception as exc:  # the stream reader raises many types for a cut or damaged file
            out.problem = (f"the file breaks after {len(out.messages)} messages "
                           f"({type(exc).__name__}: {exc or 'unexpected end of file'})")
    out.finalised = seen_footer and out.problem is None
    return out


def recover(path, out_path) -> Scan:
    """Write the readable part of `path` to `out_path` as a finalised MCAP file; the Scan of `path`.

    Schemas keep their text and channels their QoS and type hash; messages keep their log and
    publish times, in file order.
    """
    import yaml

    from mapf_world.mcap_log import McapRos2Writer
    from mapf_world.rosbag2_format import QosProfile

    result = scan(path)
    out_path = Path(out_path)
    if out_path.resolve() == Path(path).resolve():
        raise ValueError(f"{out_path}: the recovered copy must not overwrite the damaged file")
    texts = {s.name: s.data.decode() for s in result.schemas.values()}
    ids = {}
    with McapRos2Writer(out_path, definition=lambda full: texts[full]) as writer:
        for cid, channel in result.channels.items():
            schema = result.schemas.get(channel.schema_id)
            if schema is None:
                raise ValueError(f"{path}: channel {channel.topic} names schema {channel.schema_id}, "
                                 f"which the file does not hold")
            try:
                listed = yaml.safe_load(channel.metadata.get("offered_qos_profiles", "")) or []
                profiles = [QosProfile.from_dict(p) for p in listed]
            except (yaml.YAMLError, TypeError, KeyError, ValueError, AttributeError) as exc:
                # A log of an older recorder (four QoS fields only): the copy says nothing rather than guess.
                profiles = []
                result.notes.append(f"{channel.topic}: offered_qos_profiles not readable as rosbag2's "
                                    f"({type(exc).__name__}: {exc}); the copy lists none")
            ids[cid] = writer.add_channel(channel.topic, schema.name, profiles,
                                          channel.metadata.get("topic_type_hash", ""))
        for m in result.messages:
            writer.write(ids[m.channel_id], m.data, m.log_time, m.publish_time)
    return result
