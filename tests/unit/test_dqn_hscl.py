"""The second training design's pieces: n-step rows, losses on the dueling split, the executed last action."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from mapf_policy.config import NetworkConfig
from mapf_policy.network import QNetwork, count_parameters
from mapf_policy.train.dqn_hscl import (Args, Replay, contact_rows, episode_rows, losses, meeting_rows, mixed_sample,
                                         parse_stage, play_episode)
from mapf_world.env import MapfEnv
from mapf_world.grid import STAY


def _steps(rewards, n_agents=1, l=9):
    """Per-step arrays of a fake episode with the given (T, N) rewards; observation t has position (t, 0)."""
    rewards = np.asarray(rewards, dtype=np.float32).reshape(len(rewards), n_agents)
    t_len = len(rewards)
    obs = [{"fov": np.zeros((n_agents, 6, l, l), np.float32), "last_action": np.eye(5, dtype=np.float32)[[t % 5] * n_agents],
            "position": np.full((n_agents, 2), t, np.float32), "still": np.full(n_agents, 10 * t)}
           for t in range(t_len + 1)]
    return {"obs": obs, "action": [np.ones(n_agents, np.int64)] * t_len, "reward": list(rewards),
            "expert": [np.full(n_agents, 2)] * t_len, "failed": [np.zeros(n_agents, bool)] * t_len}


def test_n_step_rows_of_a_terminated_episode():
    g = 0.9
    rows = episode_rows(_steps([-1, -2, 3]), terminated=True, gamma=g, n_step=2)
    np.testing.assert_allclose(rows["ret"], [-1 + g * -2, -2 + g * 3, 3], rtol=1e-6)
    # bootstrap from obs[t + 2] (or the end), discount gamma^m, none into the terminal state
    np.testing.assert_allclose(rows["boot_gamma"], [g ** 2, 0.0, 0.0], rtol=1e-6)
    assert rows["next_position"][:, 0].tolist() == [2, 3, 3]
    np.testing.assert_allclose(rows["mc_return"], [-1 + g * -2 + g * g * 3, -2 + g * 3, 3], rtol=1e-6)


def test_n_step_rows_of_a_truncated_episode_bootstrap_at_the_end():
    g = 0.5
    rows = episode_rows(_steps([-1, -1, -1]), terminated=False, gamma=g, n_step=3)
    np.testing.assert_allclose(rows["ret"], [-1.75, -1.5, -1.0])
    np.testing.assert_allclose(rows["boot_gamma"], [g ** 3, g ** 2, g])  # a time limit is no terminal state
    assert rows["next_last_action"].tolist() == [3, 3, 3]


def test_an_episode_shorter_than_n_step_sums_what_it_has():
    rows = episode_rows(_steps([-1, 3]), terminated=True, gamma=0.5, n_step=8)
    np.testing.assert_allclose(rows["ret"], [-1 + 0.5 * 3, 3])
    assert rows["boot_gamma"].tolist() == [0.0, 0.0]  # both reach the terminal state


def test_rows_are_step_major_over_agents():
    rows = episode_rows(_steps([[-1, 0], [3, 3]], n_agents=2), terminated=True, gamma=1.0, n_step=1)
    np.testing.assert_allclose(rows["ret"], [-1, 0, 3, 3])
    assert rows["position"][:, 0].tolist() == [0, 0, 1, 1]


def test_replay_keeps_the_newest_and_builds_inputs():
    rows = episode_rows(_steps([-1] * 5), terminated=False, gamma=0.9, n_step=1)
    rep = Replay(3)
    rep.add(rows)
    assert rep.size == 3 and sorted(rep.data["position"][:, 0].tolist()) == [2, 3, 4]
    b = rep.sample(4, np.random.default_rng(0))
    assert b["fov"].shape == (4, 6, 9, 9) and b["last_action"].shape == (4, 5) and b["action"].dtype == torch.int64


def test_a_mixed_batch_draws_its_share_from_the_mined_replay_once_it_can():
    main, mined = Replay(100), Replay(100)
    main.add(episode_rows(_steps([-1] * 20), terminated=False, gamma=0.9, n_step=1))
    rng = np.random.default_rng(0)
    b, n_main = mixed_sample(main, mined, 8, 0.25, rng)  # the mined replay is empty: all from the main one
    assert n_main == 8 and len(b["action"]) == 8
    mined_rows = episode_rows(_steps([3] * 4), terminated=True, gamma=0.9, n_step=1)
    mined_rows["position"][:] = 99  # tells the mined rows apart
    mined.add(mined_rows)
    b, n_main = mixed_sample(main, mined, 8, 0.25, rng)
    assert n_main == 6 and b["fov"].shape == (8, 6, 9, 9) and b["index"].shape == (8,)
    assert (b["position"][:6, 0] < 99).all() and (b["position"][6:, 0] == 99).all()
    assert mixed_sample(main, None, 8, 0.25, rng)[1] == 8
    with pytest.raises(ValueError, match="mined_batch_share needs mine_episodes"):
        Args(mined_batch_share=0.25).validate()


def test_prioritised_replay_draws_rows_by_td_error():
    rows = episode_rows(_steps([-1] * 4), terminated=False, gamma=0.9, n_step=1)
    rep = Replay(10, alpha=1.0, beta=1.0)
    rep.add(rows)
    assert rep.priority[:4].tolist() == [1.0] * 4  # new rows at the highest priority so far
    rep.update_priorities(np.arange(4), torch.tensor([0.0, 0.0, 0.0, 9.0]))
    b = rep.sample(4000, np.random.default_rng(0))
    drawn = np.bincount(b["index"], minlength=4) / 4000
    assert drawn[3] > 0.99 and rep.max_priority == pytest.approx(9.001)
    # importance weights (size * P)^-beta / max: the rarely drawn rows weigh 1, the frequent one about 1/9000
    w = dict(zip(b["index"].tolist(), b["weight"].tolist()))
    assert w[3] == pytest.approx(0.001 / 9.001, rel=1e-3) and max(w.values()) == 1.0
    rep.add(rows)  # new rows again at the maximum
    assert rep.priority[4:8].tolist() == [pytest.approx(9.001)] * 4


def test_dueling_network_adds_only_the_value_output():
    plain, dueling = QNetwork(NetworkConfig()), QNetwork(NetworkConfig(dueling=True))
    assert count_parameters(plain) == 1_004_443
    assert count_parameters(dueling) == 1_004_443 + 301


def test_hscl_on_the_advantage_ignores_the_level_of_q():
    """A shift of every Q-value of a row (the value V) changes the DQN term, never the HSCL term."""
    args = Args(dueling=True)
    q = torch.randn(8, 5)
    batch = {"action": torch.zeros(8, dtype=torch.long), "ret": torch.zeros(8), "boot_gamma": torch.zeros(8),
             "expert": torch.tensor([0, 1, 2, 3, 4, 1, -1, 2])}
    l1, l2, _ = losses(q, torch.zeros(8, 5), batch, args)
    l1s, l2s, _ = losses(q + torch.randn(8, 1) * 5, torch.zeros(8, 5), batch, args)
    assert torch.isclose(l2, l2s, atol=1e-5) and not torch.isclose(l1, l1s)
    plain = Args(dueling=False)
    assert not torch.isclose(losses(q, torch.zeros(8, 5), batch, plain)[1],
                             losses(q + 5, torch.zeros(8, 5), batch, plain)[1])


def test_td_error_uses_the_n_step_return_and_discount():
    q = torch.tensor([[0.0, 1.0, 0, 0, 0]])
    batch = {"action": torch.tensor([1]), "ret": torch.tensor([-0.5]), "boot_gamma": torch.tensor([0.81]),
             "expert": torch.tensor([-1])}
    _, _, td = losses(q, torch.tensor([[2.0, 0, 0, 0, 0]]), batch, Args())
    assert td.item() == pytest.approx(-0.5 + 0.81 * 2.0 - 1.0)


def test_infeasible_labels_lead_into_a_cell_another_agent_holds():
    from mapf_policy.train.dqn_hscl import infeasible_labels

    # agent 0 at (1,0) labelled right into (1,1), where agent 1 stays; agent 1 labelled stay; agent 2 moves
    # right into (0,1), which agent 3 leaves (following is feasible); agent 4 unlabelled.
    pos = np.array([[[1, 0], [1, 1], [0, 0], [0, 1], [3, 3]],
                    [[1, 0], [1, 1], [0, 1], [0, 2], [3, 3]]])
    expert = np.array([[4, 0, 4, 4, -1]])
    assert infeasible_labels(pos, expert).tolist() == [[True, False, False, False, False]]
    steps = _steps([[-0.5, 0.0, -0.075, -0.075, 0.0]], n_agents=5)
    steps["obs"][0]["position"], steps["obs"][1]["position"] = pos[0].astype(np.float32), pos[1].astype(np.float32)
    steps["expert"] = [expert[0]]
    assert episode_rows(steps, False, 0.9, 1, feasible_labels=True)["expert"].tolist() == [-1, 0, 4, 4, -1]
    assert episode_rows(steps, False, 0.9, 1)["expert"].tolist() == [4, 0, 4, 4, -1]


def test_labels_that_push_into_an_agent_parked_on_its_goal_are_dropped_on_request():
    from mapf_policy.train.dqn_hscl import parked_push_labels

    # agent 0 labelled right into (1,1), where agent 1 stands on its goal and steps aside down (as the joint plan
    # says: feasible); agent 2 labelled right into (0,1), which agent 3, off its goal, leaves; agent 4 unlabelled.
    pos = np.array([[[1, 0], [1, 1], [0, 0], [0, 1], [3, 3]],
                    [[1, 1], [2, 1], [0, 1], [0, 2], [3, 3]]])
    goals = np.array([[1, 3], [1, 1], [0, 4], [0, 5], [3, 0]])
    expert = np.array([[4, 2, 4, 4, -1]])
    assert parked_push_labels(pos, goals, expert).tolist() == [[True, False, False, False, False]]
    steps = _steps([[-0.075] * 5], n_agents=5)
    steps["obs"][0]["position"], steps["obs"][1]["position"] = pos[0].astype(np.float32), pos[1].astype(np.float32)
    steps["expert"] = [expert[0]]
    assert episode_rows(steps, False, 0.9, 1, goals=goals)["expert"].tolist() == [-1, 2, 4, 4, -1]
    assert episode_rows(steps, False, 0.9, 1)["expert"].tolist() == [4, 2, 4, 4, -1]


def test_monte_carlo_lower_bound_only_on_solved_rows():
    q = torch.zeros(2, 5)
    batch = {"action": torch.tensor([1, 1]), "ret": torch.tensor([-0.5, -0.5]), "boot_gamma": torch.tensor([0.5, 0.5]),
             "expert": torch.tensor([-1, -1]), "mc_return": torch.tensor([2.0, 2.0]), "solved": torch.tensor([True, False])}
    next_q = torch.full((2, 5), -1.0)
    _, _, td = losses(q, next_q, batch, Args(mc_lower_bound=True))
    assert td.tolist() == pytest.approx([2.0, -1.0])
    _, _, td = losses(q, next_q, batch, Args())
    assert td.tolist() == pytest.approx([-1.0, -1.0])


def test_executed_last_action_is_stay_after_a_refused_move():
    grid = np.zeros((3, 3), np.uint8)
    starts, goals = np.array([[1, 0], [1, 1]]), np.array([[1, 1], [1, 0]])
    for mode, expect in (("requested", [4, 3]), ("executed", [STAY, STAY])):
        env = MapfEnv(grid, starts, goals, last_action=mode)
        env.reset()
        obs, _, _, _, info = env.step([4, 3])  # a head-on swap: both refused
        assert info["failed"].all()
        assert obs["last_action"].argmax(axis=1).tolist() == expect
    with pytest.raises(ValueError, match="last_action"):
        MapfEnv(grid, starts, goals, last_action="planned")


def test_play_episode_with_the_expert_driving_solves_and_labels():
    from mapf_policy.train.expert import make_oracle

    grid = np.zeros((5, 5), np.uint8)
    env = MapfEnv(grid, np.array([[0, 0]]), np.array([[4, 4]]))
    oracle = make_oracle("shortest_path", env.grid, env.goals, env.dist, 10.0, 1.0)
    net = QNetwork(NetworkConfig(dueling=True)).eval()
    steps, stats = play_episode(net, env, 0.0, np.random.default_rng(0), oracle, 10.0, expert_drives=True)
    assert stats["success"] and stats["steps"] == 8 and stats["expert_drove"]
    assert all(e[0] in (2, 4) for e in steps["expert"])


@pytest.mark.parametrize("text,msg", [("4by20", "AGENTSxSIZE"), ("0x10", "agents"), ("60x10", "agents")])
def test_bad_stages_and_args_are_named(text, msg):
    with pytest.raises(ValueError, match=msg):
        parse_stage(text)
    with pytest.raises(ValueError, match="dqn_share"):
        Args(dqn_share=1.0).validate()
    with pytest.raises(ValueError, match="last_action"):
        Args(last_action="both").validate()
    with pytest.raises(ValueError, match="greedy_fraction"):
        Args(greedy_fraction=1.5).validate()
    with pytest.raises(ValueError, match="expert_order"):
        Args(expert_order="random").validate()
    with pytest.raises(ValueError, match="stuck_steps"):
        Args(stuck_steps=-1).validate()
    with pytest.raises(ValueError, match="blocking_penalty"):
        Args(blocking_penalty=0.5).validate()
    with pytest.raises(ValueError, match="imitation"):
        Args(imitation="supcon").validate()
    with pytest.raises(ValueError, match="priority_alpha"):
        Args(priority_alpha=2.0).validate()
    with pytest.raises(ValueError, match="expert_objective"):
        Args(expert_objective="sum_of_cost").validate()
    with pytest.raises(ValueError, match="expert_epsilon"):
        Args(expert_epsilon=0.5).validate()
    assert parse_stage("16x40") == (16, 40)


def test_goal_keeping_labels_go_round_an_agent_on_its_goal():
    # Agent 1 rests on its goal between agent 0 and agent 0's goal (planners' goal_keeping test). The paper's
    # expert labels the push and has agent 1 step aside; goal keeping (at epsilon 1) labels the way round.
    from mapf_policy.train.expert import make_oracle
    from mapf_world.grid import RIGHT, grid_from_text

    grid = grid_from_text(". . .\n. . .")
    env = MapfEnv(grid, np.array([[1, 0], [1, 1]]), np.array([[1, 2], [1, 1]]), max_steps=20)
    labels = {obj: make_oracle("odrmstar", env.grid, env.goals, env.dist, 1.0, 2.0, objective=obj).actions(env.positions)
              for obj in ("free_goal_wait", "goal_keeping")}
    assert labels["free_goal_wait"][0] == RIGHT and labels["free_goal_wait"][1] != STAY
    assert labels["goal_keeping"][0] != RIGHT and labels["goal_keeping"][1] == STAY


def test_the_harness_builds_observations_with_the_solvers_last_action_mode():
    from mapf_world.evaluate import run_case
    from mapf_world.instances import Instance

    class Pusher:  # both agents push into each other (a head-on swap, refused), recording what they see
        def __init__(self, mode):
            self.last_action, self.seen = mode, []

        def reset(self, env):
            pass

        def act(self, obs):
            self.seen.append(obs["last_action"].argmax(axis=1).tolist())
            return np.array([4, 3])

    inst = Instance(np.zeros((3, 3), np.uint8), np.array([[1, 0], [1, 1]]), np.array([[1, 1], [1, 0]]))
    for mode, second in (("executed", [STAY, STAY]), ("requested", [4, 3])):
        solver = Pusher(mode)
        run_case(solver, inst, 3)
        assert solver.seen[1] == second


def test_a_resumed_log_gets_the_columns_added_since(tmp_path):
    from mapf_policy.train.dqn_hscl import add_log_columns

    log = tmp_path / "train.csv"
    log.write_text("step,loss\n100,0.5\n200,0.4\n")
    add_log_columns(log, ("step", "new", "loss"))
    assert log.read_text().splitlines() == ["step,new,loss", "100,,0.5", "200,,0.4"]
    other = tmp_path / "other.csv"
    other.write_text("step,gone\n1,2\n")
    add_log_columns(other, ("step", "new"))  # not a subset: left alone (CsvLog refuses it)
    assert other.read_text() == "step,gone\n1,2\n"


def test_greedy_until_stuck_explores_only_after_a_fixed_point():
    """Two agents pushing head-on forever (a greedy deadlock): no random action before the positions have
    stayed the same for k steps, then epsilon (here 1) applies."""
    grid = np.zeros((3, 3), np.uint8)
    env = MapfEnv(grid, np.array([[1, 0], [1, 1]]), np.array([[1, 1], [1, 0]]), max_steps=12, last_action="executed")

    def push(fov, last, pos):  # agent 0 right, agent 1 left: a swap, refused every step
        return torch.tensor([[0.0, 0, 0, 0, 1], [0.0, 0, 0, 1, 0]])

    steps, _ = play_episode(push, env, 1.0, np.random.default_rng(1), greedy_until_stuck=3)
    acts = np.stack(steps["action"])
    assert acts[:3].tolist() == [[4, 3]] * 3  # greedy while the positions had stayed the same < 3 steps
    assert (acts[3:] != [4, 3]).any()  # exploration from the fixed point on
    steps, _ = play_episode(push, env, 1.0, np.random.default_rng(1), greedy_until_stuck=0)
    assert (np.stack(steps["action"])[:3] != [4, 3]).any()  # plain epsilon-greedy from the first step


def test_compare_and_failure_modes_evaluate_a_model_in_its_last_action_mode(tmp_path):
    """scripts/compare_models and scripts/failure_modes load a model and hand the network to the harness: the
    model file's last-action mode must come with it (they once played every model in 'requested')."""
    from mapf_policy.action_selection import PAPER_RULE
    from mapf_policy.model_io import load_model, save_model
    from mapf_policy.train.compare import policy_solver
    from mapf_policy.train.failures import _Recorder

    path = tmp_path / "m.pt"
    save_model(path, QNetwork(NetworkConfig(dueling=True)), NetworkConfig(dueling=True), {"last_action": "executed"})
    net, _, meta = load_model(path)
    solver = policy_solver(net, path, PAPER_RULE, 0, meta)
    assert solver.last_action == "executed" and _Recorder(solver).last_action == "executed"
    assert policy_solver(net, path, PAPER_RULE, 0).last_action == "requested"  # no metadata: the first design's


