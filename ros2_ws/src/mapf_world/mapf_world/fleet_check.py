"""scripts/check_fleet: does a fleet run's grid trajectory (its MCAP log) equal the evaluation harness's?

    scripts/evaluate --solver hscl --action-rule paper --instances CASES.npz --cases 1 --trajectories eval.npz
    scripts/demo --npz CASES.npz --case 0 --robots N --action-rule paper ... --out RUN
    scripts/check_fleet RUN/fleet.mcap eval.npz [--case 0]

Compares the cells of every robot at every step (the log's /fleet/status, mapf_world/fleet_replay.py) with
case --case of the trajectory file `scripts/evaluate --trajectories` wrote. Equal: exit 0. Different: exit 1,
with the first step and robots that differ, and the steps where the log shows robots that got no action in
time (outcome TIMEOUT: the world made them stay, which the harness never does) or whose action was refused,
the usual reason for a difference.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

TIMEOUT, REJECTED = 2, 3  # mapf_msgs/CellMove OUTCOME_*


def compare(logged: np.ndarray, expected: np.ndarray) -> tuple[int, list[int]] | None:
    """None when the (T+1, N, 2) trajectories are equal; else (first step that differs, robots differing there).
    A different length counts as a difference at the shorter one's end."""
    t = min(len(logged), len(expected))
    if logged.shape[1:] != expected.shape[1:]:
        raise ValueError(f"the log has {logged.shape[1]} robots, the trajectory file {expected.shape[1]} agents")
    for k in range(t):
        differ = np.flatnonzero((logged[k] != expected[k]).any(axis=1))
        if differ.size:
            return k, differ.tolist()
    return None if len(logged) == len(expected) else (t, [])


def failed_answers(statuses) -> list[tuple[int, int, str]]:
    """[(step, robot, 'timeout' | 'rejected')] from the log's FleetStatus outcomes."""
    out = []
    for s in statuses:
        for robot, outcome in enumerate(getattr(s, "outcomes", []) or []):
            if outcome in (TIMEOUT, REJECTED) and s.state != 0:
                out.append((int(s.step) - 1, robot, "timeout" if outcome == TIMEOUT else "rejected"))
    return sorted(set(out))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scripts/check_fleet", description=__doc__.split("\n\n")[0])
    ap.add_argument("mcap", type=Path, help="the fleet's MCAP log")
    ap.add_argument("trajectories", type=Path, help="scripts/evaluate --trajectories output")
    ap.add_argument("--case", type=int, default=0, help="which case of the trajectory file (default 0)")
    args = ap.parse_args(argv)
    from mapf_world.fleet_replay import load_run
    run = load_run(args.mcap)
    logged = run.positions()
    with np.load(args.trajectories) as traj:
        if not 0 <= args.case < len(traj["steps"]):
            print(f"check_fleet: error: --case {args.case} is not in {args.trajectories}", file=sys.stderr)
            return 2
        steps = int(traj["steps"][args.case])
        expected = traj["positions"][args.case][:steps + 1]
    failed = failed_answers(run.statuses)
    result = compare(logged, expected)
    print(f"check_fleet: log {len(logged) - 1} steps, {logged.shape[1]} robots; harness {steps} steps; "
          f"robots without a valid action in the log: {len(failed)}")
    if result is None:
        print("check_fleet: the fleet's grid trajectory equals the harness's, step for step")
        return 0
    step, robots = result
    print(f"check_fleet: DIFFERENT from step {step}" + (f", robots {robots[:12]}" if robots else " (length)"))
    before = [f for f in failed if f[0] < step]
    if before:
        print("check_fleet: the log shows robots that stayed without their own action before that step: "
              + ", ".join(f"step {s} robot {r} ({why})" for s, r, why in before[:12]))
    return 1


if __name__ == "__main__":
    sys.exit(main())
