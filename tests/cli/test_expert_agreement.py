"""scripts/expert_agreement: agreement with the expert split by situation."""
from __future__ import annotations

import json
import subprocess

import numpy as np

import pytest

from mapf_policy.train.agreement import BESIDE, Setup, model_agreement, shared_agreement, situations, tally
from mapf_policy.train.demos import COMPARE_STREAM, generated_cases


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
    beside = _view(True, 0)
    beside[1, 3, 4] = 1  # on its goal, another agent right above it
    fov = np.stack([_view(True, 0), _view(True, 5), _view(False, 1), _view(False, 3), _view(False, 4), beside])
    masks = situations(fov)
    assert masks["on goal, 0-1 in view"].tolist() == [True, False, False, False, False, True]
    assert masks["on goal, 4+ in view"].tolist() == [False, True, False, False, False, False]
    assert masks["off goal, 0-1 in view"].tolist() == [False, False, True, False, False, False]
    assert masks["off goal, 2-3 in view"].tolist() == [False, False, False, True, False, False]
    assert masks["off goal, 4+ in view"].tolist() == [False, False, False, False, True, False]
    buckets = [m for name, m in masks.items() if name != BESIDE]
    assert np.sum(buckets, axis=0).tolist() == [1] * 6  # every row in one crowd bucket
    assert masks[BESIDE].tolist() == [False, False, False, False, False, True]  # the others stand far away
    q = np.eye(5)[[0, 0, 1, 2, 3, 4]]            # argmax: 0, 0, 1, 2, 3, 4
    expert = np.array([0, 1, 1, -1, 3, 0])       # row 3 unlabelled
    t = tally(q, expert, fov)
    assert t["all"] == {"rows": 5, "agree": 3, "label_moves": 3, "argmax_moves": 3}
    assert t["on goal, 4+ in view"] == {"rows": 1, "agree": 0, "label_moves": 1, "argmax_moves": 0}
    assert t["off goal, 2-3 in view"] == {"rows": 0, "agree": 0, "label_moves": 0, "argmax_moves": 0}
    assert t["off goal, 4+ in view"] == {"rows": 1, "agree": 1, "label_moves": 1, "argmax_moves": 1}
    assert t[BESIDE] == {"rows": 1, "agree": 0, "label_moves": 0, "argmax_moves": 1}


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
        assert sum(v["rows"] for k, v in t.items() if k not in ("all", BESIDE)) == t["all"]["rows"]
        assert all(0 <= v["agree"] <= v["rows"] for v in t.values())
    assert "off goal, 4+ in view" in run.stdout and "episodes solved" in run.stdout
    missing = subprocess.run([script, str(tmp_path / "nope.pt")], capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and "nope.pt" in missing.stderr


def test_a_second_design_model_is_refused_with_the_tool_that_serves_it(tmp_path):
    from mapf_policy.config import NetworkConfig
    from mapf_policy.model_io import save_model
    from mapf_policy.network import QNetwork
    from mapf_policy.train.agreement import load_forward
    cfg = NetworkConfig(dueling=True, goal_dirs=True, still_bins=4, still_count="revisit")
    path = save_model(tmp_path / "second.pt", QNetwork(cfg), cfg, {})
    with pytest.raises(ValueError, match="scripts/ladder .* --agreement"):
        load_forward(path)


def test_shared_states_score_every_model_on_the_reference_rows(tmp_path, two_random_models):
    ref, other = two_random_models
    cases = generated_cases(5, COMPARE_STREAM, [2, 3], 1, 10, 0.3)
    setup = Setup(expert_budget=5.0, max_steps=20)
    own = model_agreement(ref, cases, setup)
    shared, states = shared_agreement(ref, [ref, other], cases, setup)
    # The reference scored on its own states is exactly the own-states mode: same episodes, same rows.
    assert shared[ref]["tallies"] == own["tallies"]
    assert states == {"model": ref, "episodes": 2, "solved": own["solved"]}
    # Every model sees the same rows; only the agreement may differ.
    for name, t in shared[ref]["tallies"].items():
        assert shared[other]["tallies"][name]["rows"] == t["rows"]
    assert shared[other]["solved"] is None


def test_shared_states_refuse_a_different_field_of_view(tmp_path, two_random_models):
    from mapf_policy.config import NetworkConfig
    from mapf_policy.model_io import save_model
    from mapf_policy.network import QNetwork

    small = tmp_path / "fov11.pt"
    save_model(small, QNetwork(NetworkConfig(fov_size=11)), NetworkConfig(fov_size=11), {"step": 0})
    cases = generated_cases(5, COMPARE_STREAM, [2], 1, 10, 0.3)
    with pytest.raises(ValueError, match="11x11 field of view.*9x9"):
        shared_agreement(two_random_models[0], [str(small)], cases, Setup(expert_budget=5.0, max_steps=20))


def test_cli_states_from(repo_root, tmp_path, two_random_models):
    ref, other = two_random_models
    out = tmp_path / "shared.json"
    script = str(repo_root / "scripts" / "expert_agreement")
    run = subprocess.run([script, ref, other, "--states-from", ref, "--sizes", "2", "--cases", "1", "--map-size", "10",
                          "--max-steps", "20", "--json", str(out), "--no-progress"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    data = json.loads(out.read_text())
    assert data["states_from"]["model"] == ref and data["states_from"]["episodes"] == 1
    rows = {p: r["tallies"]["all"]["rows"] for p, r in data["results"].items()}
    assert set(rows) == {ref, other} and len(set(rows.values())) == 1 and rows[ref] > 0
    assert "States visited by" in run.stdout and "episodes solved" not in run.stdout
    missing = subprocess.run([script, ref, "--states-from", str(tmp_path / "none.pt")],
                             capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and "none.pt" in missing.stderr


def test_second_expert_labels_the_same_rows(two_random_models):
    ref = two_random_models[0]
    cases = generated_cases(5, COMPARE_STREAM, [3, 4], 1, 10, 0.3)
    first_only = model_agreement(ref, cases, Setup(expert_budget=5.0, max_steps=20))
    # The same bound twice: the planner is deterministic, so the two experts agree on every labelled row.
    same = model_agreement(ref, cases, Setup(expert_budget=10.0, max_steps=20, second_epsilon=10.0))
    assert same["tallies"] == first_only["tallies"]
    assert same["tallies_second"] == same["tallies"]
    assert same["experts"]["all"]["rows"] == same["tallies"]["all"]["rows"] > 0
    assert all(v["agree"] == v["rows"] for v in same["experts"].values())
    # Another bound labels exactly the same rows; the counts stay consistent.
    other = model_agreement(ref, cases, Setup(expert_budget=10.0, max_steps=20, second_epsilon=1.0))
    assert other["tallies_second"]["all"]["rows"] == other["tallies"]["all"]["rows"] == other["experts"]["all"]["rows"]
    assert all(0 <= v["agree"] <= v["rows"] for v in other["experts"].values())


def test_cli_second_epsilon(repo_root, tmp_path, two_random_models):
    ref = two_random_models[0]
    out = tmp_path / "second.json"
    script = str(repo_root / "scripts" / "expert_agreement")
    run = subprocess.run([script, ref, "--states-from", ref, "--second-epsilon", "1.5", "--sizes", "3", "--cases", "1",
                          "--map-size", "10", "--max-steps", "20", "--json", str(out), "--no-progress"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    data = json.loads(out.read_text())
    assert data["setup"]["second_epsilon"] == 1.5
    r = data["results"][ref]
    assert r["experts"]["all"]["rows"] == r["tallies_second"]["all"]["rows"] == r["tallies"]["all"]["rows"] > 0
    assert "vs eps 1.5" in run.stdout and "eps 10 vs eps 1.5" in run.stdout
    bad = subprocess.run([script, ref, "--second-epsilon", "0.5"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--second-epsilon must be >= 1" in bad.stderr


def test_cli_second_order(repo_root, tmp_path, two_random_models):
    ref = two_random_models[0]
    script = str(repo_root / "scripts" / "expert_agreement")
    tiny = ["--states-from", ref, "--sizes", "4", "--cases", "1", "--map-size", "10", "--max-steps", "20", "--no-progress"]
    for order in ("index", "reversed"):
        out = tmp_path / f"{order}.json"
        run = subprocess.run([script, ref, *tiny, "--second-order", order, "--json", str(out)],
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr[-2000:]
        data = json.loads(out.read_text())
        assert data["setup"]["second_order"] == order and data["setup"]["second_epsilon"] == 10.0
        r = data["results"][ref]
        assert r["experts"]["all"]["rows"] == r["tallies"]["all"]["rows"] > 0
        if order == "index":  # the same expert twice agrees with itself everywhere
            assert all(v["agree"] == v["rows"] for v in r["experts"].values())
        else:
            assert "eps 10 vs eps 10, reversed order" in run.stdout
    bad = subprocess.run([script, ref, "--second-order", "random"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "invalid choice" in bad.stderr