def test_rows_carry_the_still_counts_of_the_state_and_of_the_bootstrap_state():
    rows = episode_rows(_steps([-1, -2, -3]), terminated=False, gamma=0.9, n_step=2)
    assert rows["still"].tolist() == [0, 10, 20]
    assert rows["next_still"].tolist() == [20, 30, 30]  # obs[t + 2], cut at the end


def test_env_counts_the_steps_each_agent_stands_on_its_cell():
    grid = np.zeros((3, 3), np.uint8)
    env = MapfEnv(grid, np.array([[1, 0], [1, 1]]), np.array([[0, 0], [2, 1]]), max_steps=12)
    obs, _ = env.reset()
    assert obs["still"].tolist() == [0, 0]
    obs, *_ = env.step([4, 0])  # agent 0 pushes into agent 1 (refused), agent 1 stays
    assert obs["still"].tolist() == [1, 1] and obs["refused_run"].tolist() == [1, 0]
    obs, *_ = env.step([4, 0])  # again
    assert obs["still"].tolist() == [2, 2] and obs["refused_run"].tolist() == [2, 0]
    obs, *_ = env.step([1, 0])  # agent 0 moves up, agent 1 stays again
    assert obs["still"].tolist() == [0, 3] and obs["refused_run"].tolist() == [0, 0]
    obs, _ = env.reset()
    assert obs["still"].tolist() == [0, 0] and obs["refused_run"].tolist() == [0, 0]


