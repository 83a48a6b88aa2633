"""The soak's RSS series (mapf_world.fleet_soak.RssSeries), with a fake clock and fake processes."""
from __future__ import annotations

import pytest

from mapf_world.fleet_soak import RssSeries, SoakConfig, main


def test_rss_series_writes_a_header_then_one_line_per_period(tmp_path):
    now = [100.0]
    series = RssSeries(tmp_path / "rss_kb.tsv", ["recorder", "drive_0"], 60.0, clock=lambda: now[0])
    rss = {"recorder": 98.5, "drive_0": None}     # MiB; drive_0 not running
    assert series.sample(rss.get, 0, 0)           # the first call always writes
    now[0] = 159.0
    assert not series.sample(rss.get, 50, 2)      # within the period: nothing
    now[0] = 160.0
    rss["drive_0"] = 82.0
    assert series.sample(rss.get, 96, 4)
    now[0] = 170.0
    assert series.sample(rss.get, 100, 5, force=True)  # the last sample, at the end
    lines = [line.split("\t") for line in (tmp_path / "rss_kb.tsv").read_text().splitlines()]
    assert lines == [["t_s", "steps", "episodes", "recorder", "drive_0"],
                     ["0", "0", "0", "100864", "-"],
                     ["60", "96", "4", "100864", "83968"],
                     ["70", "100", "5", "100864", "83968"]]


def test_rss_series_period_must_be_positive(tmp_path):
    with pytest.raises(ValueError, match="period"):
        RssSeries(tmp_path / "x.tsv", ["recorder"], 0.0)
    assert SoakConfig().rss_period_s == 60.0
    with pytest.raises(SystemExit):
        main(["--rss-period-s", "0", "--out", str(tmp_path / "soak")])
