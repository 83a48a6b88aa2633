"""Action selection: greedy argmax, Boltzmann sampling, settled agents, the deadlock it exists for, the
obstacle mask, the backtrack penalty and the typed ActionRule."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from mapf_policy.action_selection import (PAPER_RULE, ActionChooser, ActionRule, backtrack_moves,
                                          check_action_temperature, make_rule, obstacle_moves, select_actions, settled)
from mapf_policy.config import NetworkConfig
from mapf_policy.model_io import save_model
from mapf_policy.network import QNetwork
from mapf_policy.policy import Policy
from mapf_policy.solver import make_hscl
from mapf_world.env import MapfEnv
from mapf_world.evaluate import run_case
from mapf_world.grid import grid_from_text
from mapf_world.instances import Instance, generate_instance
from mapf_world.observation import ObservationBuilder

# One corridor with a single side pocket above its middle cell (0, 3).
CORRIDOR = grid_from_text("""
###.###
.......
#######
""")


def test_zero_temperature_is_argmax_with_ties_to_stay():
    q = np.array([[0.1, 0.3, 0.3, 0.0, -1.0], [0.5, 0.5, 0.5, 0.5, 0.5], [-2, -1, -3, 0, -4]])
    assert select_actions(q, 0.0, None).tolist() == [1, 0, 3]


def test_sampling_follows_softmax_of_q_over_temperature():
    q = np.array([[0.0, 0.2, -0.1, 0.05, 0.0]])
    t = 0.1
    draws = select_actions(np.repeat(q, 40_000, axis=0), t, np.random.default_rng(3))
    freq = np.bincount(draws, minlength=5) / draws.size
    expected = np.exp(q[0] / t) / np.exp(q[0] / t).sum()
    # 40,000 draws: the standard error of each share is below 0.0025.
    np.testing.assert_allclose(freq, expected, atol=0.01)
    # A small temperature concentrates on the argmax; a same-seed generator repeats the draws.
    assert (select_actions(np.repeat(q, 1000, axis=0), 0.01, np.random.default_rng(0)) == 1).mean() > 0.99
    a = select_actions(np.repeat(q, 50, axis=0), t, np.random.default_rng(7))
    b = select_actions(np.repeat(q, 50, axis=0), t, np.random.default_rng(7))
    assert np.array_equal(a, b)


def test_greedy_rows_ignore_the_noise():
    q = np.tile([0.0, 0.0, 0.0, 0.0, 0.01], (500, 1))
    rows = np.zeros(500, dtype=bool)
    rows[::2] = True
    a = select_actions(q, 1.0, np.random.default_rng(1), greedy_rows=rows)
    assert (a[rows] == 4).all()
    assert len(set(a[~rows].tolist())) == 5  # near-uniform draws elsewhere


def test_settled_means_on_goal_with_no_agent_next_to_it():
    grid = grid_from_text("""