def test_env_counts_the_steps_in_contact_with_the_same_unmoved_neighbours():
    grid = np.zeros((4, 4), np.uint8)
    env = MapfEnv(grid, np.array([[1, 0], [1, 1], [3, 3]]), np.array([[0, 0], [2, 1], [3, 2]]), max_steps=12)
    obs, _ = env.reset()
    assert obs["contact_run"].tolist() == [0, 0, 0]
    obs, *_ = env.step([4, 0, 0])  # 0 pushes into 1 (refused); both stay side by side; 2 alone
    assert obs["contact_run"].tolist() == [1, 1, 0]
    obs, *_ = env.step([0, 0, 0])
    assert obs["contact_run"].tolist() == [2, 2, 0]
    obs, *_ = env.step([1, 0, 0])  # 0 moves away: both counts end
    assert obs["contact_run"].tolist() == [0, 0, 0]


def test_a_network_with_the_still_input_reads_it_and_one_without_refuses_it():
    from mapf_policy.inference import InferenceNet
    from mapf_policy.network import network_inputs, still_onehot

    assert still_onehot(np.array([0, 2, 9]), 4).argmax(dim=1).tolist() == [0, 2, 3]  # 3 or more: the last bin
    with pytest.raises(ValueError, match="counts >= 0"):
        still_onehot(np.array([-1]), 4)
    grid = np.zeros((5, 5), np.uint8)
    env = MapfEnv(grid, np.array([[0, 0], [2, 2]]), np.array([[4, 4], [0, 4]]))
    obs, _ = env.reset()
    torch.manual_seed(0)
    net = QNetwork(NetworkConfig(dueling=True, still_bins=4)).eval()
    inputs = network_inputs(obs, net.cfg)
    assert len(inputs) == 4 and inputs[3].shape == (2, 4)
    q0 = net(*inputs)
    q3 = net(*inputs[:3], still_onehot(np.array([3, 3]), 4))
    assert not torch.allclose(q0, q3)  # the counts change the Q-values
    torch.testing.assert_close(InferenceNet(net)(*inputs), q0, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="still input"):
        net(*inputs[:3])
    plain = QNetwork(NetworkConfig(dueling=True)).eval()
    with pytest.raises(ValueError, match="no still input"):
        plain(*inputs)
    assert len(network_inputs(obs, plain.cfg)) == 3
    refused = QNetwork(NetworkConfig(dueling=True, still_bins=4, still_count="refused")).eval()
    assert torch.equal(network_inputs(obs | {"refused_run": np.array([5, 1])}, refused.cfg)[3].argmax(dim=1),
                       torch.tensor([3, 1]))
    with pytest.raises(ValueError, match="still_count"):
        NetworkConfig(still_bins=4, still_count="moves").validate()
    steps, _ = play_episode(InferenceNet(net), env, 0.0, np.random.default_rng(0))
    assert len(steps["action"]) >= 1


