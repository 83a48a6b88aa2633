"""Evaluation harness: solver registry, greedy, evaluate_file, and a smoke run of scripts/evaluate."""
from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from mapf_world.env import MapfEnv
from mapf_world.evaluate import evaluate_file, sum_of_costs
from mapf_world.grid import DOWN, STAY, UP
from mapf_world.instances import Instance, generate_instance, load_npz
from mapf_world.solvers import REGISTRY, PlanFailed, Solver, get_solver
from mapf_world.validate import validate_solution


# --- registry ---------------------------------------------------------------------------------
def test_registry_names_and_errors():
    for name in ("greedy", "odrmstar", "cbs", "hscl", "hscl_no_self_attention", "hscl_no_channel_attention",
                 "hscl_no_spatial_attention"):
        assert name in REGISTRY
    with pytest.raises(ValueError, match="unknown solver 'nope'; known solvers: cbs, greedy"):
        get_solver("nope")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['epsilon'\]"):
        get_solver("greedy", epsilon=1.0)
    solver = get_solver("greedy")
    assert solver.name == "greedy" and isinstance(solver, Solver)


def test_plan_failed_reasons():
    assert PlanFailed("timeout").reason == "timeout"
    with pytest.raises(ValueError, match="reason"):
        PlanFailed("bored")


# --- greedy -----------------------------------------------------------------------------------
def test_greedy_follows_shortest_paths_with_action_order_ties():
    grid = np.zeros((3, 3), np.uint8)
    env = MapfEnv(grid, [[0, 0], [2, 2]], [[2, 2], [1, 2]])
    obs, _ = env.reset()
    greedy = get_solver("greedy")
    greedy.reset(env)
    # Agent 0: down and right both get closer; down (2) comes before right (4). Agent 1: up.
    assert greedy.act(obs).tolist() == [DOWN, UP]
    env2 = MapfEnv(grid, [[1, 1]], [[1, 1]])
    obs2, _ = env2.reset()
    greedy.reset(env2)
    assert greedy.act(obs2).tolist() == [STAY]


def test_greedy_ignores_others_and_fails_in_a_corridor():
    # Two agents that must pass each other in a 1-wide corridor: greedy swaps forever (both fail).
    grid = np.zeros((1, 4), np.uint8)
    results = evaluate_file("greedy", [Instance(grid, [[0, 0], [0, 3]], [[0, 3], [0, 0]])], max_steps=20)
    (r,) = results
    assert not r.success and r.steps == 20 and r.reason == "max_steps" and r.failed_moves > 0
    assert r.positions.shape == (21, 2, 2)


# --- harness ----------------------------------------------------------------------------------
def test_sum_of_costs_counts_last_arrival():
    goals = np.array([[0, 2], [1, 0]])
    run = np.array([
        [[0, 0], [1, 0]],
        [[0, 1], [1, 1]],
        [[0, 2], [1, 0]],
        [[0, 2], [1, 0]],
    ])
    assert sum_of_costs(run, goals, steps=3) == 2 + 2  # agent 1 left its goal and came back at step 2
    assert sum_of_costs(run[:2], goals, steps=256) == 256 + 256


def test_evaluate_file_on_generated_cases():
    instances = [generate_instance(s, size=12, density=0.2, n_agents=3) for s in range(4)]
    results = evaluate_file(get_solver("greedy"), instances, max_steps=64)
    assert [r.index for r in results] == [0, 1, 2, 3]
    for inst, r in zip(instances, results):
        validate_solution(inst.grid, inst.starts, inst.goals, r.positions, success=r.success)
        assert r.steps == (r.positions.shape[0] - 1 if r.success else 64)
        assert r.seconds > 0 and (r.reason is None) == r.success


class _Refuses:
    name = "refuses"

    def reset(self, env):
        raise PlanFailed("timeout", "no plan within 0 s")

    def act(self, obs):
        raise AssertionError("act() after a failed plan")


def test_plan_failed_is_a_failed_case():
    inst = generate_instance(0, size=8, n_agents=2)
    (r,) = evaluate_file(_Refuses(), [inst], max_steps=50)
    assert not r.success and r.steps == 50 and r.reason == "timeout"
    # Without a plan the robots stand still: the real cells of all 50 counted steps are the starts.
    assert r.sum_of_costs == 100 and r.positions.shape == (51, 2, 2)
    assert (r.positions == np.asarray(inst.starts)[None]).all() and r.failed_moves == 0


class _StaysPut:
    name = "stays"

    def reset(self, env):
        pass

    def act(self, obs):
        return np.full(len(obs["position"]), STAY)


def test_a_case_solved_at_the_start_takes_zero_steps():
    grid = np.zeros((2, 2), np.uint8)
    (r,) = evaluate_file(_StaysPut(), [Instance(grid, [[0, 0]], [[0, 0]])], max_steps=5)
    assert r.success and r.steps == 0 and r.sum_of_costs == 0