.....
.....
.....
""")
    # Agent 0 on its goal, alone; agent 1 on its goal with agent 2 beside it; agent 2 off its goal.
    goals = np.array([[0, 0], [2, 3], [0, 4]])
    positions = np.array([[0, 0], [2, 3], [2, 4]])
    obs = ObservationBuilder(grid, goals, fov_size=3).build(positions, np.zeros(3, dtype=np.int64))
    assert settled(obs["fov"]).tolist() == [True, False, False]
    with pytest.raises(ValueError, match="fov must have shape"):
        settled(obs["fov"][:, :5])


def test_bad_input_is_refused_with_the_reason():
    with pytest.raises(ValueError, match="finite number >= 0"):
        check_action_temperature(-0.1)
    with pytest.raises(ValueError, match="finite number >= 0"):
        check_action_temperature(float("nan"))
    with pytest.raises(ValueError, match="a number"):
        check_action_temperature("hot")
    with pytest.raises(ValueError, match="needs a random generator"):
        select_actions(np.zeros((1, 5)), 0.5, None)
    with pytest.raises(ValueError, match="NaN"):
        select_actions(np.array([[0.0, np.nan, 0, 0, 0]]), 0.0, None)
    with pytest.raises(ValueError, match=r"shape \(batch, actions\)"):
        select_actions(np.zeros(5), 0.0, None)
    with pytest.raises(ValueError, match="greedy_rows must have shape"):
        select_actions(np.zeros((2, 5)), 0.5, np.random.default_rng(0), greedy_rows=np.zeros(3, dtype=bool))


def goal_seeking_q(obs: dict) -> np.ndarray:
    """A stand-in Q: 1 for a move that gets closer to the goal, 0.2 for staying on the goal, else 0."""
    c = obs["fov"].shape[-1] // 2
    bits = obs["fov"][:, 2:6, c, c]
    on_goal = bits.sum(axis=1) == 0
    return np.concatenate([np.where(on_goal, 0.2, 0.0)[:, None], bits], axis=1)


def run_corridor(action_temperature: float, seed: int) -> tuple[bool, int]:
    env = MapfEnv(CORRIDOR, [[1, 0], [1, 6]], [[1, 6], [1, 0]], fov_size=3, max_steps=256)
    obs, _ = env.reset()
    rng = np.random.default_rng(seed)
    while True:
        actions = select_actions(goal_seeking_q(obs), action_temperature, rng, greedy_rows=settled(obs["fov"]))
        obs, _, terminated, truncated, info = env.step(actions)
        if terminated or truncated:
            return bool(info["success"]), env.step_count


def test_sampling_breaks_the_head_on_deadlock_that_greedy_never_leaves():
    # Greedy: the two agents meet in the corridor and push into each other until the step limit.
    assert run_corridor(0.0, seed=0) == (False, 256)
    # Sampling: one of them sooner or later steps into the pocket and lets the other pass. Every seed
    # tried here succeeds; the shortest joint plan takes 8 steps (one agent waits in the pocket).
    for seed in range(5):
        success, steps = run_corridor(0.5, seed)
        assert success and 8 <= steps < 256, (seed, steps)


def test_hscl_solver_settings_and_repeatable_cases(tmp_path):
    torch.manual_seed(0)
    cfg = NetworkConfig()
    path = save_model(tmp_path / "m.pt", QNetwork(cfg), cfg, {"steps": 0})
    inst = generate_instance(5, size=12, density=0.2, n_agents=4)
    assert isinstance(inst, Instance)
    sampled = make_hscl(model=str(path), action_temperature=0.5, seed=11)
    assert sampled.settings == {"model": str(path), "action_temperature": 0.5, "backtrack_penalty": 0.05,
                                "mask_obstacle_moves": True, "settled_greedy": True, "goal_stay_bonus": 0.0,
                                "seed": 11, "last_action": "requested"}
    # A model of the second design carries its last-action mode to the harness.
    executed = save_model(tmp_path / "e.pt", QNetwork(cfg), cfg, {"steps": 0, "last_action": "executed"})
    assert make_hscl(model=str(executed)).last_action == "executed"
    # The generator restarts at each case: running a case twice gives the same trajectory.
    first = run_case(sampled, inst, 20).positions
    assert np.array_equal(first, run_case(sampled, inst, 20).positions)
    # The paper's rule is the network's argmax.
    greedy = make_hscl(model=str(path), action_rule="paper")
    assert greedy.policy.rule == PAPER_RULE
    obs, _ = MapfEnv(inst.grid, inst.starts, inst.goals).reset()
    q = greedy.policy.q_values(obs["fov"], obs["last_action"], obs["position"]).numpy()
    assert np.array_equal(greedy.act(obs), q.argmax(axis=1))
    with pytest.raises(ValueError, match="finite number >= 0"):
        make_hscl(model=str(path), action_temperature=-1)
    with pytest.raises(ValueError, match="seed must be an integer >= 0"):
        make_hscl(model=str(path), seed=-3)
    with pytest.raises(ValueError, match="solver hscl: unknown action rule 'greedy'"):
        make_hscl(model=str(path), action_rule="greedy")
    with pytest.raises(ValueError, match="backtrack_penalty must be a finite number >= 0"):
        make_hscl(model=str(path), backtrack_penalty=-0.1)


def test_policy_keeps_settled_agents_greedy_unless_told_not_to(tmp_path):
    torch.manual_seed(2)
    cfg = NetworkConfig()
    path = save_model(tmp_path / "m.pt", QNetwork(cfg), cfg, {"steps": 0})
    grid = np.zeros((12, 12), dtype=np.uint8)
    obs = ObservationBuilder(grid, [[5, 5]]).build([[5, 5]], [0])  # on its goal, nobody near: settled
    batch = {k: np.repeat(v, 300, axis=0) for k, v in obs.items()}
    kept = Policy(path, rule=make_rule(action_temperature=100.0), seed=0)
    argmax = int(kept.q_values(obs["fov"], obs["last_action"], obs["position"]).argmax())
    assert (kept.act_obs(batch) == argmax).all()
    sampled = Policy(path, rule=make_rule(action_temperature=100.0, settled_greedy=False), seed=0)
    assert len(set(sampled.act_obs(batch).tolist())) == 5


def test_obstacle_moves_are_the_walls_and_map_edges_around_the_agent():
    grid = grid_from_text("""