def test_double_dqn_values_the_online_argmax_with_the_target_network():
    batch = {"action": torch.tensor([0]), "ret": torch.tensor([0.0]), "boot_gamma": torch.tensor([1.0]),
             "expert": torch.tensor([-1]), "solved": torch.tensor([False]), "mc_return": torch.tensor([0.0])}
    q = torch.zeros(1, 5)
    next_target = torch.tensor([[1.0, 5.0, 0.0, 0.0, 0.0]])
    next_online = torch.tensor([[3.0, 2.0, 0.0, 0.0, 0.0]])  # the online net prefers action 0
    _, _, td_max = losses(q, next_target, batch, Args())
    _, _, td_double = losses(q, next_target, batch, Args(double_dqn=True), next_online)
    assert td_max.item() == 5.0 and td_double.item() == 1.0


def test_an_agent_on_its_goal_blocks_a_seen_agent_whose_path_it_cuts_or_lengthens_past_the_margin():
    from mapf_policy.train.dqn_hscl import blocking_agents
    from mapf_world.heuristics import distance_maps

    corridor = np.ones((3, 7), np.uint8)
    corridor[1] = 0  # one free row: an agent standing in it cuts the way through
    pos, goals = np.array([[1, 3], [1, 0]]), np.array([[1, 3], [1, 6]])
    dist = distance_maps(corridor, goals)
    assert blocking_agents(corridor, pos, goals, dist, margin=4).tolist() == [True, False]
    assert blocking_agents(corridor, pos, goals, dist, margin=4, radius=2).tolist() == [False, False]  # unseen
    off_goal = np.array([[1, 2], [1, 0]])  # the same agent one cell off its goal blocks nobody (it may move on)
    assert blocking_agents(corridor, off_goal, goals, dist, margin=4).tolist() == [False, False]

    open_grid = np.zeros((5, 5), np.uint8)  # in the open, going round costs 2 steps
    pos, goals = np.array([[2, 2], [2, 0]]), np.array([[2, 2], [2, 4]])
    dist = distance_maps(open_grid, goals)
    assert blocking_agents(open_grid, pos, goals, dist, margin=2).tolist() == [False, False]
    assert blocking_agents(open_grid, pos, goals, dist, margin=1).tolist() == [True, False]


def test_play_episode_charges_the_blocking_penalty_to_the_blocker_only():
    corridor = np.ones((3, 5), np.uint8)
    corridor[1] = 0
    env = MapfEnv(corridor, np.array([[1, 2], [1, 0]]), np.array([[1, 2], [1, 4]]), max_steps=3)

    def stay(fov, last, pos):  # both stay: agent 0 on its goal in the corridor, agent 1 waiting behind it
        return torch.tensor([[1.0, 0, 0, 0, 0]] * 2)

    plain, _ = play_episode(stay, env, 0.0, np.random.default_rng(0))
    shaped, stats = play_episode(stay, env, 0.0, np.random.default_rng(0), blocking=(-0.5, 4))
    diff = np.stack(shaped["reward"]) - np.stack(plain["reward"])
    assert np.allclose(diff, [[-0.5, 0.0]] * 3) and stats["blocked"] == 3


