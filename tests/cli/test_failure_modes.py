"""scripts/failure_modes: what a trajectory shows (off at end, all but k, goal departures, flicker) and the CLI."""
from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from mapf_policy.train.failures import (REFUSAL_CAUSES, beside_others, case_actions, refusal_causes, summarize,
                                        trace_case)

GOALS = np.array([[0, 0], [0, 1], [5, 5]])


def _trajectory(steps_of_agent0: list, others=((0, 2), (4, 5))) -> np.ndarray:
    """Agent 0 walks `steps_of_agent0`; agent 1 sits at (0, 2) beside its goal (0, 1), agent 2 at (4, 5)."""
    return np.array([[a0, others[0], others[1]] for a0 in steps_of_agent0])


def test_beside_others_looks_at_the_four_neighbour_cells_only():
    cells = np.array([[[0, 0], [0, 1], [2, 2], [3, 3]]])
    assert beside_others(cells).tolist() == [[True, True, False, False]]  # (2, 2) and (3, 3) are diagonal


def test_trace_counts_departures_beside_others_and_flicker():
    # Agent 0 steps on and off its goal (0, 0) three times. The neighbour cells of (0, 0) are (1, 0) and
    # (0, 1); agent 1 at (0, 2) is two cells away, so on its goal agent 0 is alone.
    path = [(0, 1), (0, 0), (0, 1), (0, 0), (0, 1), (0, 0), (0, 1)]
    trace = trace_case(_trajectory(path), GOALS, success=False, window=64)
    assert trace["steps"] == 6 and trace["n_agents"] == 3
    assert trace["on_goal"] == [0, 1, 0, 1, 0, 1, 0]  # agent 0 only; agents 1 and 2 never on their goals
    assert trace["off_at_end"] == 3
    assert trace["all_but"] == {1: None, 0: None}  # k < 3 only: never 2 of 3 on goal
    assert (trace["on_goal_alone"], trace["departures_alone"]) == (3, 3)  # steps 1, 3, 5, left each time
    assert (trace["on_goal_beside"], trace["departures_beside"]) == (0, 0)
    assert trace["flickering"] == 1
    # Agents 1 and 2 never move and are never on their goals: 12 still off-goal agent-steps of 18; agent
    # 0 moves at every step.
    assert (trace["agent_steps"], trace["off_goal"], trace["still_off_goal"]) == (18, 15, 12)
    # With agent 2 at (1, 0), below the goal, the same departures happen beside another agent.
    near = trace_case(_trajectory(path, others=((0, 2), (1, 0))), GOALS, success=False)
    assert (near["on_goal_beside"], near["departures_beside"], near["on_goal_alone"]) == (3, 3, 0)
    # The last 2 steps hold one departure (step 5 to 6): not flickering.
    assert trace_case(_trajectory(path), GOALS, success=False, window=2)["flickering"] == 0
    # A solved case has no flickering agents.
    assert trace_case(_trajectory(path), GOALS, success=True)["flickering"] == 0


def test_all_but_k_is_the_first_step_with_that_many_on_goal():
    positions = np.array([[[1, 0], [1, 1], [5, 5]], [[0, 0], [1, 1], [5, 5]], [[0, 0], [0, 1], [5, 5]]])
    trace = trace_case(positions, GOALS, success=True, failed_moves=3)
    assert trace["all_but"] == {1: 1, 0: 2} and trace["failed_moves"] == 3
    assert trace["on_goal"] == [1, 2, 3] and trace["off_at_end"] == 0


def _causes(cells, actions, goals=None, grid=None) -> dict:
    """The non-zero refusal causes of one joint step on a free 5x5 grid (obstacle at (4, 4))."""
    if grid is None:
        grid = np.zeros((5, 5), dtype=np.uint8)
        grid[4, 4] = 1
    cells = np.array(cells)
    goals = np.array(goals) if goals is not None else np.full_like(cells, 9)  # 9: nobody on its goal
    return {k: v for k, v in refusal_causes(grid, cells, np.array(actions), goals).items() if v}


