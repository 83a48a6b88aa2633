"""Publisher history of the fleet's topics (mapf_world.fleet_qos): REPAIR_WINDOW_S of samples for the
reliable protocol to resend, never less than the default depth."""
from __future__ import annotations

import pytest

from mapf_world.fleet_qos import DEFAULT_DEPTH, REPAIR_WINDOW_S, history_depth


def test_history_depth_keeps_the_repair_window_of_samples():
    assert REPAIR_WINDOW_S == 5.0
    assert history_depth(100.0) == 500      # odometry and cmd_vel: rate_hz 10 x real_time_factor 10
    assert history_depth(20) == 100         # real time at 20 Hz
    assert history_depth(33.4) == 167       # a partial sample still counts
    assert history_depth(2.0) == DEFAULT_DEPTH == 10  # below 2 messages/s the default depth is more
    assert history_depth(5.0) == 25         # fleet/markers every 0.2 s
    assert history_depth(0.5) == DEFAULT_DEPTH


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), True, "100"])
def test_history_depth_rejects_a_rate_that_is_not_a_positive_number(bad):
    with pytest.raises(ValueError, match="publisher rate"):
        history_depth(bad)