def test_play_episode_takes_one_epsilon_per_agent():
    grid = np.zeros((3, 3), np.uint8)
    env = MapfEnv(grid, np.array([[1, 0], [1, 1]]), np.array([[1, 1], [1, 0]]), max_steps=20)

    def push(fov, last, pos):
        return torch.tensor([[0.0, 0, 0, 0, 1], [0.0, 0, 0, 1, 0]])

    steps, _ = play_episode(push, env, np.array([0.0, 1.0]), np.random.default_rng(3))
    acts = np.stack(steps["action"])
    assert (acts[:, 0] == 4).all() and (acts[:, 1] != 3).any()  # agent 0 greedy throughout, agent 1 random


def test_without_goal_exploration_an_agent_on_its_goal_plays_greedily():
    grid = np.zeros((3, 3), np.uint8)
    env = MapfEnv(grid, np.array([[0, 0], [2, 2]]), np.array([[0, 0], [2, 0]]), max_steps=30)

    def stay(fov, last, pos):  # agent 0 starts on its goal; agent 1 does not
        return torch.tensor([[1.0, 0, 0, 0, 0]] * 2)

    steps, _ = play_episode(stay, env, 1.0, np.random.default_rng(0), goal_exploration=False)
    acts = np.stack(steps["action"])
    assert (acts[:, 0] == 0).all() and (acts[:, 1] != 0).any()
    steps, _ = play_episode(stay, env, 1.0, np.random.default_rng(0))
    assert (np.stack(steps["action"])[:, 0] != 0).any()  # the default: it explores like the others


def test_the_learning_rate_falls_linearly_to_lr_end_only_on_request():
    from mapf_policy.train.dqn_hscl import learning_rate
    flat, decay = Args(lr=1e-4, total_steps=1000), Args(lr=1e-4, lr_end=1e-5, total_steps=1000)
    assert learning_rate(flat, 0) == learning_rate(flat, 999) == 1e-4
    assert learning_rate(decay, 0) == 1e-4 and learning_rate(decay, 1000) == pytest.approx(1e-5)
    assert learning_rate(decay, 500) == pytest.approx(5.5e-5) and learning_rate(decay, 2000) == pytest.approx(1e-5)
    with pytest.raises(ValueError, match="lr_end"):
        Args(lr_end=-1.0).validate()


def test_advantage_learning_lowers_the_target_of_a_non_greedy_action_by_alpha_times_its_gap():
    q = torch.zeros(2, 5, requires_grad=True)
    q_target = torch.tensor([[0.0, 1.0, 0.2, 0.0, 0.0], [0.0, 1.0, 0.2, 0.0, 0.0]])
    batch = {"action": torch.tensor([1, 2]), "ret": torch.zeros(2), "boot_gamma": torch.zeros(2),
             "expert": torch.tensor([-1, -1]), "solved": torch.zeros(2, dtype=torch.bool)}
    args = Args(advantage_learning=0.5, huber_delta=10.0)
    _, _, td = losses(q, torch.zeros(2, 5), batch, args, q_target=q_target)
    assert td.tolist() == pytest.approx([0.0, -0.4])  # greedy action: no change; the other: 0.5 x (1.0 - 0.2)
    _, _, plain = losses(q, torch.zeros(2, 5), batch, Args(huber_delta=10.0), q_target=q_target)
    assert plain.tolist() == [0.0, 0.0]


def test_a_greedy_fixed_point_ends_the_episode_and_bootstraps_from_its_exact_value():
    """stuck_value: the head-on pushers above end the episode after 3 still steps, and the rows that bootstrap
    from the last state get the value of pushing for ever, -0.5 / (1 - gamma), with no network bootstrap."""
    grid = np.zeros((3, 3), np.uint8)
    env = MapfEnv(grid, np.array([[1, 0], [1, 1]]), np.array([[1, 1], [1, 0]]), max_steps=12, last_action="executed")

    def push(fov, last, pos):
        return torch.tensor([[0.0, 0, 0, 0, 1], [0.0, 0, 0, 1, 0]])

    steps, stats = play_episode(push, env, 1.0, np.random.default_rng(1), greedy_until_stuck=3, stuck_ends=True)
    assert stats["fixed_point"] and not stats["success"] and stats["steps"] == 3
    rows = episode_rows(steps, False, 0.9, 2, fixed_point=True)
    by_step = rows["ret"].reshape(3, 2)
    assert by_step[1].tolist() == pytest.approx([-5.0, -5.0]) and by_step[2].tolist() == pytest.approx([-5.0, -5.0])
    assert by_step[0].tolist() == pytest.approx([-0.95, -0.95])  # bootstraps from step 2, inside the episode
    assert rows["boot_gamma"].reshape(3, 2)[1:].tolist() == [[0.0, 0.0]] * 2
    assert rows["boot_gamma"].reshape(3, 2)[0].tolist() == pytest.approx([0.81, 0.81])
    plain = episode_rows(steps, False, 0.9, 2)
    assert plain["boot_gamma"].reshape(3, 2)[2].tolist() == pytest.approx([0.9, 0.9])  # a time limit bootstraps
    with pytest.raises(ValueError, match="stuck_value"):
        Args(stuck_value=True).validate()


def test_stuck_rescue_hands_a_greedy_fixed_point_to_the_expert_and_it_leads_the_team_out():
    """stuck_rescue: the head-on pushers above push greedily until they have stood still 3 steps; from then on the
    expert (ODrM*) drives, with no random steps although epsilon is 1, and its way out solves the case."""
    from mapf_policy.train.expert import make_oracle

    grid = np.zeros((3, 3), np.uint8)
    env = MapfEnv(grid, np.array([[1, 0], [1, 1]]), np.array([[1, 1], [1, 0]]), max_steps=20, last_action="executed")

    def push(fov, last, pos):
        return torch.tensor([[0.0, 0, 0, 0, 1], [0.0, 0, 0, 1, 0]])

    oracle = make_oracle("odrmstar", env.grid, env.goals, env.dist, 1.0, 2.0)
    steps, stats = play_episode(push, env, 1.0, np.random.default_rng(1), oracle, 5.0, greedy_until_stuck=3,
                                stuck_rescue=True)
    acts, labels = np.stack(steps["action"]), np.stack(steps["expert"])
    assert acts[:3].tolist() == [[4, 3]] * 3 and (labels[:3] >= 0).all()  # greedy, and labelled (DAgger)
    assert stats["rescued"] and stats["success"] and stats["expert_drove"]
    assert np.array_equal(acts[3:], labels[3:])  # the expert's actions, no random ones
    steps, stats = play_episode(push, env, 1.0, np.random.default_rng(1), oracle, 5.0, greedy_until_stuck=3)
    assert not stats["rescued"] and (np.stack(steps["action"])[3:] != np.stack(steps["expert"])[3:]).any()
    with pytest.raises(ValueError, match="stuck_rescue"):
        Args(stuck_rescue=True).validate()
    with pytest.raises(ValueError, match="stuck_rescue"):
        Args(stuck_rescue=True, greedy_fraction=0.25, stuck_steps=3, stuck_value=True).validate()
    Args(stuck_rescue=True, greedy_fraction=0.25, stuck_steps=3).validate()


