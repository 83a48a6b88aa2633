"""QoS of the fleet's publishers (docs/FLEET.md, "Where the guarantee ends").

Every fleet topic is reliable. A sample a subscriber missed (the recorder's process starved of CPU, a
full transport queue) is resent by the reliable protocol only while it is still in the publisher's
KEEP_LAST history. Publishers at tens of Hz or more (odometry and cmd_vel at rate_hz x real_time_factor,
fleet/markers) therefore keep REPAIR_WINDOW_S of their samples (history_depth), so a recorder starved
that long still receives every message; per-step topics (a step is an action round trip, a few per
second) keep DEFAULT_DEPTH, fleet/status STATUS_DEPTH, latched topics their last sample.
The recorder writes the QoS the graph reports for each publisher (recorder_node.offered_profile).
"""
from __future__ import annotations

import math

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

# Seconds of samples a high-rate publisher keeps for the reliable protocol to resend (see above).
REPAIR_WINDOW_S = 5.0
# History of the per-step topics (observation, action, cell_move), and the least any publisher keeps.
DEFAULT_DEPTH = 10
# History of fleet/status (one message per step and phase change).
STATUS_DEPTH = 100
# Latched topics (map, initialpose): the last sample, also for subscribers that join later.
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def history_depth(rate_hz: float) -> int:
    """KEEP_LAST depth of a publisher sending up to rate_hz messages per wall-clock second: the samples of
    REPAIR_WINDOW_S, at least DEFAULT_DEPTH."""
    if isinstance(rate_hz, bool) or not isinstance(rate_hz, (int, float)) or not math.isfinite(rate_hz) or rate_hz <= 0:
        raise ValueError(f"publisher rate must be a positive number of messages per second, got {rate_hz!r}")
    return max(DEFAULT_DEPTH, math.ceil(REPAIR_WINDOW_S * rate_hz - 1e-9))
