"""rosbag2 (Jazzy) metadata text, as its MCAP storage plugin writes it (no rclpy needed here).

Facts this module reproduces (rosbag2 Jazzy: rosbag2_storage qos.cpp and yaml.hpp, rosbag2_storage_mcap):
- a channel's metadata has two keys: "offered_qos_profiles", the YAML block sequence of the
  publishers' QoS profiles, and "topic_type_hash" (the type's RIHS01 hash, "" when unknown);
- a profile lists every field in rmw order: history, depth, reliability, durability, deadline,
  lifespan, liveliness, liveliness_lease_duration, avoid_ros_namespace_conventions. Enums are the
  rmw names (metadata version 9: "keep_last", "reliable", "transient_local", "automatic", ...;
  "unknown" for an unknown value), durations are maps {sec, nsec}, and infinity is rmw's
  RMW_DURATION_INFINITE {sec: 9223372036, nsec: 854775807}, i.e. INT64_MAX nanoseconds split;
- the bag's own metadata (the metadata.yaml of a bag directory, version 9) is stored in an MCAP
  metadata record named "rosbag2" under the key "serialized_metadata". rosbag2 writes one when
  the file is opened and one before it is closed; readers take the last. Without it rosbag2 reads
  the QoS enums as version-8 integers, so it is what makes the string enums readable there.

One deliberate difference: rosbag2's recorder lists one profile per publisher, so /rosout with
eight nodes lists the same profile eight times; here identical profiles are listed once (playback
adapts its offer from the distinct profiles alone, so nothing is lost).
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from typing import Dict, List, Sequence

METADATA_VERSION = 9
METADATA_RECORD = "rosbag2"
METADATA_KEY = "serialized_metadata"
ROS_DISTRO = "jazzy"
INFINITE_NS = (1 << 63) - 1  # rclpy's infinite Duration; rmw writes it as {9223372036, 854775807}

HISTORY = ("system_default", "keep_last", "keep_all", "unknown")
RELIABILITY = ("system_default", "reliable", "best_effort", "unknown", "best_available")
DURABILITY = ("system_default", "transient_local", "volatile", "unknown", "best_available")
LIVELINESS = ("system_default", "automatic", "manual_by_topic", "unknown", "best_available")


@dataclass(frozen=True)
class QosProfile:
    """One offered QoS profile, enums as rmw names, durations in nanoseconds (INFINITE_NS = infinite)."""
    history: str = "unknown"
    depth: int = 0
    reliability: str = "reliable"
    durability: str = "volatile"
    deadline_ns: int = INFINITE_NS
    lifespan_ns: int = INFINITE_NS
    liveliness: str = "automatic"
    liveliness_lease_duration_ns: int = INFINITE_NS
    avoid_ros_namespace_conventions: bool = False

    def __post_init__(self):
        for name, allowed in (("history", HISTORY), ("reliability", RELIABILITY), ("durability", DURABILITY),
                              ("liveliness", LIVELINESS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"QoS {name} {getattr(self, name)!r} is not one of {', '.join(allowed)}")
        for name in ("depth", "deadline_ns", "lifespan_ns", "liveliness_lease_duration_ns"):
            if not 0 <= getattr(self, name) <= INFINITE_NS:
                raise ValueError(f"QoS {name} must be in 0..{INFINITE_NS}, got {getattr(self, name)}")

    @classmethod
    def from_dict(cls, d: dict) -> "QosProfile":
        """Inverse of as_dict (a profile read back from a log); KeyError/TypeError on a missing field."""
        def ns(t):
            return int(t["sec"]) * 1_000_000_000 + int(t["nsec"])
        return cls(history=str(d["history"]), depth=int(d["depth"]), reliability=str(d["reliability"]),
                   durability=str(d["durability"]), deadline_ns=ns(d["deadline"]), lifespan_ns=ns(d["lifespan"]),
                   liveliness=str(d["liveliness"]), liveliness_lease_duration_ns=ns(d["liveliness_lease_duration"]),
                   avoid_ros_namespace_conventions=bool(d["avoid_ros_namespace_conventions"]))

    def as_dict(self) -> dict:
        """The profile as rosbag2 serialises it (key order matters for byte-exact output)."""
        return {
            "history": self.history,
            "depth": self.depth,
            "reliability": self.reliability,
            "durability": self.durability,
            "deadline": duration(self.deadline_ns),
            "lifespan": duration(self.lifespan_ns),
            "liveliness": self.liveliness,
            "liveliness_lease_duration": duration(self.liveliness_lease_duration_ns),
            "avoid_ros_namespace_conventions": self.avoid_ros_namespace_conventions,
        }


def duration(ns: int) -> Dict[str, int]:
    """Nanoseconds as rmw_time_t {sec, nsec}; INT64_MAX ns gives RMW_DURATION_INFINITE exactly."""
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def distinct(profiles: Sequence[QosProfile]) -> List[QosProfile]:
    """Profiles in first-seen order, each once."""
    return list(dict.fromkeys(profiles))


# --- a small YAML emitter in yaml-cpp's block style (YAML::Dump) -------------------------------
_PLAIN = re.compile(r"^[A-Za-z0-9_/.][A-Za-z0-9_/.\- ]*$")


def _scalar(value) -> str:
    if value is None:
        return "~"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        # Plain when unambiguous, else double-quoted (JSON strings are valid YAML double-quoted scalars).
        plain = (_PLAIN.match(value) and not value.endswith(" ") and value.lower() not in
                 ("true", "false", "yes", "no", "on", "off", "null", "~") and not _looks_numeric(value))
        return value if plain else json.dumps(value)
    raise TypeError(f"cannot write {type(value).__name__} as YAML")


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def _lines(value, indent: int) -> List[str]:
    pad = " " * indent
    if isinstance(value, dict):
        if not value:
            return [pad + "{}"]
        out = []
        for key, item in value.items():
            if isinstance(item, (dict, list)) and item:
                out.append(f"{pad}{key}:")
                out += _lines(item, indent + 2)
            else:
                out.append(f"{pad}{key}: {_inline(item)}")
        return out
    if isinstance(value, list):
        if not value:
            return [pad + "[]"]
        out = []
        for item in value:
            if isinstance(item, (dict, list)) and item:
                inner = _lines(item, indent + 2)
                out.append(pad + "- " + inner[0][indent + 2:])
                out += inner[1:]
            else:
                out.append(f"{pad}- {_inline(item)}")
        return out
    return [pad + _scalar(value)]


def _inline(item) -> str:
    if isinstance(item, dict):
        return "{}"
    if isinstance(item, list):
        return "[]"
    return _scalar(item)


def dump_yaml(value) -> str:
    """Block-style YAML of dicts, lists and scalars, without a final newline (as YAML::Dump)."""
    return "\n".join(_lines(value, 0))


# --- the two texts rosbag2 stores -------------------------------------------------------------
def offered_qos_profiles(profiles: Sequence[QosProfile]) -> str:
    """Channel metadata "offered_qos_profiles": the distinct profiles as a YAML sequence."""
    return dump_yaml([p.as_dict() for p in distinct(profiles)])


@dataclass
class TopicRecord:
    """What the bag metadata says about one topic."""
    name: str
    type: str
    profiles: Sequence[QosProfile]
    type_hash: str = ""
    message_count: int = 0


def bag_metadata(file_name: str, topics: Sequence[TopicRecord], starting_time_ns: int, duration_ns: int,
                 message_count: int) -> str:
    """The "serialized_metadata" YAML of the "rosbag2" metadata record (rosbag2 BagMetadata, version 9)."""
    topic_entries = [{
        "topic_metadata": {
            "name": t.name,
            "type": t.type,
            "serialization_format": "cdr",
            "offered_qos_profiles": [p.as_dict() for p in distinct(t.profiles)],
            "type_description_hash": t.type_hash,
        },
        "message_count": t.message_count,
    } for t in topics]
    meta = {
        "version": METADATA_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": int(duration_ns)},
        "starting_time": {"nanoseconds_since_epoch": int(starting_time_ns)},
        "message_count": int(message_count),
        "topics_with_message_count": topic_entries,
        # rosbag2's own compression is off; MCAP chunks carry their compression themselves.
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [file_name],
        "files": [{"path": file_name, "starting_time": {"nanoseconds_since_epoch": int(starting_time_ns)},
                   "duration": {"nanoseconds": int(duration_ns)}, "message_count": int(message_count)}],
        "custom_data": None,
        "ros_distro": ROS_DISTRO,
    }
    return dump_yaml(meta)
