"""scripts/train end to end with a tiny budget: run, logs, checkpoint, model file, then a resume."""
from __future__ import annotations

import csv
import subprocess

import pytest

from mapf_policy.model_io import load_model

TINY = [
    "--total-steps", "20", "--map-size", "10", "--max-agents", "2", "--curriculum-start-agents", "2",
    "--expert", "shortest_path", "--demo-instances", "4", "--demo-shard-size", "2", "--batch-size", "16",
    "--learning-starts", "10", "--log-every", "5", "--eval-minutes", "0", "--no-progress",
    "--weights-sync-every", "5",  # unconsumed weights at exit must not hang the process
]


def _run(repo_root, tmp_path, *extra):
    cmd = [str(repo_root / "scripts" / "train"), *TINY, "--runs-dir", str(tmp_path / "runs"),
           "--cache-dir", str(tmp_path / "cache"), *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


def _steps(run_dir):
    with (run_dir / "train.csv").open() as f:
        return [int(r["step"]) for r in csv.DictReader(f)]


@pytest.mark.slow
def test_train_smoke_then_resume(repo_root, tmp_path):
    first = _run(repo_root, tmp_path)
    assert first.returncode == 0, first.stderr[-3000:]
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert run_dir.name == "hscl_m10_a1-2_shortest_path_s0"
    for name in ("config.json", "checkpoint.pt", "last.pt", "train.csv", "training.png", "demos.json"):
        assert (run_dir / name).is_file(), name
    assert _steps(run_dir) == [5, 10, 15, 20]
    net, cfg, meta = load_model(run_dir / "last.pt")
    assert meta["step"] == 20 and cfg.fov_size == 9
    assert any((tmp_path / "cache" / "demos").rglob("shard_*.npz"))

    second = _run(repo_root, tmp_path, "--total-steps", "30")  # same run, longer schedule: resumes
    assert second.returncode == 0, second.stderr[-3000:]
    assert _steps(run_dir) == [5, 10, 15, 20, 25, 30]
    assert load_model(run_dir / "last.pt")[2]["step"] == 30

    clash = _run(repo_root, tmp_path, "--lr", "0.5")
    assert clash.returncode == 2 and "lr" in clash.stderr


@pytest.mark.slow
def test_train_two_actors_no_demos_stops_at_session_limit(repo_root, tmp_path):
    """Several actor processes feed one learner; --session-minutes ends the session with a checkpoint."""
    run = _run(repo_root, tmp_path, "--actors", "2", "--demo-instances", "0", "--session-minutes", "0.3",
               "--max-replay-ratio", "4", "--total-steps", "1000000", "--run-name", "two")
    assert run.returncode == 0, run.stderr[-3000:]
    assert "session limit of 0.3 min reached" in run.stdout
    run_dir = tmp_path / "runs" / "two"
    step = load_model(run_dir / "last.pt")[2]["step"]
    assert 0 < step < 1_000_000 and _steps(run_dir)[-1] <= step
    with (run_dir / "train.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert int(rows[-1]["episodes"]) >= 2 and int(rows[-1]["demo_size"]) == 0


@pytest.mark.slow
def test_train_relabels_with_odrmstar_in_position_order(repo_root, tmp_path):
    """--expert-order position reaches the actors' ODrM* relabelling: every online sample gets a label."""
    run = _run(repo_root, tmp_path, "--expert", "odrmstar", "--expert-order", "position", "--demo-instances", "0",
               "--relabel-fraction", "1.0", "--max-agents", "4", "--curriculum-start-agents", "4", "--run-name", "pos")
    assert run.returncode == 0, run.stderr[-3000:]
    run_dir = tmp_path / "runs" / "pos"
    assert '"expert_order": "position"' in (run_dir / "config.json").read_text()
    with (run_dir / "train.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert rows and all(float(r["labelled_share"]) > 0.9 for r in rows)
    assert all(0.0 <= float(r["agreement"]) <= 1.0 for r in rows)
