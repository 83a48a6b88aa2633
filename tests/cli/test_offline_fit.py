"""scripts/collect_rows and scripts/fit_rows: expert-labelled rows on disk and the offline fit on them."""
from __future__ import annotations

import dataclasses
import subprocess

import numpy as np
import pytest
import torch

from mapf_policy.model_io import load_model
from mapf_policy.train.agreement import Setup, situations
from mapf_policy.train.fit import CROWDED, FitConfig, Fitter, fit, fit_loss
from mapf_policy.train.rows import ROW_FIELDS, collect, labelled_rows, load_rows

TINY = {"sizes": [3, 4], "cases": 2, "map_size": 12}
SETUP = Setup(max_steps=30)


@pytest.fixture
def rows_dirs(tmp_path, two_random_models):
    """Training rows (own stream) and held-out rows (comparison stream) played by a random model."""
    model = two_random_models[0]
    train, held = tmp_path / "rows_train", tmp_path / "rows_held"
    collect(model, train, TINY["sizes"], TINY["cases"], 0, SETUP, shard_episodes=3, map_size=TINY["map_size"])
    collect(model, held, TINY["sizes"], TINY["cases"], 0, SETUP, held_out=True, map_size=TINY["map_size"])
    return model, train, held


def test_labelled_rows_keep_only_labelled_states():
    rows = {"fov": np.arange(4)[:, None], "last_action": np.arange(4), "position": np.arange(8).reshape(4, 2),
            "expert": np.array([2, -1, 0, -1]), "action": np.zeros(4)}
    out = labelled_rows(rows, 7)
    assert set(out) == set(ROW_FIELDS)
    assert out["fov"][:, 0].tolist() == [0, 2] and out["expert"].tolist() == [2, 0]
    assert out["n_agents"].tolist() == [7, 7]


def test_collect_resumes_repeats_and_refuses_other_settings(rows_dirs, tmp_path):
    model, train, held = rows_dirs
    shards = sorted(train.glob("shard_*.npz"))
    assert len(shards) == 2  # 4 episodes, 3 per shard
    first = load_rows([train])
    assert len(first["expert"]) > 0 and first["expert"].min() >= 0
    assert sorted(set(first["n_agents"].tolist())) == [3, 4]
    # A lost shard is redone with the same rows; the others are kept as they are.
    kept = shards[0].stat().st_mtime_ns
    shards[1].unlink()
    summary = collect(model, train, TINY["sizes"], TINY["cases"], 0, SETUP, shard_episodes=3, map_size=12)
    assert summary["new_shards"] == 1 and shards[0].stat().st_mtime_ns == kept
    again = load_rows([train])
    assert all(np.array_equal(first[f], again[f]) for f in ROW_FIELDS)
    # The held-out stream gives other worlds.
    held_rows = load_rows([held])
    assert not np.array_equal(held_rows["position"][:50], first["position"][:50])
    with pytest.raises(ValueError, match="other settings"):
        collect(model, train, [3], TINY["cases"], 0, SETUP, shard_episodes=3, map_size=12)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="no row shards"):
        load_rows([empty])


def test_cross_entropy_term_is_the_likelihood_under_the_sampling_temperature():
    q = torch.tensor([[0.3, 0.1, 0.0, -0.1, 0.2], [0.0, 0.2, 0.1, 0.0, 0.0]])
    expert = torch.tensor([0, 2])
    cfg = FitConfig(init_model="m", rows=("a",), held_out=("b",), phi=0.0, ce=1.0, ce_temperature=0.04)
    total, l_hscl, l_ce = fit_loss(q, expert, cfg)
    p = torch.softmax(q / 0.04, dim=1)
    assert l_hscl.item() == 0.0
    assert total.item() == pytest.approx(-(p[0, 0].log() + p[1, 2].log()).item() / 2, rel=1e-5)


def test_fit_raises_agreement_on_the_rows_it_fits(rows_dirs, tmp_path):
    """Minimising the loss on a small fixed set makes argmax Q agree with the expert there."""
    model, train, held = rows_dirs
    for phi, ce in ((1.0, 0.0), (0.0, 1.0)):
        cfg = FitConfig(init_model=model, rows=(str(train),), held_out=(str(held),), steps=150, batch_size=64, lr=1e-3,
                        phi=phi, ce=ce, eval_every=150, train_sample=10_000, threads=1)
        fitter = fit(cfg, tmp_path / f"fit_{phi}_{ce}", progress=False)
        start, end = [np.genfromtxt(tmp_path / f"fit_{phi}_{ce}" / "fit.csv", delimiter=",", names=True)[k]
                      for k in ("train_all",)][0][[0, -1]]
        assert fitter.step == 150
        assert start < 0.5 and end > 0.9, (phi, ce, start, end)  # random weights agree about 1 time in 5


