"""scripts/expert_agreement: agreement with the expert split by situation."""
from __future__ import annotations

import json
import subprocess

import numpy as np

from mapf_policy.train.agreement import situations, tally


def _view(on_goal: bool, others: int) -> np.ndarray:
    fov = np.zeros((6, 9, 9), dtype=np.uint8)
    fov[1, 4, 4] = 1  # the agent itself
    cells = [(r, c) for r in range(9) for c in range(9) if (r, c) != (4, 4)][:others]
    for r, c in cells:
        fov[1, r, c] = 1
    if not on_goal:
        fov[2, 4, 4] = 1  # moving up gets closer
    return fov


def test_situations_and_tally_count_by_hand():
    fov = np.stack([_view(True, 0), _view(True, 5), _view(False, 1), _view(False, 3), _view(False, 4)])
    masks = situations(fov)
    assert masks["on goal, 0-1 in view"].tolist() == [True, False, False, False, False]
    assert masks["on goal, 4+ in view"].tolist() == [False, True, False, False, False]
    assert masks["off goal, 0-1 in view"].tolist() == [False, False, True, False, False]
    assert masks["off goal, 2-3 in view"].tolist() == [False, False, False, True, False]
    assert masks["off goal, 4+ in view"].tolist() == [False, False, False, False, True]
    assert np.sum([m for m in masks.values()], axis=0).tolist() == [1] * 5  # every row in one bucket
    q = np.eye(5)[[0, 0, 1, 2, 3]]               # argmax: 0, 0, 1, 2, 3
    expert = np.array([0, 1, 1, -1, 3])          # row 3 unlabelled
    t = tally(q, expert, fov)
    assert t["all"] == {"rows": 4, "agree": 3}
    assert t["on goal, 4+ in view"] == {"rows": 1, "agree": 0}
    assert t["off goal, 2-3 in view"] == {"rows": 0, "agree": 0}
    assert t["off goal, 4+ in view"] == {"rows": 1, "agree": 1}


def test_cli_reports_every_model_and_refuses_missing(repo_root, tmp_path, two_random_models):
    paths = two_random_models
    out = tmp_path / "agree.json"
    script = str(repo_root / "scripts" / "expert_agreement")
    run = subprocess.run([script, *paths, "--sizes", "2", "3", "--cases", "1", "--map-size", "10", "--max-steps", "20",
                          "--json", str(out), "--no-progress"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    data = json.loads(out.read_text())
    assert set(data["results"]) == set(paths)
    for r in data["results"].values():
        t = r["tallies"]
        assert t["all"]["rows"] > 0 and r["episodes"] == 2
        assert sum(v["rows"] for k, v in t.items() if k != "all") == t["all"]["rows"]
        assert all(0 <= v["agree"] <= v["rows"] for v in t.values())
    assert "off goal, 4+ in view" in run.stdout and "episodes solved" in run.stdout
    missing = subprocess.run([script, str(tmp_path / "nope.pt")], capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and "nope.pt" in missing.stderr
