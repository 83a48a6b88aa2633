"""Recorder: every fleet topic to one MCAP file, the way rosbag2 does (see mcap_log.py).

Topics are discovered on the live graph (like `ros2 bag record -a`, or only the names listed in the
`topics` parameter) and subscribed as raw CDR once a publisher exists, with a QoS that matches the
publishers (transient local for latched topics such as /map) and keeps every sample (recorder_qos).
The chunk in progress is written every `flush_period_s`, so a killed recorder's file is readable up
to it (mcap_recover.py); on SIGINT or SIGTERM the writer is closed in `finally` and the file finalised.
On close it prints its loss account from the writers' sequence numbers (recorder_core.py).
"""
from __future__ import annotations

import importlib
import re
import sys
import time
from pathlib import Path

import rclpy
from rclpy.node import Node
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from mapf_world.mcap_log import McapRos2Writer
from mapf_world.recorder_core import SequenceTracker
from mapf_world.rosbag2_format import QosProfile
from mapf_world.node_main import run_node


def message_class(type_name: str):
    """'pkg/msg/Name' -> the generated Python class; ValueError when it cannot be imported."""
    try:
        pkg, kind, name = type_name.split("/")
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    except (ValueError, ImportError, AttributeError) as exc:
        raise ValueError(f"cannot import message type {type_name!r}: {exc}") from exc


def recorder_qos(publishers) -> QoSProfile:
    """The recorder's subscription QoS: compatible with every publisher, and keeps every sample.

    Reliability and durability follow rosbag2's adaptation rule (reliable / transient local only
    when every publisher offers it, otherwise a reliable publisher would refuse a best-effort
    request or vice versa). History is KEEP_ALL, unlike rosbag2's default keep-last: the reader
    never drops a received sample to make room, so with reliable publishers a recorder that falls
    behind slows the acknowledgements instead of losing messages (docs/FLEET.md, "MCAP logs").
    """
    profiles = [p.qos_profile for p in publishers]
    reliable = all(q.reliability == ReliabilityPolicy.RELIABLE for q in profiles)
    latched = all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in profiles)
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=0,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def offered_profile(qos: QoSProfile) -> QosProfile:
    """An rclpy QoS profile (as graph queries report it) in rosbag2's terms."""
    return QosProfile(history=qos.history.name.lower(), depth=int(qos.depth),
                      reliability=qos.reliability.name.lower(), durability=qos.durability.name.lower(),
                      deadline_ns=qos.deadline.nanoseconds, lifespan_ns=qos.lifespan.nanoseconds,
                      liveliness=qos.liveliness.name.lower(),
                      liveliness_lease_duration_ns=qos.liveliness_lease_duration.nanoseconds,
                      avoid_ros_namespace_conventions=bool(qos.avoid_ros_namespace_conventions))


# Seconds a subscription may match no publisher, while the graph shows some, before it is made anew.
UNMATCHED_S = 2.0


