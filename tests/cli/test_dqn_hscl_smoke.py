"""scripts/dqn_hscl and scripts/ladder end to end with tiny budgets: logs, resume, fresh-machine resume."""
from __future__ import annotations

import csv
import json
import shutil
import subprocess

import pytest
import torch

from mapf_policy.model_io import load_model

TINY = ["--stages", "1x6", "2x6", "--total-steps", "12", "--batch-size", "16", "--learning-starts", "40",
        "--log-every", "4", "--eval-every", "6", "--eval-cases", "2", "--expert", "shortest_path",
        "--max-episode-steps", "32", "--resume-refill", "200", "--no-progress"]


def _run(repo_root, tmp_path, *extra):
    cmd = [str(repo_root / "scripts" / "dqn_hscl"), *TINY, "--runs-dir", str(tmp_path / "runs"), *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=180)


def _rows(path):
    with path.open() as f:
        return list(csv.DictReader(f))


def test_dqn_hscl_help_lists_every_option(repo_root):
    out = subprocess.run([str(repo_root / "scripts" / "dqn_hscl"), "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "--heading-refused" in out.stdout and "--total-steps" in out.stdout


@pytest.mark.slow
def test_dqn_hscl_logs_what_it_learns_and_resumes(repo_root, tmp_path):
    pub = tmp_path / "published"
    first = _run(repo_root, tmp_path, "--run-name", "t", "--publish-dir", str(pub))
    assert first.returncode == 0, first.stderr[-3000:]
    run = tmp_path / "runs" / "t"
    rows = _rows(run / "train.csv")
    assert [int(r["step"]) for r in rows] == [4, 8, 12]
    for r in rows:  # every monitored figure is a number in its range
        assert 0.0 <= float(r["dqn_share"]) <= 1.0
        assert float(r["hscl_weight"]) > 0 and float(r["learner_steps_per_s"]) > 0
        assert -1.0 <= float(r["q_return_corr"]) <= 1.0 and float(r["td_abs"]) >= 0
        assert r["agreement_meet"] == "" or 0.0 <= float(r["agreement_meet"]) <= 1.0  # empty: no agents met
        assert 0.0 <= float(r["ongoal_share"]) <= 1.0  # expert rows of agents on their goal with another in view
        assert r["contact_share"] == r["agreement_contact"] == ""  # no priority channel: who comes first is unseen
        assert 0 <= int(r["blocker_move_labels"]) <= int(r["blocker_rows"])
        assert 0 <= int(r["blocker_states"]) <= int(r["blocker_rows"])
    evals = _rows(run / "eval.csv")
    assert {int(e["step"]) for e in evals} == {6, 12} and evals[0]["stage"] == "1x6"
    net, cfg, meta = load_model(run / "last.pt")
    assert cfg.dueling and meta["step"] == 12 and meta["last_action"] == "executed"
    for name in ("last.pt", "best.pt", "state.json", "config.json", "train.csv", "training.png"):
        assert (pub / name).is_file(), name
    last_stage = [e for e in evals if e["stage"] == "2x6"]  # best.pt: the first evaluation with the best success
    best = max(float(e["success_rate"]) for e in last_stage)
    _, _, best_meta = load_model(run / "best.pt")
    assert best_meta["validation_success"] == best
    assert best_meta["step"] == next(int(e["step"]) for e in last_stage if float(e["success_rate"]) == best)

    longer = _run(repo_root, tmp_path, "--run-name", "t", "--total-steps", "16")  # same run: full resume
    assert longer.returncode == 0, longer.stderr[-3000:]
    assert "resumed" in longer.stdout and [int(r["step"]) for r in _rows(run / "train.csv")][-1] == 16

    shutil.rmtree(tmp_path / "runs")  # a fresh machine: only the published folder is left
    published = json.loads((pub / "state.json").read_text())
    fresh = _run(repo_root, tmp_path, "--run-name", "t", "--total-steps", "20", "--publish-dir", str(pub))
    assert fresh.returncode == 0, fresh.stderr[-3000:]
    assert "resumed weights from" in fresh.stdout
    after = json.loads((pub / "state.json").read_text())
    assert after["step"] == 20
    # Learning went on only once the replay held --resume-refill rows again (at most 2 agents x 32 steps an episode)
    assert "refilling the replay to 200 rows" in fresh.stdout
    assert after["episodes"] - published["episodes"] >= 200 // 64

    clash = _run(repo_root, tmp_path, "--run-name", "t", "--lr", "0.5")
    assert clash.returncode == 2 and "lr" in clash.stderr
    bad = _run(repo_root, tmp_path, "--run-name", "u", "--stages", "4by20")
    assert bad.returncode == 2 and "AGENTSxSIZE" in bad.stderr

    # A published run whose last.pt was kept out of git cannot resume: refused by name, its logs left as they were.
    shutil.rmtree(tmp_path / "runs")
    (pub / "last.pt").unlink()
    logs = (pub / "train.csv").read_bytes()
    orphan = _run(repo_root, tmp_path, "--run-name", "t", "--total-steps", "24", "--publish-dir", str(pub))
    assert orphan.returncode == 2 and "step 20 but no last.pt" in orphan.stderr, orphan.stderr[-2000:]
    assert (pub / "train.csv").read_bytes() == logs


@pytest.mark.slow
def test_ladder_reports_a_rung_and_fails_an_untrained_model(repo_root, tmp_path):
    run = _run(repo_root, tmp_path, "--run-name", "l", "--total-steps", "4")
    assert run.returncode == 0, run.stderr[-3000:]
    model = tmp_path / "runs" / "l" / "last.pt"
    out = subprocess.run([str(repo_root / "scripts" / "ladder"), str(model), "--rung", "1", "--cases", "5",
                          "--json", str(tmp_path / "l.json"), "--stuck", "--no-progress"], capture_output=True, text=True, timeout=120)
    rows = json.loads((tmp_path / "l.json").read_text())
    assert rows[0]["agents"] == 1 and rows[0]["map"] == 10 and rows[0]["cases"] == 5
    assert out.returncode == (0 if rows[0]["passed"] else 1) and "| 1 | 1 | 10x10 | 5 |" in out.stdout
    if not rows[0]["passed"]:  # the stuck report counts what it saw in the failed cases
        stuck = rows[0]["stuck"]
        assert stuck["failed_cases"] == 5 - rows[0]["successes"] and "refused moves" in out.stdout
        assert 0 <= stuck["refused_is_argmax"] <= stuck["refused"] and stuck["label_is_refused_move"] <= stuck["labelled"]
        assert stuck["fixed_point"] <= stuck["failed_cases"] and stuck["refused_with_room"] <= stuck["refused"]
        assert stuck["blocker_on_goal"] <= stuck["blockers"] and stuck["blocker_label_moves"] <= stuck["blockers"]
        assert sum(stuck["blocker_label_rank_counts"]) == stuck["blocker_label_moves"] and "pushed into" in out.stdout
        assert 0 <= stuck["blocker_moves_outweigh_stay"] <= stuck["blockers"] and "outweigh" in out.stdout
        assert sum(stuck["period_counts"]) == stuck["failed_cases"] and "Loops at the end" in out.stdout
        assert stuck["moving_off_goal"] <= stuck["off_goal"] and stuck["moving_on_goal"] >= 0
        assert stuck["loops"] == sum(stuck["period_counts"][:-1]) and stuck["loops_expert_leaves"] <= stuck["loops"]
        assert 0 <= stuck["loop_argmax_is_label"] <= stuck["loop_agent_steps"] and "expert's label at" in out.stdout
    missing = subprocess.run([str(repo_root / "scripts" / "ladder"), str(tmp_path / "nope.pt")], capture_output=True,
                             text=True, timeout=60)
    assert missing.returncode == 2 and "does not exist" in missing.stderr
    # --agents keeps only those team sizes of a rung (here the 2-agent row of rung 4) and names a size it lacks.
    # With --agreement each row also counts the agent-steps with another agent in view and the label agreement there.
    two = subprocess.run([str(repo_root / "scripts" / "ladder"), str(model), "--rung", "4", "--agents", "2", "--cases", "2",
                          "--json", str(tmp_path / "two.json"), "--agreement", "--no-progress"], capture_output=True,
                         text=True, timeout=120)
    two_rows = json.loads((tmp_path / "two.json").read_text())
    assert [(r["agents"], r["map"], r["cases"]) for r in two_rows] == [(2, 40, 2)], two.stderr
    agree = two_rows[0]["agreement"]
    assert 0 <= agree["solved_agree"] <= agree["solved_steps"] and 0 <= agree["failed_agree"] <= agree["failed_steps"]
    assert agree["expert"] in ("odrmstar", "prioritized") and "with another agent in view" in two.stdout
    for kind in ("solved", "failed"):  # the contact split covers every counted row; ties only add agreement
        rows = [c for k, c in agree["by_contact"].items() if k.startswith(kind)]
        assert sum(c["rows"] for c in rows) == agree[f"{kind}_steps"]
        assert sum(c["agree"] for c in rows) == agree[f"{kind}_agree"]
        if agree["expert"] == "prioritized":
            assert agree[f"{kind}_agree"] <= agree[f"{kind}_agree_tied"] <= agree[f"{kind}_steps"]
        else:
            assert agree[f"{kind}_agree_tied"] is None
    wrong = subprocess.run([str(repo_root / "scripts" / "ladder"), str(model), "--rung", "2", "--agents", "3"],
                           capture_output=True, text=True, timeout=60)
    assert wrong.returncode == 2 and "none of --agents [3]" in wrong.stderr
    # --epsilon: a diagnostic with random actions, which never passes a rung; --stuck is for greedy play only.
    noisy = subprocess.run([str(repo_root / "scripts" / "ladder"), str(model), "--rung", "1", "--cases", "2", "--epsilon",
                            "0.5", "--json", str(tmp_path / "e.json"), "--no-progress"], capture_output=True, text=True,
                           timeout=120)
    row = json.loads((tmp_path / "e.json").read_text())[0]
    assert noisy.returncode == 1 and row["epsilon"] == 0.5 and not row["passed"] and "epsilon-greedy 0.5" in noisy.stdout
    both = subprocess.run([str(repo_root / "scripts" / "ladder"), str(model), "--epsilon", "0.1", "--stuck"],
                          capture_output=True, text=True, timeout=60)
    assert both.returncode == 2 and "drop --epsilon" in both.stderr


@pytest.mark.slow
def test_a_recurrent_run_trains_on_sequences_and_the_ladder_plays_it_with_memory(repo_root, tmp_path):
    run = _run(repo_root, tmp_path, "--run-name", "g", "--recurrent", "--sequence-length", "4", "--double-dqn")
    assert run.returncode == 0, run.stderr[-3000:]
    rows = _rows(tmp_path / "runs" / "g" / "train.csv")
    assert [int(r["step"]) for r in rows] == [4, 8, 12] and all(float(r["adv_norm"]) > 0 for r in rows)
    _, cfg, meta = load_model(tmp_path / "runs" / "g" / "last.pt")
    assert cfg.recurrent and meta["train_args"]["sequence_length"] == 4
    out = subprocess.run([str(repo_root / "scripts" / "ladder"), str(tmp_path / "runs" / "g" / "last.pt"), "--rung", "1",
                          "--cases", "3", "--json", str(tmp_path / "g.json"), "--stuck", "--no-progress"],
                         capture_output=True, text=True, timeout=120)
    rows = json.loads((tmp_path / "g.json").read_text())
    assert out.returncode == (0 if rows[0]["passed"] else 1) and rows[0]["cases"] == 3, out.stderr[-2000:]
    exported = subprocess.run([str(repo_root / "scripts" / "export_model"), str(tmp_path / "runs" / "g" / "last.pt")],
                              capture_output=True, text=True, timeout=120)
    assert exported.returncode != 0 and "recurrent" in exported.stderr


@pytest.mark.slow
def test_a_heading_run_stores_seven_channels_and_the_ladder_plays_it_with_them(repo_root, tmp_path):
    run = _run(repo_root, tmp_path, "--run-name", "h", "--heading", "--double-dqn")
    assert run.returncode == 0, run.stderr[-3000:]
    _, cfg, meta = load_model(tmp_path / "runs" / "h" / "last.pt")
    assert cfg.heading and cfg.fov_channels == 7 and meta["train_args"]["heading"] is True
    out = subprocess.run([str(repo_root / "scripts" / "ladder"), str(tmp_path / "runs" / "h" / "last.pt"), "--rung", "1",
                          "--cases", "3", "--json", str(tmp_path / "h.json"), "--stuck", "--no-progress"],
                         capture_output=True, text=True, timeout=120)
    rows = json.loads((tmp_path / "h.json").read_text())
    assert out.returncode == (0 if rows[0]["passed"] else 1) and rows[0]["cases"] == 3, out.stderr[-2000:]


def test_a_priority_run_stores_its_channels_and_mining_and_the_ladder_play_them(repo_root, tmp_path):
    # --augment too: its batches (mined rows among them) are turned through all twelve channels
    run = _run(repo_root, tmp_path, "--run-name", "p", "--priority", "--heading", "--goal-dirs", "--greedy-fraction",
               "0.5", "--stuck-steps", "1", "--stuck-cycles", "--stuck-rollout", "4", "--mine-episodes", "1",
               "--mined-batch-share", "0.25", "--augment")
    assert run.returncode == 0, run.stderr[-3000:]
    _, cfg, meta = load_model(tmp_path / "runs" / "p" / "last.pt")
    assert cfg.priority and cfg.heading and cfg.goal_dirs and cfg.fov_channels == 12
    assert meta["train_args"]["priority"] is True and meta["train_args"]["goal_dirs"] is True
    assert meta["train_args"]["augment"] is True
    for r in _rows(tmp_path / "runs" / "p" / "train.csv"):  # rows touching an earlier agent (contact_rows)
        assert 0.0 <= float(r["contact_share"]) <= 1.0
        assert r["agreement_contact"] == "" or 0.0 <= float(r["agreement_contact"]) <= 1.0
    out = subprocess.run([str(repo_root / "scripts" / "ladder"), str(tmp_path / "runs" / "p" / "last.pt"), "--rung", "1",
                          "--cases", "3", "--json", str(tmp_path / "p.json"), "--stuck", "--no-progress"],
                         capture_output=True, text=True, timeout=120)
    rows = json.loads((tmp_path / "p.json").read_text())
    assert out.returncode == (0 if rows[0]["passed"] else 1) and rows[0]["cases"] == 3, out.stderr[-2000:]


def test_a_revisit_count_run_mines_and_the_ladder_plays_it_with_the_count(repo_root, tmp_path):
    run = _run(repo_root, tmp_path, "--run-name", "v", "--still-bins", "4", "--still-count", "revisit",
               "--greedy-fraction", "0.5", "--stuck-steps", "1", "--stuck-cycles", "--stuck-rollout", "4",
               "--mine-episodes", "1")
    assert run.returncode == 0, run.stderr[-3000:]
    _, cfg, _ = load_model(tmp_path / "runs" / "v" / "last.pt")
    assert cfg.still_bins == 4 and cfg.still_count == "revisit" and cfg.env_channels()["revisit_cap"] == 3
    out = subprocess.run([str(repo_root / "scripts" / "ladder"), str(tmp_path / "runs" / "v" / "last.pt"), "--rung", "1",
                          "--cases", "3", "--json", str(tmp_path / "v.json"), "--stuck", "--no-progress"],
                         capture_output=True, text=True, timeout=120)
    rows = json.loads((tmp_path / "v.json").read_text())
    assert out.returncode == (0 if rows[0]["passed"] else 1) and rows[0]["cases"] == 3, out.stderr[-2000:]


@pytest.mark.slow
def test_a_run_can_start_from_another_runs_weights_of_the_same_network(repo_root, tmp_path):
    first = _run(repo_root, tmp_path, "--run-name", "a", "--total-steps", "4")
    assert first.returncode == 0, first.stderr[-3000:]
    start = tmp_path / "runs" / "a" / "last.pt"
    # Another seed (other random weights) and a learning rate of 1e-12, which moves no weight measurably: the new
    # run's end weights are the first run's end weights only if it started from them.
    second = _run(repo_root, tmp_path, "--run-name", "b", "--seed", "1", "--total-steps", "4", "--lr", "1e-12",
                  "--init-model", str(start))
    assert second.returncode == 0, second.stderr[-3000:]
    assert "started from the weights of" in second.stdout
    a, _, _ = load_model(start)
    b, _, meta = load_model(tmp_path / "runs" / "b" / "last.pt")
    assert meta["step"] == 4
    for (name, pa), pb in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.allclose(pa, pb, atol=1e-6), name

    other = _run(repo_root, tmp_path, "--run-name", "d", "--heading", "--init-model", str(start))
    assert other.returncode == 2 and "--init-model" in other.stderr and "heading" in other.stderr
    missing = _run(repo_root, tmp_path, "--run-name", "e", "--init-model", str(tmp_path / "nope.pt"))
    assert missing.returncode == 2 and "init_model" in missing.stderr and "not a file" in missing.stderr


@pytest.mark.slow
def test_an_imitation_run_weighs_the_pushed_blockers_rows(repo_root, tmp_path):
    run = _run(repo_root, tmp_path, "--run-name", "bw", "--imitation", "ce", "--dqn-weight", "0", "--dqn-share", "0",
               "--hscl-weight", "1", "--blocker-weight", "4", "--greedy-fraction", "0.5")
    assert run.returncode == 0, run.stderr[-3000:]
    rows = _rows(tmp_path / "runs" / "bw" / "train.csv")
    assert [int(r["step"]) for r in rows] == [4, 8, 12] and all(float(r["l_hscl"]) > 0 for r in rows)
    bad = _run(repo_root, tmp_path, "--run-name", "bw2", "--blocker-weight", "4")  # the HSCL term: refused
    assert bad.returncode == 2 and "blocker_weight" in bad.stderr


def test_an_imitation_run_can_drop_the_experts_labels_of_agents_on_their_goal(repo_root, tmp_path):
    run = _run(repo_root, tmp_path, "--run-name", "og", "--stages", "2x6", "--imitation", "ce", "--ongoal-weight", "0",
               "--greedy-fraction", "0.5", "--stuck-steps", "2", "--stuck-rollout", "8", "--mine-episodes", "2",
               "--mined-batch-share", "0.25")
    assert run.returncode == 0, run.stderr[-3000:]
    rows = _rows(tmp_path / "runs" / "og" / "train.csv")
    assert [int(r["step"]) for r in rows] == [4, 8, 12]
    assert all(0.0 <= float(r["ongoal_share"]) <= 1.0 and float(r["l_hscl"]) >= 0 for r in rows)
    bad = _run(repo_root, tmp_path, "--run-name", "og2", "--ongoal-weight", "0")  # the HSCL term: refused
    assert bad.returncode == 2 and "ongoal_weight" in bad.stderr


def test_greedy_episodes_get_out_of_fixed_points_by_rollouts(repo_root, tmp_path):
    # Greedy actor episodes only, one agent on 6x6: an untrained greedy agent soon stands still (a wait, or a move
    # into a wall), and a step elsewhere gets it closer.
    run = _run(repo_root, tmp_path, "--run-name", "sr", "--stages", "1x6", "--total-steps", "24",
               "--expert-drive-fraction", "0", "--greedy-fraction", "1", "--stuck-steps", "2", "--stuck-rollout", "8")
    assert run.returncode == 0, run.stderr[-3000:]
    rows = _rows(tmp_path / "runs" / "sr" / "train.csv")
    assert all(int(r["deviations"]) >= 0 for r in rows) and sum(int(r["deviations"]) for r in rows) > 0
    bad = _run(repo_root, tmp_path, "--run-name", "sr2", "--stuck-rollout", "8")  # no greedy episodes: refused
    assert bad.returncode == 2 and "stuck_rollout" in bad.stderr


def test_mined_greedy_episodes_add_only_rollout_labels(repo_root, tmp_path):
    run = _run(repo_root, tmp_path, "--run-name", "mine", "--stages", "1x6", "--total-steps", "24",
               "--greedy-fraction", "0.5", "--stuck-steps", "2", "--stuck-rollout", "8", "--mine-episodes", "2")
    assert run.returncode == 0, run.stderr[-3000:]
    rows = _rows(tmp_path / "runs" / "mine" / "train.csv")
    assert sum(int(r["mined_labels"]) for r in rows) > 0
    assert json.loads((tmp_path / "runs" / "mine" / "state.json").read_text())["mined"] > 0
    # The same with the mined rows in a replay of their own, a quarter of every batch
    run = _run(repo_root, tmp_path, "--run-name", "mine2", "--stages", "1x6", "--total-steps", "24",
               "--greedy-fraction", "0.5", "--stuck-steps", "2", "--stuck-rollout", "8", "--mine-episodes", "2",
               "--mined-batch-share", "0.25")
    assert run.returncode == 0, run.stderr[-3000:]
    assert sum(int(r["mined_labels"]) for r in _rows(tmp_path / "runs" / "mine2" / "train.csv")) > 0
    # Mining a larger team once at the last stage; a mine stage without mining is refused
    run = _run(repo_root, tmp_path, "--run-name", "mine3", "--stages", "1x6", "--total-steps", "24",
               "--greedy-fraction", "0.5", "--stuck-steps", "2", "--stuck-rollout", "8", "--mine-episodes", "2",
               "--mine-stage", "3x6")
    assert run.returncode == 0, run.stderr[-3000:]
    assert sum(int(r["mined_labels"]) for r in _rows(tmp_path / "runs" / "mine3" / "train.csv")) > 0
    for bad_args, word in ((["--mine-stage", "3x6"], "mine_stage"), (["--greedy-fraction", "0.5", "--stuck-steps", "2",
                                                                      "--stuck-rollout", "8", "--mine-episodes", "2",
                                                                      "--mine-stage", "3by6"], "AGENTSxSIZE")):
        bad = _run(repo_root, tmp_path, "--run-name", "mine4", *bad_args)
        assert bad.returncode == 2 and word in bad.stderr, bad.stderr[-500:]


def test_averaged_weights_are_validated_saved_published_and_resumed(repo_root, tmp_path):
    pub = tmp_path / "published"
    run = _run(repo_root, tmp_path, "--run-name", "ema", "--ema-decay", "0.5", "--publish-dir", str(pub),
               "--keep-ema-at", "5", "12")
    assert run.returncode == 0, run.stderr[-3000:]
    d = tmp_path / "runs" / "ema"
    last, _, _ = load_model(d / "last.pt")
    ema, _, meta = load_model(d / "ema.pt")
    assert meta["ema_decay"] == 0.5 and meta["step"] == 12 and (pub / "ema.pt").is_file()
    # --keep-ema-at: copies of the average at those steps, in the run and published; the last one is ema.pt itself.
    at5, _, meta5 = load_model(pub / "ema_at5.pt")
    at12, _, _ = load_model(d / "ema_at12.pt")
    assert meta5["step"] == 5 and (d / "ema_at5.pt").is_file() and not (d / "ema_at6.pt").exists()
    assert all(torch.equal(a, b) for a, b in zip(ema.parameters(), at12.parameters()))
    assert not all(torch.equal(a, b) for a, b in zip(ema.parameters(), at5.parameters()))
    # After 12 steps at decay 0.5 the average is near, but not at, the online weights.
    diffs = [float((a - b).detach().abs().max()) for a, b in zip(last.parameters(), ema.parameters())]
    assert max(diffs) > 0
    evals = _rows(d / "eval.csv")
    last_stage = [e for e in evals if e["stage"] == "2x6"]
    assert last_stage and all(0.0 <= float(e["ema_success_rate"]) <= 1.0 for e in last_stage)
    assert all(e["ema_success_rate"] == "" for e in evals if e["stage"] == "1x6")
    # A fresh machine resumes the average from the published ema.pt, not from the online weights.
    shutil.rmtree(tmp_path / "runs")
    fresh = _run(repo_root, tmp_path, "--run-name", "ema", "--ema-decay", "0.5", "--total-steps", "12",
                 "--publish-dir", str(pub))
    assert fresh.returncode == 0, fresh.stderr[-3000:]
    again, _, _ = load_model(d / "ema.pt")
    assert all(torch.equal(a, b) for a, b in zip(ema.parameters(), again.parameters()))
    bad = _run(repo_root, tmp_path, "--run-name", "ema2", "--ema-decay", "1.0")
    assert bad.returncode == 2 and "ema_decay" in bad.stderr
    for bad_args, words in ((["--ema-decay", "0.5", "--keep-ema-at", "13"], "1..total_steps"),
                            (["--ema-decay", "0.5", "--keep-ema-at", "five"], "whole numbers"),
                            (["--keep-ema-at", "5"], "needs ema_decay")):
        bad = _run(repo_root, tmp_path, "--run-name", "ema3", *bad_args)
        assert bad.returncode == 2 and words in bad.stderr, bad.stderr[-500:]


def test_a_prioritized_expert_run_logs_the_share_of_states_it_labelled(repo_root, tmp_path):
    run = _run(repo_root, tmp_path, "--run-name", "pp", "--priority", "--expert", "prioritized")
    assert run.returncode == 0, run.stderr[-3000:]
    shares = [float(r["pp_label_share"]) for r in _rows(tmp_path / "runs" / "pp" / "train.csv")]
    assert shares and all(0.0 <= s <= 1.0 for s in shares) and max(shares) > 0.0
    # The ladder's agreement with this expert also counts moves its plan ranks equal to the label.
    out = subprocess.run([str(repo_root / "scripts" / "ladder"), str(tmp_path / "runs" / "pp" / "last.pt"), "--rung", "4",
                          "--agents", "4", "--cases", "1", "--json", str(tmp_path / "pp.json"), "--agreement",
                          "--no-progress"], capture_output=True, text=True, timeout=300)
    agree = json.loads((tmp_path / "pp.json").read_text())[0]["agreement"]
    assert agree["expert"] == "prioritized" and "ranks equal to its label" in out.stdout, out.stderr[-2000:]
    steps = agree["solved_steps"] + agree["failed_steps"]
    assert steps > 0 and agree["solved_agree"] + agree["failed_agree"] <= \
        agree["solved_agree_tied"] + agree["failed_agree_tied"] <= steps
    assert sum(c["rows"] for c in agree["by_contact"].values()) == steps
    bad = _run(repo_root, tmp_path, "--run-name", "pp2", "--expert", "prioritized", "--expert-order", "position")
    assert bad.returncode == 2 and "index order" in bad.stderr


def test_retired_options_are_refused_and_a_run_trained_with_one_is_not_resumed(repo_root, tmp_path):
    """--rollout-yielding, --rollout-plan-best and --contact-weight lost their ablations and were retired (fortieth
    session); a run directory saved with one of them on cannot be resumed as if it had been off."""
    for flag in ("--rollout-yielding", "--rollout-plan-best", "--contact-weight"):
        bad = _run(repo_root, tmp_path, "--run-name", "gone", flag)
        assert bad.returncode == 2 and f"unrecognized arguments: {flag}" in bad.stderr, bad.stderr[-500:]
    run = _run(repo_root, tmp_path, "--run-name", "old")
    assert run.returncode == 0, run.stderr[-3000:]
    saved = tmp_path / "runs" / "old" / "config.json"
    saved.write_text(json.dumps(json.loads(saved.read_text()) | {"rollout_plan_best": True}))
    again = _run(repo_root, tmp_path, "--run-name", "old")
    assert again.returncode == 2 and "retired options ['rollout_plan_best']" in again.stderr, again.stderr[-500:]
