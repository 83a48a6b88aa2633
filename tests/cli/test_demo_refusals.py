"""scripts/demo refuses bad input before it starts any process: more robots than the case has agents, a case
index out of range, a model whose exported file is missing or belongs to another model file (exit status 2,
one line naming the problem and the fix)."""
from __future__ import annotations

import shutil

import pytest

from mapf_world.fleet_demo import main as demo

TINY = "tests/fixtures/tiny.npz"  # 3 cases of 3 agents


@pytest.fixture
def models(tmp_path, two_random_models):
    """Two model files; the first has its export beside it, the second a copy of the first's export."""
    from mapf_policy.export import export_model
    a, b = (tmp_path / "a.pt", tmp_path / "b.pt")
    shutil.copy(two_random_models[0], a)
    shutil.copy(two_random_models[1], b)
    export_model(a)
    return a, b


def refusal(capsys, argv) -> str:
    assert demo(argv + ["--out", "/nonexistent/never/written"]) == 2
    return capsys.readouterr().err


def test_more_robots_than_the_case_has_agents(capsys, repo_root, models):
    err = refusal(capsys, ["--npz", str(repo_root / TINY), "--case", "1", "--robots", "4", "--model", str(models[0])])
    assert "--robots 4: more robots than the 3 agents of case 1" in err


def test_case_index_out_of_range(capsys, repo_root, models):
    err = refusal(capsys, ["--npz", str(repo_root / TINY), "--case", "3", "--robots", "3", "--model", str(models[0])])
    assert "--case 3 is outside 0..2" in err and "holds 3 cases" in err


def test_an_export_of_another_model(capsys, repo_root, models):
    a, b = models
    shutil.copy(a.with_suffix(".npz"), b.with_suffix(".npz"))
    err = refusal(capsys, ["--npz", str(repo_root / TINY), "--robots", "3", "--model", str(b)])
    assert f"{b.with_suffix('.npz')} was not exported from {b}" in err and f"scripts/export_model {b}" in err


def test_a_model_without_its_export(capsys, repo_root, models):
    err = refusal(capsys, ["--npz", str(repo_root / TINY), "--robots", "3", "--model", str(models[1])])
    assert f"{models[1].with_suffix('.npz')} does not exist: scripts/export_model {models[1]}" in err