def test_ce_imitation_is_the_cross_entropy_of_the_expert_action_under_the_advantage():
    q = torch.tensor([[0.3, 0.1, 0.0, -0.2, 0.5], [1.0, 1.2, 0.9, 0.8, 1.1]])
    batch = {"action": torch.tensor([0, 1]), "ret": torch.zeros(2), "boot_gamma": torch.zeros(2),
             "expert": torch.tensor([4, -1])}
    args = Args(imitation="ce", temperature=0.5)
    _, l_ce, _ = losses(q, torch.zeros(2, 5), batch, args)
    a = q[0] - q[0].mean()
    assert float(l_ce) == pytest.approx(float(-torch.log_softmax(a / 0.5, dim=0)[4]), rel=1e-6)
    with pytest.raises(ValueError, match="imitation"):
        Args(imitation="bc").validate()


def test_pushed_blockers_are_agents_that_stay_where_a_refused_move_tried_to_go():
    from mapf_policy.train.dqn_hscl import pushed_blockers
    # Step 0: agent 0 at (0, 0) pushes right into agent 1 at (0, 1), refused; agent 1 stays; agent 2 stays apart.
    # Step 1: agent 0 waits; agent 1 moves down (nobody pushes into anyone).
    positions = np.array([[[0, 0], [0, 1], [3, 3]], [[0, 0], [0, 1], [3, 3]], [[0, 0], [1, 1], [3, 3]]])
    actions = np.array([[4, 0, 0], [0, 2, 0]])
    failed = np.array([[True, False, False], [False, False, False]])
    assert pushed_blockers(positions, actions, failed).tolist() == [[False, True, False], [False, False, False]]
    # An agent whose own move was refused into the pusher's cell is not a blocker (it did not choose to stay).
    assert not pushed_blockers(positions[:2], np.array([[4, 3, 0]]), np.array([[True, True, False]])).any()


def test_distinct_observations_counts_repeated_states_once():
    from mapf_policy.train.dqn_hscl import distinct_observations
    fov = np.zeros((4, 2, 3, 3), np.uint8)
    fov[3, 0, 1, 1] = 1  # the fourth row sees something else
    rows = {"fov": fov, "last_action": np.array([0, 0, 1, 0], np.int8),
            "position": np.array([[1, 1], [1, 1], [1, 1], [1, 1]], np.int16)}
    assert distinct_observations(rows, np.array([True, True, False, False])) == 1  # two copies of one state
    assert distinct_observations(rows, np.ones(4, bool)) == 3  # another last action, another fov
    assert distinct_observations(rows, np.zeros(4, bool)) == 0


def test_blocker_weight_weighs_the_pushed_blockers_labelled_rows_in_the_ce_term():
    q = torch.tensor([[0.3, 0.1, 0.0, -0.2, 0.5], [1.0, 1.2, 0.9, 0.8, 1.1], [0.0, 0.4, 0.0, 0.0, 0.0]])
    batch = {"action": torch.tensor([0, 0, 0]), "ret": torch.zeros(3), "boot_gamma": torch.zeros(3),
             "expert": torch.tensor([4, 2, -1]), "blocker": torch.tensor([False, True, True])}
    per_row = [float(-torch.log_softmax((q[i] - q[i].mean()) / 0.1, dim=0)[k]) for i, k in ((0, 4), (1, 2))]
    _, plain, _ = losses(q, torch.zeros(3, 5), batch, Args(imitation="ce"))
    _, weighted, _ = losses(q, torch.zeros(3, 5), batch, Args(imitation="ce", blocker_weight=4.0))
    assert float(plain) == pytest.approx((per_row[0] + per_row[1]) / 2, rel=1e-5)
    assert float(weighted) == pytest.approx((per_row[0] + 4 * per_row[1]) / 5, rel=1e-5)  # the unlabelled row: none
    with pytest.raises(ValueError, match="blocker_weight"):
        Args(blocker_weight=4.0).validate()  # the HSCL term
    with pytest.raises(ValueError, match="blocker_weight"):
        Args(imitation="ce", blocker_weight=0.0).validate()


def test_meet_weight_weighs_the_meeting_rows_in_the_ce_term():
    q = torch.tensor([[0.3, 0.1, 0.0, -0.2, 0.5], [1.0, 1.2, 0.9, 0.8, 1.1], [0.0, 0.4, 0.0, 0.0, 0.0]])
    fov = torch.zeros(3, 6, 9, 9)
    fov[:, 2, 4, 4] = 1.0  # all three off their goal
    fov[1, 1, 2, 6] = 1.0  # row 1 sees another agent: a meeting row
    fov[2, 1, 0, 0] = 1.0  # row 2 too, but it has no label
    batch = {"action": torch.tensor([0, 0, 0]), "ret": torch.zeros(3), "boot_gamma": torch.zeros(3),
             "expert": torch.tensor([4, 2, -1]), "blocker": torch.tensor([False, False, True]), "fov": fov}
    per_row = [float(-torch.log_softmax((q[i] - q[i].mean()) / 0.1, dim=0)[k]) for i, k in ((0, 4), (1, 2))]
    _, weighted, _ = losses(q, torch.zeros(3, 5), batch, Args(imitation="ce", meet_weight=3.0))
    assert float(weighted) == pytest.approx((per_row[0] + 3 * per_row[1]) / 4, rel=1e-5)
    _, both, _ = losses(q, torch.zeros(3, 5), batch | {"blocker": torch.tensor([False, True, False])},
                        Args(imitation="ce", meet_weight=3.0, blocker_weight=2.0))
    assert float(both) == pytest.approx((per_row[0] + 6 * per_row[1]) / 7, rel=1e-5)  # the weights multiply
    with pytest.raises(ValueError, match="meet_weight"):
        Args(meet_weight=3.0).validate()  # the HSCL term
    with pytest.raises(ValueError, match="meet_weight"):
        Args(imitation="ce", meet_weight=-1.0).validate()


