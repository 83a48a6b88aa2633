"""scripts/bench_inference and scripts/bench_learner: tiny runs print a figure for every way asked for."""
from __future__ import annotations

import re
import subprocess


def _run(repo_root, *args) -> subprocess.CompletedProcess:
    return subprocess.run([str(repo_root / "scripts" / args[0]), *args[1:]], capture_output=True, text=True,
                          timeout=300, cwd=repo_root)


def test_bench_inference_times_every_forward_and_batch(repo_root):
    proc = _run(repo_root, "bench_inference", "--forward", "fast", "im2col", "winograd", "reference",
                "--batches", "1", "9", "--repeats", "4", "--rounds", "2")
    assert proc.returncode == 0, proc.stderr
    rows = re.findall(r"batch +(\d+), (\w+) +forward: median ([\d.]+) ms", proc.stdout)
    assert {(b, f) for b, f, _ in rows} == {(b, f) for b in ("1", "9") for f in ("fast", "im2col", "winograd", "reference")}
    assert all(float(ms) > 0 for _, _, ms in rows)


def test_bench_inference_refuses_fewer_repeats_than_rounds(repo_root):
    proc = _run(repo_root, "bench_inference", "--repeats", "2", "--rounds", "3")
    assert proc.returncode != 0 and "--repeats (2) must be at least --rounds (3)" in proc.stderr


def test_bench_learner_times_both_ways(repo_root):
    proc = _run(repo_root, "bench_learner", "--batch-size", "16", "--steps", "2", "--rounds", "1", "--agents", "4")
    assert proc.returncode == 0, proc.stderr
    rows = re.findall(r"(fast|reference) +forward: median ([\d.]+) ms per gradient step", proc.stdout)
    assert sorted(name for name, _ in rows) == ["fast", "reference"]
    assert all(float(ms) > 0 for _, ms in rows)


def test_bench_bf16_times_both_precisions_for_both_forwards(repo_root):
    proc = _run(repo_root, "bench_bf16", "--batches", "4", "--steps", "1", "--rounds", "1")
    assert proc.returncode == 0, proc.stderr
    rows = re.findall(r"\| 4 \| (QNetwork.forward|FastForward) \| ([\d.]+) \| ([\d.]+) \| ([\d.]+)x \|", proc.stdout)
    assert sorted(r[0] for r in rows) == ["FastForward", "QNetwork.forward"]
    assert all(float(a) > 0 and float(b) > 0 for _, a, b, _ in rows)
    bad = _run(repo_root, "bench_bf16", "--steps", "0")
    assert bad.returncode != 0 and "must be >= 1" in bad.stderr


def test_bench_mining_times_both_ways_of_mining(repo_root, tmp_path):
    import torch

    from mapf_policy.config import NetworkConfig
    from mapf_policy.model_io import save_model
    from mapf_policy.network import QNetwork

    torch.manual_seed(0)
    cfg = NetworkConfig(dueling=True, heading=True)
    save_model(tmp_path / "m.pt", QNetwork(cfg), cfg, {"last_action": "executed"})
    proc = _run(repo_root, "bench_mining", str(tmp_path / "m.pt"), "--size", "8", "--episodes", "8", "--batch", "4",
                "--horizon", "4")
    assert proc.returncode == 0, proc.stderr
    rows = re.findall(r"(one by one|lockstep screen) +([\d.]+) s .* played with the search: +(\d+) +labels: (\d+) +"
                      r"solved with them: (\d+)", proc.stdout)
    assert [r[0] for r in rows] == ["one by one", "lockstep screen"]
    assert int(rows[0][2]) == 8 and int(rows[1][2]) <= 8
    assert rows[0][3:] == rows[1][3:]  # the screen changes which episodes are searched, not the labels
    assert all(int(r[4]) <= min(int(r[2]), int(r[3])) for r in rows)
    bad = _run(repo_root, "bench_mining", str(tmp_path / "missing.pt"))
    assert bad.returncode != 0 and "missing.pt" in bad.stderr