.#..
....
""")
    obs = ObservationBuilder(grid, [[1, 3], [1, 0]], fov_size=3).build([[0, 0], [1, 2]], np.zeros(2, dtype=np.int64))
    # Agent 0 at the top-left corner, wall to its right: up, left (map edge) and right (obstacle) are blocked.
    # Agent 1 at (1, 2): down is off the map; up (0, 2) is free; no agent counts as an obstacle.
    assert obstacle_moves(obs["fov"]).tolist() == [[False, True, False, True, True],
                                                   [False, False, True, False, False]]


def test_excluded_actions_are_never_chosen_and_stay_cannot_be_excluded():
    q = np.tile([0.0, 5.0, 0.0, 0.0, 0.0], (2000, 1))
    excluded = np.zeros_like(q, dtype=bool)
    excluded[:, 1] = True
    greedy = select_actions(q, 0.0, None, excluded=excluded)
    assert (greedy == 0).all()  # the best action is excluded; ties among the rest go to stay
    sampled = select_actions(q, 10.0, np.random.default_rng(0), excluded=excluded)
    assert 1 not in set(sampled.tolist()) and set(sampled.tolist()) == {0, 2, 3, 4}
    excluded[0, 0] = True
    with pytest.raises(ValueError, match="stay.*cannot be excluded"):
        select_actions(q, 0.0, None, excluded=excluded)
    with pytest.raises(ValueError, match="excluded must have the shape"):
        select_actions(q, 0.0, None, excluded=np.zeros((2000, 4), dtype=bool))


def test_backtrack_move_points_at_the_previous_cell_only_when_it_is_a_neighbour():
    position = np.array([[5, 5], [5, 5], [5, 5], [5, 5]])
    previous = np.array([[4, 5], [5, 6], [5, 5], [7, 5]])  # came from above, from the right, stayed, jumped
    assert backtrack_moves(position, previous).tolist() == [[False, True, False, False, False],
                                                            [False, False, False, False, True],
                                                            [False] * 5, [False] * 5]
    with pytest.raises(ValueError, match="shape \\(batch, 2\\)"):
        backtrack_moves(position, previous[:2])


def test_policy_penalises_moving_back_from_its_own_memory_and_reset_forgets(tmp_path):
    torch.manual_seed(4)
    cfg = NetworkConfig()
    path = save_model(tmp_path / "m.pt", QNetwork(cfg), cfg, {"steps": 0})
    grid = np.zeros((12, 12), dtype=np.uint8)
    build = ObservationBuilder(grid, [[9, 9]]).build
    before, now = build([[5, 4]], [0]), build([[5, 5]], [4])  # moved right from (5, 4) to (5, 5)
    batch = {k: np.repeat(v, 400, axis=0) for k, v in now.items()}
    rule = make_rule(action_temperature=100.0, backtrack_penalty=1e6)  # near-uniform draws, moving back vetoed
    policy = Policy(path, rule=rule, seed=0)
    policy.act_obs({k: np.repeat(v, 400, axis=0) for k, v in before.items()})
    assert set(policy.act_obs(batch).tolist()) == {0, 1, 2, 4}  # never 3 (left, back to (5, 4))
    policy.reset(0)  # a new episode: no previous cell
    assert set(policy.act_obs(batch).tolist()) == {0, 1, 2, 3, 4}
    # Without the penalty, the memory changes nothing.
    free = Policy(path, rule=make_rule(action_temperature=100.0, backtrack_penalty=0.0), seed=0)
    free.act_obs({k: np.repeat(v, 400, axis=0) for k, v in before.items()})
    assert 3 in set(free.act_obs(batch).tolist())


def test_action_rule_is_validated_and_named_rules_are_known():
    assert ActionRule().asdict() == {"action_temperature": 0.04, "backtrack_penalty": 0.05,
                                     "mask_obstacle_moves": True, "settled_greedy": True, "goal_stay_bonus": 0.0}
    assert make_rule("paper") == PAPER_RULE and PAPER_RULE.action_temperature == 0.0
    assert make_rule("paper", action_temperature=0.04).mask_obstacle_moves is False
    with pytest.raises(ValueError, match="mask_obstacle_moves must be true or false"):
        ActionRule(mask_obstacle_moves="yes")
    with pytest.raises(ValueError, match="unknown action-rule fields \\['temperature'\\]"):
        make_rule(temperature=0.1)
    with pytest.raises(ValueError, match="rule must be an ActionRule"):
        Policy(QNetwork(NetworkConfig()), rule={"action_temperature": 0.1})


def test_goal_stay_bonus_holds_agents_on_their_goal_only(tmp_path):
    torch.manual_seed(5)
    cfg = NetworkConfig()
    path = save_model(tmp_path / "m.pt", QNetwork(cfg), cfg, {"steps": 0})
    grid = np.zeros((12, 12), dtype=np.uint8)
    # Two agents side by side, so neither is settled: agent 0 on its goal, agent 1 two cells from its goal.
    obs = ObservationBuilder(grid, [[5, 5], [5, 8]]).build([[5, 5], [5, 6]], [0, 0])
    batch = {k: np.repeat(v, 200, axis=0) for k, v in obs.items()}
    on = np.repeat([True, False], 200)
    held = Policy(path, rule=make_rule(action_temperature=100.0, goal_stay_bonus=1e6), seed=0).act_obs(batch)
    assert (held[on] == 0).all()  # on its goal: always stays
    assert len(set(held[~on].tolist())) > 2  # off its goal: untouched, near-uniform draws
    free = Policy(path, rule=make_rule(action_temperature=100.0), seed=0).act_obs(batch)
    assert (free[on] != 0).any()
    with pytest.raises(ValueError, match="goal_stay_bonus must be a finite number >= 0"):
        ActionRule(goal_stay_bonus=-0.1)


def test_per_agent_seeds_draw_what_one_robot_per_generator_draws():
    """Row i of a team chooser with per_agent_seeds samples exactly as a one-row chooser seeded with seed + i
    (robot i's policy node, seed -1 = its id), step after step."""
    rng = np.random.default_rng(3)
    rule = ActionRule(action_temperature=0.5, backtrack_penalty=0.0, mask_obstacle_moves=False)
    team = ActionChooser(rule, 0, per_agent_seeds=True)
    robots = [ActionChooser(rule, i) for i in range(4)]
    fov = np.zeros((4, 6, 9, 9))
    for _ in range(6):
        q = rng.normal(size=(4, 5))
        pos = rng.integers(0, 9, (4, 2))
        together = team.choose(q, fov, pos)
        alone = [robots[i].choose(q[i:i + 1], fov[i:i + 1], pos[i:i + 1])[0] for i in range(4)]
        assert together.tolist() == alone
    with pytest.raises(ValueError, match="per_agent_seeds"):
        ActionChooser(rule, None, per_agent_seeds=True)