def test_ongoal_weight_weighs_the_expert_rows_of_agents_on_their_goal_not_the_searchs():
    from mapf_policy.train.dqn_hscl import ongoal_rows
    q = torch.tensor([[0.3, 0.1, 0.0, -0.2, 0.5], [1.0, 1.2, 0.9, 0.8, 1.1], [0.0, 0.4, 0.0, 0.0, 0.2],
                      [0.2, 0.0, 0.6, 0.0, 0.1]])
    fov = torch.zeros(4, 6, 9, 9)
    fov[0, 2, 4, 4] = 1.0  # row 0 off its goal, alone
    fov[1:, 1, 2, 6] = 1.0  # rows 1-3 on their goals (no heuristic bit at the centre), another agent in view
    assert ongoal_rows(fov).tolist() == [False, True, True, True]
    batch = {"action": torch.zeros(4, dtype=torch.long), "ret": torch.zeros(4), "boot_gamma": torch.zeros(4),
             "expert": torch.tensor([4, 0, 1, -1]), "blocker": torch.zeros(4, dtype=torch.bool), "fov": fov}
    per_row = [float(-torch.log_softmax((q[i] - q[i].mean()) / 0.1, dim=0)[k]) for i, k in ((0, 4), (1, 0), (2, 1))]
    _, plain, _ = losses(q, torch.zeros(4, 5), batch, Args(imitation="ce"))
    assert float(plain) == pytest.approx(sum(per_row) / 3, rel=1e-5)
    _, dropped, _ = losses(q, torch.zeros(4, 5), batch, Args(imitation="ce", ongoal_weight=0.0))
    assert float(dropped) == pytest.approx(per_row[0], rel=1e-5)  # the expert's on-goal labels weigh nothing
    # rows 2 and 3 came from the mined replay: the search's on-goal label (row 2) keeps its weight
    _, mined, _ = losses(q, torch.zeros(4, 5), batch, Args(imitation="ce", ongoal_weight=0.0), n_main=2)
    assert float(mined) == pytest.approx((per_row[0] + per_row[2]) / 2, rel=1e-5)
    _, half, _ = losses(q, torch.zeros(4, 5), batch, Args(imitation="ce", ongoal_weight=0.5), n_main=2)
    assert float(half) == pytest.approx((per_row[0] + 0.5 * per_row[1] + per_row[2]) / 2.5, rel=1e-5)
    only_ongoal = batch | {"expert": torch.tensor([-1, 0, -1, -1])}
    _, none, _ = losses(q, torch.zeros(4, 5), only_ongoal, Args(imitation="ce", ongoal_weight=0.0))
    assert float(none) == 0.0 and torch.isfinite(none)
    with pytest.raises(ValueError, match="ongoal_weight"):
        Args(ongoal_weight=0.0).validate()  # the HSCL term
    with pytest.raises(ValueError, match="ongoal_weight"):
        Args(imitation="ce", ongoal_weight=-1.0).validate()


def test_episode_rows_mark_the_pushed_blockers():
    from mapf_policy.train.dqn_hscl import episode_rows
    env = MapfEnv(np.zeros((3, 3), dtype=bool), [(0, 0), (0, 1)], [(0, 2), (0, 1)], max_steps=4)
    obs0, _ = env.reset()
    steps = {"obs": [obs0], "action": [], "reward": [], "expert": [], "failed": []}
    obs, reward, _, _, info = env.step(np.array([4, 0]))  # agent 0 pushes right into agent 1, parked on its goal
    for k, v in (("obs", obs), ("action", np.array([4, 0])), ("reward", reward), ("expert", np.array([1, 2])),
                 ("failed", info["failed"])):
        steps[k].append(v)
    rows = episode_rows(steps, False, 0.99, 2)
    assert info["failed"].tolist() == [True, False] and rows["blocker"].tolist() == [False, True]


def test_replay_batches_carry_the_blocker_flag():
    env = MapfEnv(np.zeros((3, 3), dtype=bool), [(0, 0), (0, 1)], [(0, 2), (0, 1)], max_steps=4)
    obs0, _ = env.reset()
    obs, reward, _, _, info = env.step(np.array([4, 0]))
    steps = {"obs": [obs0, obs], "action": [np.array([4, 0])], "reward": [reward], "expert": [np.array([1, 2])],
             "failed": [info["failed"]]}
    replay = Replay(16, 0.0, 0.4)
    replay.add(episode_rows(steps, False, 0.99, 2))
    batch = replay.sample(8, np.random.default_rng(0))
    assert batch["blocker"].dtype == torch.bool and batch["blocker"].tolist() == (batch["index"] % 2 == 1).tolist()


def _heuristic_greedy(fov, last_action, position):
    """A stand-in greedy policy: a move that gets closer to the goal (right first), else stay."""
    h = fov[:, 2:6, 4, 4]
    return torch.cat([torch.full((fov.shape[0], 1), 0.5), h * torch.tensor([1.0, 1.0, 1.0, 1.5])], dim=1)


def test_best_deviation_finds_the_step_aside_that_gets_a_greedy_team_out():
    from mapf_policy.train.rollout import best_deviation
    from mapf_world.grid import RIGHT, STAY, UP
    # Agent 0 pushes right into agent 1, parked on its goal in an open 3x5 room: a greedy fixed point.
    env = MapfEnv(np.zeros((3, 5), np.uint8), np.array([[1, 1], [1, 2]]), np.array([[1, 4], [1, 2]]),
                  last_action="executed")
    env.reset()
    before = env.positions
    assert best_deviation(_heuristic_greedy, env, np.array([RIGHT, STAY]), 20, 2) == (1, UP)  # solved soonest
    assert np.array_equal(env.positions, before) and env.step_count == 0  # the search plays on copies only
    steps, stats = play_episode(_heuristic_greedy, env, 0.0, np.random.default_rng(0), greedy_until_stuck=2,
                                stuck_rollout=20)
    assert stats["success"] and stats["deviations"] == 1
    labels = np.stack(steps["expert"])
    assert labels[2].tolist() == [-1, UP] and (np.delete(labels, 2, axis=0) == -1).all()  # the deviation is the label


