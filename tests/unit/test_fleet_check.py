"""scripts/check_fleet's comparison: equal trajectories, the first differing step and robots, lengths."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from mapf_world.fleet_check import compare, failed_answers


def test_compare_finds_the_first_differing_step_and_robots():
    a = np.zeros((5, 3, 2), dtype=np.int64)
    assert compare(a, a.copy()) is None
    b = a.copy()
    b[3, 1] = (1, 0)
    b[4, 2] = (0, 1)
    assert compare(a, b) == (3, [1])
    assert compare(a, a[:4]) == (4, [])


def test_failed_answers_reads_timeouts_and_refusals_from_the_status_outcomes():
    statuses = [SimpleNamespace(state=0, step=0, outcomes=[]),
                SimpleNamespace(state=1, step=1, outcomes=[0, 2, 0]),
                SimpleNamespace(state=1, step=2, outcomes=[3, 0, 1])]
    assert failed_answers(statuses) == [(0, 1, "timeout"), (1, 0, "rejected")]
