"""scripts/compare_models: held-out generated cases, the same cases for every model, clear refusals."""
from __future__ import annotations

import json
import subprocess

import torch

from mapf_policy.config import NetworkConfig
from mapf_policy.model_io import save_model
from mapf_policy.network import QNetwork
from mapf_policy.train.compare import held_out_cases


def test_held_out_cases_are_fixed_and_sized():
    a = held_out_cases([2, 3], 2, seed=0, map_size=10, density=0.3)
    b = held_out_cases([2, 3], 2, seed=0, map_size=10, density=0.3)
    assert [x.n_agents for x in a] == [2, 2, 3, 3]
    assert all((x.grid == y.grid).all() and (x.starts == y.starts).all() for x, y in zip(a, b))
    c = held_out_cases([2], 1, seed=1, map_size=10, density=0.3)
    assert not ((c[0].grid == a[0].grid).all() and (c[0].starts == a[0].starts).all())


def test_compare_two_models(repo_root, tmp_path, two_random_models):
    paths = two_random_models
    out = tmp_path / "cmp.json"
    run = subprocess.run([str(repo_root / "scripts" / "compare_models"), *paths, "--sizes", "1", "2", "--cases", "2",
                          "--map-size", "10", "--max-steps", "20", "--json", str(out), "--no-progress"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    data = json.loads(out.read_text())
    assert set(data["results"]) == set(paths)
    for by_size in data["results"].values():
        assert set(by_size) == {"1", "2"}
        for v in by_size.values():
            assert v["cases"] == 2 and 0 <= v["successes"] <= 2
            assert 0 < v["average_step"] <= 20
            assert v["success_rate"] == v["successes"] / 2
    assert run.stdout.count("| ") >= 3 and "1 agents" in run.stdout


def test_compare_refuses_missing_and_corrupt(repo_root, tmp_path):
    script = str(repo_root / "scripts" / "compare_models")
    missing = subprocess.run([script, str(tmp_path / "nope.pt")], capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and "nope.pt" in missing.stderr
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a model")
    corrupt = subprocess.run([script, str(bad), "--sizes", "1", "--cases", "1", "--map-size", "10", "--no-progress"],
                             capture_output=True, text=True, timeout=120)
    assert corrupt.returncode == 2 and "bad.pt" in corrupt.stderr


def test_compare_with_sampled_actions_is_repeatable_and_checked(repo_root, tmp_path):
    torch.manual_seed(1)
    path = tmp_path / "m.pt"
    save_model(path, QNetwork(NetworkConfig()), NetworkConfig(), {"step": 0})
    script = str(repo_root / "scripts" / "compare_models")
    outs = []
    for k in range(2):
        out = tmp_path / f"sampled{k}.json"
        run = subprocess.run([script, str(path), "--sizes", "2", "--cases", "2", "--map-size", "10", "--max-steps", "15",
                              "--action-temperature", "0.5", "--sample-seed", "3", "--json", str(out), "--no-progress"],
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr[-2000:]
        outs.append(json.loads(out.read_text()))
    assert outs[0] == outs[1]  # same cases, same sampling seed: same results
    # The default base rule here is the paper's; the flag replaces only the temperature.
    assert outs[0]["action_rule"] == {"action_temperature": 0.5, "backtrack_penalty": 0.0,
                                      "mask_obstacle_moves": False, "settled_greedy": True, "goal_stay_bonus": 0.0}
    assert outs[0]["sample_seed"] == 3
    v = outs[0]["results"][str(path)]["2"]
    assert v["cases"] == 2 and 0 < v["average_step"] <= 15
    bad = subprocess.run([script, str(path), "--sizes", "1", "--cases", "1", "--map-size", "10",
                          "--action-temperature", "-1", "--no-progress"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "action_temperature" in bad.stderr
    shipped = subprocess.run([script, str(path), "--sizes", "2", "--cases", "1", "--map-size", "10", "--max-steps", "15",
                              "--action-rule", "default", "--json", str(tmp_path / "shipped.json"), "--no-progress"],
                             capture_output=True, text=True, timeout=300)
    assert shipped.returncode == 0, shipped.stderr[-2000:]
    assert json.loads((tmp_path / "shipped.json").read_text())["action_rule"]["backtrack_penalty"] == 0.05