def test_crowded_share_draws_crowded_rows(rows_dirs):
    model, train, held = rows_dirs
    cfg = FitConfig(init_model=model, rows=(str(train),), held_out=(str(held),), batch_size=100)
    fitter = Fitter(cfg, None)
    assert np.array_equal(fitter.crowded, np.flatnonzero(situations(fitter.rows["fov"])[CROWDED]))
    assert len(fitter.crowded) == 0  # teams of 3 and 4: never 4 others in view
    with pytest.raises(ValueError, match="needs crowded rows"):
        Fitter(dataclasses.replace(cfg, crowded_share=0.5), None)
    fitter.cfg, fitter.crowded = dataclasses.replace(cfg, crowded_share=0.5), np.array([0, 1])
    idx = fitter.batch_indices()
    assert len(idx) == 100 and np.isin(idx[:50], [0, 1]).all()
    assert not np.isin(idx[50:], [0, 1]).all()  # the rest is drawn from all rows


def test_fit_resumes_to_the_same_weights_and_refuses_other_settings(rows_dirs, tmp_path):
    model, train, held = rows_dirs
    base = dict(init_model=model, rows=(str(train),), held_out=(str(held),), batch_size=32, eval_every=2, threads=1)
    fit(FitConfig(steps=4, **base), tmp_path / "straight", progress=False)
    fit(FitConfig(steps=2, **base), tmp_path / "resumed", progress=False)
    fit(FitConfig(steps=4, **base), tmp_path / "resumed", progress=False)
    a = load_model(tmp_path / "straight" / "last.pt")[0].state_dict()
    b = load_model(tmp_path / "resumed" / "last.pt")[0].state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    steps = [int(line.split(",")[0]) for line in (tmp_path / "resumed" / "fit.csv").read_text().splitlines()[1:]]
    assert steps == [0, 2, 4]
    with pytest.raises(ValueError, match=r"differs in \['lr'\]"):
        fit(FitConfig(steps=4, lr=1e-3, **{k: v for k, v in base.items()}), tmp_path / "resumed", progress=False)
    with pytest.raises(ValueError, match="both a training and a held-out"):
        FitConfig(init_model=model, rows=(str(train),), held_out=(str(train),)).validate()
    with pytest.raises(ValueError, match="not both 0"):
        FitConfig(init_model=model, rows=(str(train),), held_out=(str(held),), phi=0.0).validate()


def test_cli_collects_fits_and_refuses_bad_input(repo_root, tmp_path, two_random_models):
    model = two_random_models[0]
    collect_rows, fit_rows = str(repo_root / "scripts" / "collect_rows"), str(repo_root / "scripts" / "fit_rows")
    tiny = ["--sizes", "3", "--cases", "1", "--map-size", "12", "--max-steps", "20", "--no-progress"]
    for out, extra in (("train", []), ("held", ["--held-out"])):
        run = subprocess.run([collect_rows, model, str(tmp_path / out), *tiny, *extra], capture_output=True, text=True,
                             timeout=300)
        assert run.returncode == 0, run.stderr[-2000:]
        assert '"rows"' in run.stdout
    run = subprocess.run([fit_rows, model, str(tmp_path / "fit"), "--rows", str(tmp_path / "train"), "--held-out",
                          str(tmp_path / "held"), "--steps", "2", "--eval-every", "1", "--batch-size", "16",
                          "--ce", "1", "--no-progress"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert (tmp_path / "fit" / "step_2.pt").is_file() and "held_out_crowded" in run.stdout
    assert (tmp_path / "fit" / "fit.png").stat().st_size > 0
    missing = subprocess.run([fit_rows, str(tmp_path / "nope.pt"), str(tmp_path / "f2"), "--rows", "x", "--held-out",
                              "y"], capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and "nope.pt" in missing.stderr
    no_rows = subprocess.run([fit_rows, model, str(tmp_path / "f3"), "--rows", str(tmp_path / "empty"), "--held-out",
                              str(tmp_path / "held"), "--no-progress"], capture_output=True, text=True, timeout=120)
    assert no_rows.returncode == 2 and "no row shards" in no_rows.stderr