def test_refusal_causes_name_what_stood_in_the_way():
    # Actions: 0 stay, 1 up, 2 down, 3 left, 4 right.
    assert _causes([[3, 4], [0, 0]], [2, 1]) == {"obstacle": 2}  # into the obstacle; off the map
    assert _causes([[0, 0], [0, 1]], [4, 3]) == {"swap": 2}  # head-on: both refused
    # The occupant of the target waits: on its goal, or off it.
    assert _causes([[0, 0], [0, 1]], [4, 0], goals=[[4, 0], [0, 1]]) == {"occupant waited on its goal": 1}
    assert _causes([[0, 0], [0, 1]], [4, 0]) == {"occupant waited off its goal": 1}
    # A queue: agent 2 waits at (0, 2), so agent 1's move fails, and agent 0 behind it fails in cascade.
    assert _causes([[0, 0], [0, 1], [0, 2]], [4, 4, 0]) == {"occupant waited off its goal": 1, "occupant refused": 1}
    # Two movers into the free cell (0, 1): the lower index gets it.
    assert _causes([[0, 0], [1, 1]], [4, 1]) == {"contest": 1}
    # Agent 1 leaves (0, 1) and agent 0 follows it in; agent 2 also wanted the vacated cell.
    assert _causes([[0, 0], [0, 1], [1, 1]], [4, 4, 1]) == {"contest": 1}
    # Nothing refused, nothing counted; every cause is always a key.
    grid = np.zeros((5, 5), dtype=np.uint8)
    counts = refusal_causes(grid, np.array([[0, 0], [0, 1]]), np.array([2, 4]), np.array([[9, 9], [9, 9]]))
    assert tuple(counts) == REFUSAL_CAUSES and sum(counts.values()) == 0


def test_case_actions_splits_still_off_goal_steps_into_waits_and_refused_moves():
    class Case:
        grid = np.zeros((5, 5), dtype=np.uint8)
        goals = np.array([[0, 2], [4, 0]])
    # Step 0: a head-on swap, both refused. Step 1: agent 0 waits, agent 1 steps down.
    positions = np.array([[[0, 0], [0, 1]], [[0, 0], [0, 1]], [[0, 0], [1, 1]]])
    actions = [np.array([4, 3]), np.array([0, 2])]
    chosen = case_actions(Case, positions, actions)
    assert chosen["refusals"]["swap"] == 2 and sum(chosen["refusals"].values()) == 2
    assert (chosen["waits_off_goal"], chosen["refused_off_goal"]) == (1, 2)
    trace = trace_case(positions, Case.goals, success=False, chosen=chosen)
    assert trace["still_off_goal"] == trace["waits_off_goal"] + trace["refused_off_goal"] == 3
    with pytest.raises(ValueError, match="1 joint actions for a trajectory of 2 steps"):
        case_actions(Case, positions, actions[:1])


def test_summary_gives_refusal_shares_over_the_cases_that_recorded_them():
    base = trace_case(_trajectory([(0, 1), (0, 0)]), GOALS, success=True)
    summary = summarize([base], 10, 5)
    assert base["refusals"] is None and summary["refusal_shares"] is None and summary["wait_off_goal_share"] is None
    zero = dict.fromkeys(REFUSAL_CAUSES, 0)
    first = dict(base, refusals=zero | {"swap": 3, "contest": 1}, waits_off_goal=1, refused_off_goal=1)
    second = dict(base, refusals=zero | {"swap": 1, "occupant refused": 3}, waits_off_goal=0, refused_off_goal=2)
    summary = summarize([first, second, base], 10, 5)
    shares = summary["refusal_shares"]
    assert shares["swap"] == 0.5 and shares["contest"] == 0.125 and shares["occupant refused"] == 0.375
    assert shares["obstacle"] == 0 and sum(shares.values()) == pytest.approx(1.0)
    # Each trace has 3 off-goal agent-steps (agents 1 and 2 twice, agent 0 once); `base` recorded nothing.
    assert base["off_goal"] == 3
    assert summary["wait_off_goal_share"] == 1 / 6 and summary["refused_off_goal_share"] == 3 / 6


def test_trace_refuses_bad_shapes():
    with pytest.raises(ValueError, match="positions must be"):
        trace_case(np.zeros((3, 2, 2)), GOALS, success=False)
    with pytest.raises(ValueError, match="window must be >= 1"):
        trace_case(np.zeros((3, 3, 2)), GOALS, success=False, window=0)