def test_best_deviation_gives_none_where_no_single_step_helps_and_the_episode_explores():
    from mapf_policy.train.rollout import best_deviation
    from mapf_world.grid import RIGHT, STAY
    # A one-row corridor: agent 1 cannot step aside, and nothing one agent does brings the team closer.
    env = MapfEnv(np.zeros((1, 5), np.uint8), np.array([[0, 1], [0, 2]]), np.array([[0, 4], [0, 2]]),
                  last_action="executed", max_steps=12)
    env.reset()
    assert best_deviation(_heuristic_greedy, env, np.array([RIGHT, STAY]), 20, 2) is None
    steps, stats = play_episode(_heuristic_greedy, env, 0.3, np.random.default_rng(0), greedy_until_stuck=2,
                                stuck_rollout=20)
    assert not stats["success"] and stats["deviations"] == 0 and stats["steps"] == 12  # explored to the time limit
    steps, stats = play_episode(_heuristic_greedy, env, 0.0, np.random.default_rng(0), greedy_until_stuck=2,
                                stuck_rollout=20)
    assert stats["deviations"] == 0 and stats["steps"] == 2  # with nothing to explore with, it ends where it is stuck
    assert len(steps["obs"]) == len(steps["action"]) + 1 == 3  # k = 2 still steps, then the search


def test_stuck_rollout_needs_greedy_fixed_points():
    with pytest.raises(ValueError, match="stuck_rollout"):
        Args(stuck_rollout=16).validate()
    with pytest.raises(ValueError, match="stuck_rollout"):
        Args(stuck_rollout=16, greedy_fraction=0.5, stuck_steps=3, stuck_rescue=True).validate()
    Args(stuck_rollout=16, greedy_fraction=0.5, stuck_steps=3).validate()
    with pytest.raises(ValueError, match="stuck_cycles"):
        Args(stuck_cycles=True).validate()
    with pytest.raises(ValueError, match="stuck_cycles"):
        Args(stuck_cycles=True, greedy_fraction=0.5, stuck_steps=1, still_bins=4).validate()
    Args(stuck_cycles=True, stuck_rollout=16, greedy_fraction=0.5, stuck_steps=1).validate()
    # the revisit count is the one count MapfEnv.joint_state holds (revisit_cap): cycles and mining allow it
    Args(stuck_cycles=True, stuck_rollout=16, greedy_fraction=0.5, stuck_steps=1, still_bins=4,
         still_count="revisit", mine_episodes=2).validate()
    with pytest.raises(ValueError, match="mine_episodes"):
        Args(stuck_cycles=True, stuck_rollout=16, greedy_fraction=0.5, stuck_steps=1, still_bins=4,
             still_count="cell", mine_episodes=2).validate()
    with pytest.raises(ValueError, match="mine_episodes"):
        Args(mine_episodes=2).validate()


def test_stuck_cycles_catch_a_team_that_steps_back_and_forth():
    from mapf_world.grid import LEFT, RIGHT

    def back_and_forth(fov, last_action, position):  # right after anything but a right, then left: a 2-cycle
        went_right = last_action[:, RIGHT] == 1
        return torch.nn.functional.one_hot(torch.where(went_right, LEFT, RIGHT), 5).float()

    def play(cycles):
        env = MapfEnv(np.zeros((3, 5), np.uint8), np.array([[2, 0]]), np.array([[0, 4]]), last_action="executed",
                      max_steps=40)
        return play_episode(back_and_forth, env, 0.0, np.random.default_rng(0), greedy_until_stuck=2, stuck_rollout=8,
                            stuck_cycles=cycles)[1]
    still_only = play(False)  # it never stands still, so k still steps never call the search
    assert still_only["deviations"] == 0 and not still_only["success"]
    cycles = play(True)  # each repeat of (position, last action) calls it: a step up, closer to the goal
    assert cycles["deviations"] >= 1 and cycles["success"]


def test_the_lockstep_screen_finds_exactly_the_greedy_teams_that_get_stuck():
    from mapf_policy.train.rollout import greedy_gets_stuck
    from mapf_world.instances import generate_instance

    def env_of(seed, agents):
        inst = generate_instance(np.random.default_rng(seed), size=10, density=0.3, n_agents=agents)
        return MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=64, last_action="executed")

    envs = [env_of(seed, 2 if seed % 5 == 0 else 4) for seed in range(30)]  # teams of two sizes in one batch
    screened = greedy_gets_stuck(_heuristic_greedy, envs)
    one_by_one = [play_episode(_heuristic_greedy, env, 0.0, np.random.default_rng(0), greedy_until_stuck=1,
                               stuck_cycles=True, stuck_ends=True)[1]["fixed_point"] for env in envs]
    assert screened.tolist() == one_by_one
    assert 0 < screened.sum() < len(envs)  # both kinds of team are in the sample
    assert greedy_gets_stuck(_heuristic_greedy, []).shape == (0,)


def test_contact_rows_are_off_goal_agents_touching_an_earlier_agent():
    grid = np.zeros((12, 12), dtype=np.int8)
    # 0 and 1 side by side (1 touches the earlier 0; 0 touches only a later agent); 2 diagonal to 1 (touches no one);
    # 3 below 0, on its goal (touches 0 but is home); 4 far from all
    starts, goals = [(2, 2), (2, 3), (3, 4), (3, 2), (10, 10)], [(6, 2), (8, 4), (8, 8), (3, 2), (10, 6)]
    env = MapfEnv(grid, starts, goals, max_steps=8, heading=True, priority=True)
    obs, _ = env.reset()
    fov = torch.from_numpy(np.asarray(obs["fov"], dtype=np.float32))
    cfg = NetworkConfig(heading=True, priority=True)
    assert contact_rows(fov, cfg.in_channels + int(cfg.heading)).tolist() == [False, True, False, False, False]
    assert Args(heading=True, priority=True).priority_channel() == cfg.in_channels + int(cfg.heading)


def test_meeting_rows_are_off_goal_agents_with_another_in_view():
    grid = np.zeros((12, 12), dtype=np.int8)
    # agent 0 off goal, agent 1 two cells away (in view), agent 2 on its goal beside agent 1, agent 3 far from all
    starts, goals = [(2, 2), (2, 4), (2, 5), (10, 10)], [(6, 2), (8, 4), (2, 5), (10, 6)]
    env = MapfEnv(grid, starts, goals, max_steps=8)
    obs, _ = env.reset()
    fov = torch.from_numpy(np.asarray(obs["fov"], dtype=np.float32))
    assert meeting_rows(fov).tolist() == [True, True, False, False]
