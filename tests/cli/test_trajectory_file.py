"""scripts/evaluate --trajectories: every case holds its real cells for every step it counts.

The replay here uses nothing of the harness: only the file, the benchmark's maps, starts and goals,
and the grid rules written out again (unit moves, no walls, no shared cell, no swap). It must give
the harness's success and average step exactly, for a planner (including cases whose planner timed
out) and for the learned policy (including cases that ran out of steps).
"""
from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from mapf_world.instances import load_npz

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def replay(frames: np.ndarray, grid: np.ndarray, starts: np.ndarray, goals: np.ndarray, max_steps: int):
    """(success, steps) of one case from its frames alone; AssertionError on an illegal frame."""
    assert (frames[0] == starts).all(), "frame 0 is not the start"
    h, w = grid.shape
    for t in range(len(frames)):
        cells = frames[t]
        assert ((cells >= 0) & (cells < [h, w])).all(), f"frame {t}: a cell off the map"
        assert not grid[cells[:, 0], cells[:, 1]].any(), f"frame {t}: an agent on an obstacle"
        assert len({tuple(c) for c in cells.tolist()}) == len(cells), f"frame {t}: two agents share a cell"
        if t:
            prev = frames[t - 1]
            assert (np.abs(cells - prev).sum(axis=1) <= 1).all(), f"frame {t}: a move longer than one cell"
            where = {tuple(c): i for i, c in enumerate(prev.tolist())}
            for i, c in enumerate(cells.tolist()):
                j = where.get(tuple(c))
                if j is not None and j != i:
                    assert tuple(cells[j].tolist()) != tuple(prev[i].tolist()), f"frame {t}: agents {i}, {j} swap"
    on_goal = (frames == goals[None]).all(axis=2).all(axis=1)
    first = int(np.argmax(on_goal)) if on_goal.any() else None
    if first is not None and first <= max_steps:
        assert first == len(frames) - 1, f"the episode ends at step {first}, the file goes on to {len(frames) - 1}"
        return True, first
    assert len(frames) == max_steps + 1, f"a failed case holds {len(frames) - 1} steps, not max_steps {max_steps}"
    return False, max_steps


def check_file(source, out_json, out_traj, cases: int):
    report = json.loads(out_json.read_text())
    (row,) = report["files"]
    instances = load_npz(source)[:cases]
    with np.load(out_traj, allow_pickle=False) as traj:
        positions, steps, success, max_steps = traj["positions"], traj["steps"], traj["success"], int(traj["max_steps"])
    assert max_steps == report["max_steps"] and len(steps) == cases
    replayed = []
    for k, inst in enumerate(instances):
        frames = positions[k, : steps[k] + 1].astype(np.int64)
        got = replay(frames, inst.grid, inst.starts, inst.goals, max_steps)
        assert got == (bool(success[k]), int(steps[k])), f"case {k}: replay {got}, file {success[k], steps[k]}"
        assert (positions[k, steps[k] + 1:] == positions[k, steps[k]]).all(), f"case {k}: padding is not the last cells"
        replayed.append(got)
    assert np.mean([s for s, _ in replayed]) == row["success_rate"]
    assert float(np.mean([t for _, t in replayed])) == row["average_step"]
    return row


def evaluate(repo_root, tmp_path, name: str, args: list[str]):
    out_json, out_traj = tmp_path / f"{name}.json", tmp_path / f"{name}.npz"
    proc = subprocess.run([str(repo_root / "scripts" / "evaluate"), *args, "--json", str(out_json),
                           "--trajectories", str(out_traj)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return out_json, out_traj


def test_planner_file_replays_to_the_harness_figures_including_timeouts(repo_root, benchmark_dir, tmp_path):
    # 32 agents and a planning limit of a microsecond: every case times out, and its robots stand
    # still for max-steps.
    hard = benchmark_dir / "dhc_40x40_d0.3" / "agents_32.npz"
    out = evaluate(repo_root, tmp_path, "timeout", ["--solver", "odrmstar", "--time-limit", "0.000001",
                                                    "--max-steps", "48", "--instances", str(hard), "--cases", "2"])
    row = check_file(hard, *out, cases=2)
    assert [c["reason"] for c in row["results"]] == ["timeout", "timeout"] and row["average_step"] == 48
    easy = benchmark_dir / "dhc_40x40_d0.3" / "agents_08.npz"
    solved = evaluate(repo_root, tmp_path, "solved", ["--solver", "odrmstar", "--max-steps", "256",
                                                      "--instances", str(easy), "--cases", "2"])
    row = check_file(easy, *solved, cases=2)
    assert row["success_rate"] == 1.0


def test_policy_file_replays_to_the_harness_figures(repo_root, benchmark_dir, tmp_path):
    model = repo_root / "models" / "hscl.pt"
    if not model.is_file():
        pytest.skip("the shipped model models/hscl.pt is not present")
    source = benchmark_dir / "dhc_40x40_d0.3" / "agents_16.npz"
    # 30 steps: short enough that some cases run out of steps, long enough that some succeed.
    out = evaluate(repo_root, tmp_path, "hscl", ["--solver", "hscl", "--model", str(model), "--seed", "0",
                                                 "--max-steps", "30", "--instances", str(source), "--cases", "4"])
    row = check_file(source, *out, cases=4)
    assert len(row["results"]) == 4