# --- CLI --------------------------------------------------------------------------------------
def test_cli_greedy_on_three_benchmark_cases(repo_root, benchmark_dir, tmp_path):
    source = benchmark_dir / "dhc_40x40_d0.3" / "agents_04.npz"
    out_json, out_traj = tmp_path / "greedy.json", tmp_path / "greedy.npz"
    proc = subprocess.run(
        [str(repo_root / "scripts" / "evaluate"), "--solver", "greedy", "--instances", str(source),
         "--cases", "3", "--json", str(out_json), "--trajectories", str(out_traj)],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "greedy" in proc.stdout and "success" in proc.stdout
    report = json.loads(out_json.read_text())
    assert report["solver"] == "greedy" and report["max_steps"] == 256
    (row,) = report["files"]
    assert row["agents"] == 4 and row["cases"] == 3 and len(row["results"]) == 3
    for key in ("success_rate", "average_step", "mean_sum_of_costs", "wall_time_s"):
        assert key in row
    for case in row["results"]:
        assert set(case) >= {"steps", "success", "sum_of_costs", "failed_moves", "reason", "seconds"}
    steps = [c["steps"] for c in row["results"]]
    assert row["average_step"] == pytest.approx(np.mean(steps))
    assert row["success_rate"] == pytest.approx(np.mean([c["success"] for c in row["results"]]))

    # The trajectories re-check independently of the harness.
    cases = load_npz(source)[:3]
    with np.load(out_traj, allow_pickle=False) as traj:
        positions, t_steps, success = traj["positions"], traj["steps"], traj["success"]
    assert positions.dtype == np.int16 and positions.shape[0] == 3 and positions.shape[2:] == (4, 2)
    assert success.dtype == bool and t_steps.tolist() == steps
    for k, inst in enumerate(cases):
        run = positions[k, : (t_steps[k] if success[k] else 256) + 1]
        validate_solution(inst.grid, inst.starts, inst.goals, run, success=bool(success[k]))
        assert (positions[k, len(run):] == run[-1]).all()  # padded with the last cells


def test_cli_errors(repo_root, tmp_path):
    script = str(repo_root / "scripts" / "evaluate")
    proc = subprocess.run([script, "--solver", "nope", "--instances", str(tmp_path / "x.npz")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "known solvers" in proc.stderr
    proc = subprocess.run([script, "--solver", "greedy", "--instances", str(tmp_path / "missing.npz")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "missing.npz" in proc.stderr
    fixture = repo_root / "tests" / "fixtures" / "tiny.npz"
    proc = subprocess.run([script, "--solver", "greedy", "--instances", str(fixture), "--cases", "4"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "--cases 4 but the file holds 3 cases" in proc.stderr


def test_cli_hscl_sampling_options_are_recorded_and_checked(repo_root, tmp_path):
    import torch

    from mapf_policy.config import NetworkConfig
    from mapf_policy.model_io import save_model
    from mapf_policy.network import QNetwork

    torch.manual_seed(0)
    model = save_model(tmp_path / "m.pt", QNetwork(NetworkConfig()), NetworkConfig(), {"steps": 0})
    fixture = repo_root / "tests" / "fixtures" / "tiny.npz"
    script = str(repo_root / "scripts" / "evaluate")
    reports = []
    for k in range(2):
        out = tmp_path / f"hscl{k}.json"
        proc = subprocess.run([script, "--solver", "hscl", "--model", str(model), "--action-temperature", "0.5",
                               "--seed", "4", "--max-steps", "12", "--instances", str(fixture), "--json", str(out)],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        reports.append(json.loads(out.read_text()))
    assert reports[0]["settings"] == {"model": str(model), "action_temperature": 0.5, "backtrack_penalty": 0.05,
                                      "mask_obstacle_moves": True, "settled_greedy": True, "goal_stay_bonus": 0.0,
                                      "seed": 4, "last_action": "requested"}
    # Same seed: the same actions, so the same per-case steps and costs.
    strip = [[{k: v for k, v in c.items() if k != "seconds"} for c in r["files"][0]["results"]] for r in reports]
    assert strip[0] == strip[1]
    bad = subprocess.run([script, "--solver", "hscl", "--model", str(model), "--action-temperature", "-2",
                          "--instances", str(fixture)], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "action_temperature must be a finite number >= 0" in bad.stderr
    paper = tmp_path / "paper.json"
    proc = subprocess.run([script, "--solver", "hscl", "--model", str(model), "--action-rule", "paper",
                           "--backtrack-penalty", "0.2", "--max-steps", "12", "--instances", str(fixture),
                           "--json", str(paper)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(paper.read_text())["settings"] == {
        "model": str(model), "action_temperature": 0.0, "backtrack_penalty": 0.2, "mask_obstacle_moves": False,
        "settled_greedy": True, "goal_stay_bonus": 0.0, "seed": 0, "last_action": "requested"}
    unknown = subprocess.run([script, "--solver", "hscl", "--model", str(model), "--action-rule", "greedy",
                              "--instances", str(fixture)], capture_output=True, text=True, timeout=120)
    assert unknown.returncode == 2 and "unknown action rule 'greedy'" in unknown.stderr
    other = subprocess.run([script, "--solver", "greedy", "--action-temperature", "0.1", "--instances", str(fixture)],
                           capture_output=True, text=True, timeout=120)
    assert other.returncode == 2 and "unknown option" in other.stderr and "action_temperature" in other.stderr