class Recorder(Node):
    def __init__(self):
        super().__init__("recorder")
        self.declare_parameter("output", "fleet.mcap")
        self.declare_parameter("topics", [""])           # [""] or []: every topic on the graph
        self.declare_parameter("exclude_regex", r"^/parameter_events$")
        self.declare_parameter("discovery_period_s", 0.25)
        self.declare_parameter("flush_period_s", 1.0)
        self.declare_parameter("compression", "zstd")
        output = str(self.get_parameter("output").value)
        self._only = {t for t in self.get_parameter("topics").value if t}
        try:
            self._exclude = re.compile(self.get_parameter("exclude_regex").value)
        except re.error as exc:
            raise ValueError(f"parameter exclude_regex is not a valid regular expression: {exc}") from exc
        discovery = float(self.get_parameter("discovery_period_s").value)
        flush = float(self.get_parameter("flush_period_s").value)
        if not output:
            raise ValueError("parameter output must name the MCAP file to write")
        if not (discovery > 0 and flush > 0):
            raise ValueError(f"discovery_period_s and flush_period_s must be > 0, got {discovery}, {flush}")
        self.writer = McapRos2Writer(Path(output), compression=str(self.get_parameter("compression").value))
        self._subs = {}
        self._channels = {}   # topic -> MCAP channel id (kept when a subscription is made anew)
        self._matched = {}    # topic -> publishers matched by its subscription (the middleware's matched event)
        self._waiting = {}    # topic -> since when the graph shows publishers its subscription has not matched
        self._refused = set()
        self.sequences = SequenceTracker()
        self.create_timer(discovery, self._discover)
        self.create_timer(flush, self.writer.flush)
        self.get_logger().info(f"recording to {self.writer.path} "
                               f"({'topics ' + ', '.join(sorted(self._only)) if self._only else 'every topic'})")
        self._discover()

    def _resubscribe_unmatched(self) -> None:
        """A subscription that has matched no publisher for UNMATCHED_S while the graph shows publishers of its
        topic is made anew (into the same channel). Seen once in a fresh-clone test run: a robot's odom and
        cmd_vel were subscribed to and never delivered one message, while every other topic was recorded."""
        now = time.monotonic()
        for topic in list(self._subs):
            publishers = self.count_publishers(topic)
            if publishers > 1:
                self.sequences.untrack(topic)  # several numberings interleave from now on: no loss account
            if self._matched.get(topic, 0) > 0 or publishers == 0:
                self._waiting.pop(topic, None)
                continue
            since = self._waiting.setdefault(topic, now)
            if now - since < UNMATCHED_S:
                continue
            self.get_logger().warning(f"{topic}: no publisher matched in {UNMATCHED_S:g} s although the graph "
                                      f"shows {publishers}; subscribing again")
            self._waiting.pop(topic)
            self.destroy_subscription(self._subs.pop(topic))

    def _discover(self) -> None:
        self._resubscribe_unmatched()
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subs or topic in self._refused or self._exclude.search(topic):
                continue
            if self._only and topic not in self._only:
                continue
            publishers = self.get_publishers_info_by_topic(topic)
            if not publishers:
                continue  # only subscribers so far: the publisher's QoS is not known yet
            if len(types) != 1:
                self.get_logger().error(f"topic {topic} has several types {types}; not recorded")
                self._refused.add(topic)
                continue
            try:
                cls = message_class(types[0])
                if topic not in self._channels:
                    self._channels[topic] = self.writer.add_channel(
                        topic, types[0], [offered_profile(p.qos_profile) for p in publishers],
                        type_hash=str(getattr(publishers[0], "topic_type_hash", "") or ""))
                    if len(publishers) == 1:
                        self.sequences.track(topic)
            except ValueError as exc:
                self.get_logger().error(f"topic {topic} not recorded: {exc}")
                self._refused.add(topic)
                continue
            cid = self._channels[topic]

            def on_message(data, info, cid=cid, topic=topic):
                self.writer.write(cid, data, log_time_ns=time.time_ns(),
                                  publish_time_ns=info.get("source_timestamp") or None)
                self.sequences.received(topic, info.get("publication_sequence_number"))

            def on_matched(status, topic=topic):
                self._matched[topic] = status.current_count

            self._matched[topic] = 0
            self._subs[topic] = self.create_subscription(
                cls, topic, on_message, recorder_qos(publishers), raw=True,
                event_callbacks=SubscriptionEventCallbacks(matched=on_matched))
            self.get_logger().info(f"recording {topic} [{types[0]}]")

    def close(self) -> None:
        self.writer.close()
        # print, not the ROS logger: after SIGINT the context (and /rosout) is already shut down.
        print(f"[recorder] wrote {self.writer.message_count} messages on {len(self._subs)} topics "
              f"to {self.writer.path}; sequence numbers: {self.sequences.report()}", file=sys.stderr, flush=True)


def main(args=None):
    run_node("recorder", Recorder, args, close_method="close")


if __name__ == "__main__":
    main()