def test_summary_splits_tail_failures_from_jams_and_leaves_out_plans_that_gave_up():
    def fake(success, off, flick=0, plan_failed=False):
        return {"n_agents": 8, "success": success, "plan_failed": plan_failed, "steps": 40 if success else 100,
                "off_at_end": off, "all_but": {5: 10, 1: 20 if success else None, 0: 40 if success else None},
                "on_goal_beside": 10, "departures_beside": 2, "on_goal_alone": 5, "departures_alone": 0,
                "flickering": flick, "agent_steps": 80, "off_goal": 40, "still_off_goal": 10, "failed_moves": 4}
    traces = [fake(True, 0), fake(False, 2, flick=3), fake(False, 7), fake(False, 8, plan_failed=True)]
    s = summarize(traces, max_steps=100, tail_agents=5)
    assert (s["cases"], s["successes"], s["plan_failures"]) == (4, 1, 1)
    assert (s["tail_failures"], s["jams"]) == (1, 1)  # the plan that gave up is neither
    assert s["average_step"] == (40 + 100 * 3) / 4
    assert s["median_off_at_end"] == 4.5
    assert s["median_all_but"] == {"5": 10.0, "1": 20.0, "0": 40.0}
    assert s["departure_rate_beside"] == pytest.approx(6 / 30) and s["departure_rate_alone"] == 0
    assert s["failed_with_flicker"] == 1 and s["mean_flickering"] == 1.5
    assert s["still_off_goal_share"] == 0.25 and s["failed_move_rate"] == 0.05
    with pytest.raises(ValueError, match="no cases"):
        summarize([], 100, 5)


def test_failure_modes_cli_with_expert_row(repo_root, tmp_path, two_random_models):
    model = two_random_models[0]
    out = tmp_path / "fm"
    run = subprocess.run([str(repo_root / "scripts" / "failure_modes"), model, "--sizes", "2", "3", "--cases", "2",
                          "--map-size", "10", "--max-steps", "20", "--expert", "--out", str(out), "--no-progress"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    data = json.loads((out / "failures.json").read_text())
    assert set(data["summaries"]) == {model, "ODrM* (epsilon 10)"}
    for label, by_size in data["summaries"].items():
        assert set(by_size) == {"2", "3"}
        for n, s in by_size.items():
            assert s["cases"] == 2 and 0 <= s["successes"] <= 2
            assert len(data["traces"][label][n]) == 2
    # ODrM* solves these small open cases; its trajectories end with every agent on its goal.
    expert = data["traces"]["ODrM* (epsilon 10)"]
    assert all(t["success"] and t["on_goal"][-1] == t["n_agents"] for cases in expert.values() for t in cases)
    assert (out / "on_goal.png").stat().st_size > 1000
    assert run.stdout.count("| ODrM* (epsilon 10) |") == 4  # two sizes, in each of the two tables
    # Refusals by cause: the recorded causes add up to the harness's count in every played case (run()
    # also checks it), and ODrM*'s plans have none.
    assert "refused moves by cause" in run.stdout
    for label, by_size in data["traces"].items():
        for cases in by_size.values():
            assert all(sum(t["refusals"].values()) == t["failed_moves"] for t in cases)
            # An off-goal agent that did not move either chose to wait or had its move refused.
            assert all(t["still_off_goal"] == t["waits_off_goal"] + t["refused_off_goal"] for t in cases)
    assert all(t["failed_moves"] == 0 for cases in expert.values() for t in cases)


def test_failure_modes_cli_refusals(repo_root, tmp_path):
    script = str(repo_root / "scripts" / "failure_modes")
    missing = subprocess.run([script, str(tmp_path / "nope.pt")], capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and "nope.pt" in missing.stderr
    bad = subprocess.run([script, str(tmp_path / "nope.pt"), "--window", "0"], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and "--window" in bad.stderr


def test_median_curve_holds_each_case_at_its_last_count():
    from mapf_policy.train.failures import _median_curve
    cases = [{"on_goal": [0, 1, 2]}, {"on_goal": [0, 2, 2, 3, 3]}, {"on_goal": [1, 1]}]
    # Padded to 5 steps: [0 1 2 2 2], [0 2 2 3 3], [1 1 1 1 1].
    assert _median_curve(cases, max_steps=4).tolist() == [0, 1, 2, 2, 2]


def test_failure_modes_serves_a_second_design_model(repo_root, tmp_path):
    """A model that reads channels beyond the paper's six and the revisit count (issue 20's second design, shipped
    since the fortieth session) is played with the observation it reads."""
    import torch

    from mapf_policy.config import NetworkConfig
    from mapf_policy.model_io import save_model
    from mapf_policy.network import QNetwork
    cfg = NetworkConfig(dueling=True, heading=True, priority=True, goal_dirs=True, still_bins=4, still_count="revisit")
    torch.manual_seed(0)
    model = str(save_model(tmp_path / "second.pt", QNetwork(cfg), cfg, {"last_action": "executed"}))
    run = subprocess.run([str(repo_root / "scripts" / "failure_modes"), model, "--sizes", "3", "--cases", "1",
                          "--map-size", "10", "--max-steps", "10", "--out", str(tmp_path / "fm"), "--no-progress"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    data = json.loads((tmp_path / "fm" / "failures.json").read_text())
    assert data["summaries"][model]["3"]["cases"] == 1
