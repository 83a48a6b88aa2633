"""scripts/blocker_labels: the expert's labels at a model's pushed blockers, with a tiny budget."""
from __future__ import annotations

import json
import subprocess

from mapf_policy.train.blocker_labels import KINDS, summarize


def test_summarize_reads_each_states_label_mode_and_the_models_choice():
    states = [{"labels": {1: 5}, "argmax": 0}, {"labels": {0: 3, 2: 1}, "argmax": 0},
              {"labels": {-1: 4}, "argmax": 0}, {"labels": {1: 2, 3: 2}, "argmax": 1}]
    assert summarize(states) == {"mode move": 2, "mode stay": 1, "no usable label": 1, "one move direction": 2,
                                 "no or several move directions": 1, "argmax is the mode": 2}


def test_blocker_labels_counts_every_blocker_row_once(repo_root, tmp_path):
    # A trained imitation model (committed, with the heading channel) deadlocks often enough at 8 agents on 10x10.
    model = repo_root / "models" / "training" / "r63_ce_heading_dagger_s1" / "last.pt"
    out = subprocess.run([str(repo_root / "scripts" / "blocker_labels"), str(model), "--episodes", "6", "--agents", "8",
                          "--size", "10", "--expert", "shortest_path", "--json", str(tmp_path / "b.json"), "--no-progress"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads((tmp_path / "b.json").read_text())
    assert set(res["rows"]) == set(KINDS) and res["episodes"] == 6 and 0 <= res["solved"] <= 6
    assert sum(res["rows"].values()) > 0 and res["states"]
    assert sum(res["rows"].values()) == sum(s["rows"] for s in res["states"])  # each row in one kind and one state
    for s in res["states"]:
        assert abs(sum(s["p"]) - 1) < 0.01 and s["rows"] == sum(s["labels"].values())
    assert "pushed blockers' rows" in out.stdout
    missing = subprocess.run([str(repo_root / "scripts" / "blocker_labels"), str(tmp_path / "nope.pt")],
                             capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and "nope.pt" in missing.stderr
