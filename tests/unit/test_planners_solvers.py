"""Harness adapters of the planners (registry names odrmstar and cbs), the native library loader,
plan_actions, and a smoke run of the planner benchmark on a tiny benchmark folder."""
from __future__ import annotations

import json

import numpy as np
import pytest
from mapf_world.grid import grid_from_text as parse_map

from mapf_world.env import MapfEnv
from mapf_world.evaluate import evaluate_file, run_case
from mapf_world.grid import DOWN, LEFT, RIGHT, STAY, UP
from mapf_world.instances import Instance, generate_instance, save_npz
from mapf_world.planners import bench, native, plan_actions
from mapf_world.solvers import PlanFailed, Solver, get_solver


@pytest.mark.parametrize("name", ["odrmstar", "cbs"])
def test_registry_builds_planner_solvers(name):
    solver = get_solver(name, time_limit=5.0)
    assert isinstance(solver, Solver) and solver.name == name
    inst = generate_instance(11, size=20, density=0.2, n_agents=6)
    (result,) = evaluate_file(solver, [inst])
    assert result.success and result.failed_moves == 0
    assert result.steps == solver.last_result.makespan


def test_solver_options_are_checked():
    assert get_solver("odrmstar", epsilon=1.5, objective="sum_of_costs").name == "odrmstar"
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['model'\]"):
        get_solver("odrmstar", model="x.pt")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['epsilon'\]"):
        get_solver("cbs", epsilon=10.0)
    with pytest.raises(ValueError, match="epsilon"):
        get_solver("odrmstar", epsilon=0.0)
    with pytest.raises(ValueError, match="time_limit"):
        get_solver("cbs", time_limit=-1.0)


def test_plan_failed_and_act_before_reset():
    solver = get_solver("odrmstar")
    with pytest.raises(ValueError, match="act\\(\\) called before a successful reset"):
        solver.act({"position": np.zeros((2, 2))})
    inst = Instance(parse_map(". . ."), [[0, 0], [0, 1]], [[0, 1], [0, 0]])
    env = MapfEnv(inst.grid, inst.starts, inst.goals)
    env.reset()
    with pytest.raises(PlanFailed) as info:
        solver.reset(env)
    assert info.value.reason == "unsolvable"
    result = run_case(solver, inst, max_steps=256)
    assert not result.success and result.reason == "unsolvable" and result.steps == 256


def test_act_checks_the_agents_are_on_the_plan():
    inst = Instance(parse_map(". . . ."), [[0, 0]], [[0, 3]])
    env = MapfEnv(inst.grid, inst.starts, inst.goals)
    obs, _ = env.reset()
    solver = get_solver("cbs")
    solver.reset(env)
    obs, *_ = env.step(solver.act(obs))
    obs, *_ = env.step(np.array([LEFT]))  # back to the start, off the plan
    with pytest.raises(RuntimeError, match="not where the plan put them"):
        solver.act(obs)


def test_plan_actions():
    positions = np.array([[[1, 1], [0, 0]], [[0, 1], [0, 0]], [[0, 1], [1, 0]], [[0, 0], [1, 1]], [[0, 1], [1, 1]]])
    np.testing.assert_array_equal(plan_actions(positions), [[UP, STAY], [STAY, DOWN], [LEFT, RIGHT], [RIGHT, STAY]])
    with pytest.raises(ValueError, match="plan step 1: agent 0 moves by \\[2, 0\\]"):
        plan_actions(np.array([[[0, 0]], [[2, 0]]]))


def test_native_library_is_found_and_missing_library_is_explained(monkeypatch, tmp_path):
    assert native.library_path().name.startswith("_native")
    monkeypatch.setattr(native, "__file__", str(tmp_path / "planners" / "native.py"))
    with pytest.raises(FileNotFoundError, match="run scripts/setup"):
        native.library_path()


def test_native_rejects_bad_shapes_with_a_message():
    with pytest.raises(ValueError, match="native planner: start of agent 0 is off the map"):
        native.run(native.CBS, np.zeros((2, 2), np.uint8), np.array([[5, 5]]), np.array([[0, 0]]), 1.0, 1.0)
    with pytest.raises(ValueError, match="native planner: time_limit must be > 0"):
        native.run(native.CBS, np.zeros((2, 2), np.uint8), np.array([[0, 0]]), np.array([[1, 1]]), 1.0, 0.0)


def test_bench_smoke(tmp_path, capsys):
    for n, seed in ((4, 1), (8, 2)):
        save_npz(tmp_path / f"agents_{n:02d}.npz",
                 [generate_instance(seed + k, size=16, density=0.2, n_agents=n) for k in range(3)])
    out = tmp_path / "bench.json"
    assert bench.main(["--bench-dir", str(tmp_path), "--sizes", "4", "8", "--cases", "2", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "avg_step" in text and "49.74" in text  # the reference row beside the figures
    report = json.loads(out.read_text())
    assert [s["agents"] for s in report["sizes"]] == [4, 8]
    assert all(s["cases"] == 2 and s["solved"] == 2 for s in report["sizes"])
    assert bench.main(["--bench-dir", str(tmp_path), "--sizes", "16"]) == 2
    assert "missing benchmark file" in capsys.readouterr().err
    assert bench.main(["--solver", "cbs", "--bench-dir", str(tmp_path), "--sizes", "4", "--cases", "1"]) == 0
