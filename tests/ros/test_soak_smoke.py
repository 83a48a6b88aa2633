"""scripts/bench_soak on a tiny budget: episodes back to back, the report's figures are filled and agree."""
from __future__ import annotations

import json
import subprocess

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_bench_soak_runs_episodes_back_to_back_and_accounts_for_every_message(repo_root, tmp_path):
    out = tmp_path / "soak"
    proc = subprocess.run([str(repo_root / "scripts" / "bench_soak"), "--robots", "2", "--size", "8", "--steps", "30",
                           "--warmup-steps", "5", "--episode-steps", "12", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    report = json.loads((out / "soak.json").read_text())
    totals, messages = report["totals"], report["messages"]
    assert totals["steps"] >= 30 and totals["episodes"] >= 3 and totals["aborted"] == 0
    assert sum(e["steps"] for e in report["episodes"]) == totals["steps"]
    assert messages["lost"] == 0 and messages["published"] == messages["received"] > 0
    assert messages["recorder_wrote"] == messages["in_file"] >= messages["received"]
    assert report["crashes"] == [] and report["stopped_early"] is None
    assert set(report["usage"]) == {"recorder", "policy_0", "policy_1", "drive_0", "drive_1", "world"}
    for name, u in report["usage"].items():
        assert u["rss_start_mb"] > 0 and u["rss_end_mb"] > 0, name
    assert "crashes: none" in proc.stdout
    # The RSS series: a header, the first sample and the last (taken when the soak ends).
    rows = [line.split("\t") for line in (out / "rss_kb.tsv").read_text().splitlines()]
    assert rows[0][:4] == ["t_s", "steps", "episodes", "recorder"] and len(rows) >= 3
    assert rows[-1][1] == str(totals["steps"]) and all(v != "-" for v in rows[-1][3:])
