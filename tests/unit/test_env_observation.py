"""MapfEnv (rewards, termination, truncation, bad input), distance maps and observations."""
from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from mapf_world.env import MapfEnv
from mapf_world.grid import DELTAS, DOWN, LEFT, RIGHT, STAY, grid_from_text
from mapf_world.heuristics import UNREACHABLE, connected_components, distance_maps
from mapf_world.observation import ObservationBuilder

RING = grid_from_text("...\n.#.\n...")


def python_bfs(grid, goal):
    h, w = grid.shape
    dist = np.full((h, w), UNREACHABLE, dtype=np.int64)
    dist[tuple(goal)] = 0
    queue = deque([tuple(goal)])
    while queue:
        r, c = queue.popleft()
        for dr, dc in DELTAS[1:]:
            a, b = r + dr, c + dc
            if 0 <= a < h and 0 <= b < w and grid[a, b] == 0 and dist[a, b] == UNREACHABLE:
                dist[a, b] = dist[r, c] + 1
                queue.append((a, b))
    return dist


def random_case(rng, h, w, n, density=0.3):
    grid = (rng.random((h, w)) < density).astype(np.uint8)
    labels = connected_components(grid)
    largest = np.bincount(labels[labels >= 0]).argmax()
    free = np.argwhere(labels == largest)  # so that every goal is reachable
    cells = free[rng.choice(len(free), 2 * n, replace=False)]
    return grid, cells[:n], cells[n:]


# --- heuristics -------------------------------------------------------------------------------
def test_distance_maps_match_python_bfs_on_rectangular_maps():
    rng = np.random.default_rng(7)
    for h, w in [(6, 11), (13, 4), (20, 20)]:
        grid, _, goals = random_case(rng, h, w, 5)
        dist = distance_maps(grid, goals)
        assert dist.shape == (5, h, w) and dist.dtype == np.int32
        for i, goal in enumerate(goals):
            assert (dist[i] == python_bfs(grid, goal)).all()
        assert (dist[:, grid == 1] == UNREACHABLE).all()


def test_distance_maps_hand_example():
    grid = grid_from_text("..#.\n....\n#...")
    dist = distance_maps(grid, [[0, 3]])[0]
    u = UNREACHABLE
    assert dist.tolist() == [[5, 4, u, 0], [4, 3, 2, 1], [u, 4, 3, 2]]


def test_connected_components():
    grid = grid_from_text("..#.\n..#.\n##..\n.#..")
    labels = connected_components(grid)
    assert labels.tolist() == [[0, 0, -1, 3], [0, 0, -1, 3], [-1, -1, 3, 3], [12, -1, 3, 3]]


# --- observations -----------------------------------------------------------------------------
def test_observation_hand_built_fov3():
    # Agent 0 at (0, 2), goal (0, 0); agent 1 at (1, 2), goal (2, 2); obstacle in the centre.
    builder = ObservationBuilder(RING, [[0, 0], [2, 2]], fov_size=3)
    obs = builder.build(np.array([[0, 2], [1, 2]]), np.array([LEFT, STAY]))
    fov = obs["fov"]
    assert fov.shape == (2, 6, 3, 3) and fov.dtype == np.float32
    z = [[0, 0, 0]] * 3
    # Agent 0: window rows -1..1, cols 1..3 (row -1 and col 3 are outside the map = obstacles).
    assert fov[0, 0].tolist() == [[1, 1, 1], [0, 0, 1], [1, 0, 1]]
    assert fov[0, 1].tolist() == [[0, 0, 0], [0, 0, 0], [0, 1, 0]]
    assert fov[0, 2].tolist() == [[0, 0, 0], [0, 0, 0], [0, 1, 0]]  # up: (1,2) -> (0,2) is closer
    assert fov[0, 3].tolist() == z  # down never gets closer to (0, 0) here
    assert fov[0, 4].tolist() == [[0, 0, 0], [1, 1, 0], [0, 0, 0]]  # left along row 0
    assert fov[0, 5].tolist() == z
    # Agent 1: window rows 0..2, cols 1..3.
    assert fov[1, 0].tolist() == [[0, 0, 1], [1, 0, 1], [0, 0, 1]]
    assert fov[1, 1].tolist() == [[0, 1, 0], [0, 0, 0], [0, 0, 0]]
    assert fov[1, 2].tolist() == z
    assert fov[1, 3].tolist() == [[0, 1, 0], [0, 1, 0], [0, 0, 0]]
    assert fov[1, 4].tolist() == z
    assert fov[1, 5].tolist() == [[1, 0, 0], [0, 0, 0], [1, 0, 0]]
    assert obs["last_action"].tolist() == [[0, 0, 0, 1, 0], [1, 0, 0, 0, 0]]
    assert obs["position"].tolist() == [[0, 2], [1, 2]] and obs["position"].dtype == np.float32


def reference_fov(grid, dist_i, positions, i, size):
    h, w = grid.shape
    r = size // 2
    out = np.zeros((6, size, size), dtype=np.float32)
    pos = {tuple(p) for k, p in enumerate(positions.tolist()) if k != i}
    for y in range(size):
        for x in range(size):
            row, col = positions[i][0] - r + y, positions[i][1] - r + x
            if not (0 <= row < h and 0 <= col < w):
                out[0, y, x] = 1
                continue
            out[0, y, x] = grid[row, col]
            out[1, y, x] = (row, col) in pos
            if grid[row, col]:
                continue
            for a in range(4):
                nr, nc = row + DELTAS[a + 1][0], col + DELTAS[a + 1][1]
                if 0 <= nr < h and 0 <= nc < w and dist_i[nr, nc] < dist_i[row, col]:
                    out[2 + a, y, x] = 1
    return out


@pytest.mark.parametrize("fov_size", [3, 5, 9, 11])
def test_observation_matches_loop_reference_on_random_rectangular_maps(fov_size):
    rng = np.random.default_rng(fov_size)
    grid, starts, goals = random_case(rng, 9, 14, 6)
    builder = ObservationBuilder(grid, goals, fov_size=fov_size)
    acts = rng.integers(0, 5, 6)
    obs = builder.build(starts, acts)
    dists = [python_bfs(grid, g) for g in goals]
    for i in range(6):
        want = reference_fov(grid, dists[i], starts, i, fov_size)
        assert (obs["fov"][i] == want).all()
        one = builder.build_one(i, starts, acts[i])
        assert (one["fov"] == want).all()
        assert one["last_action"].tolist() == np.eye(5)[acts[i]].tolist()
        assert one["position"].tolist() == starts[i].tolist()
    # Building must not leave agents marked in the builder's scratch map.
    again = builder.build(goals, acts)
    assert again["fov"][:, 1].sum() <= 5 * 6


@pytest.mark.parametrize("fov_size", [2, 1, 8, 0, 3.0, True])
def test_bad_fov_size(fov_size):
    with pytest.raises(ValueError, match="fov_size"):
        ObservationBuilder(RING, [[0, 0]], fov_size=fov_size)


def test_observation_builder_bad_input():
    builder = ObservationBuilder(RING, [[0, 0], [2, 2]], fov_size=3)
    with pytest.raises(ValueError, match="positions must have shape"):
        builder.build(np.array([[0, 0]]), np.array([0, 0]))
    with pytest.raises(ValueError, match="agent 1: position"):
        builder.build(np.array([[0, 0], [3, 0]]), np.array([0, 0]))
    with pytest.raises(ValueError, match="action 9"):
        builder.build(np.array([[0, 0], [2, 2]]), np.array([0, 9]))
    with pytest.raises(ValueError, match="agent index 2"):
        builder.build_one(2, np.array([[0, 0], [2, 2]]), 0)
    with pytest.raises(ValueError, match="dist must have shape"):
        ObservationBuilder(RING, [[0, 0]], dist=np.zeros((2, 3, 3)))


# --- environment ------------------------------------------------------------------------------
def test_reset_and_step_api_shapes():
    rng = np.random.default_rng(3)
    grid, starts, goals = random_case(rng, 12, 12, 4)
    env = MapfEnv(grid, starts, goals)
    obs, info = env.reset()
    assert obs["fov"].shape == (4, 6, 9, 9)
    assert obs["last_action"].shape == (4, 5) and obs["position"].shape == (4, 2)
    assert info["step"] == 0 and not info["success"] and info["on_goal"].shape == (4,)
    assert (env.positions == starts).all() and env.n_agents == 4 and env.step_count == 0
    obs, rewards, terminated, truncated, info = env.step(np.zeros(4, dtype=int))
    assert rewards.shape == (4,) and rewards.dtype == np.float32
    assert isinstance(terminated, bool) and isinstance(truncated, bool)
    assert set(info) >= {"failed", "on_goal", "step", "success"} and info["step"] == 1
    pos = env.positions
    pos[0] = [-5, -5]
    assert (env.positions == starts).all()  # a copy


def test_rewards_per_case():
    # Agent 0 moves, 1 stays on its goal, 2 stays off its goal, 3 bumps into the wall.
    grid = grid_from_text("....#\n.....\n.....")
    starts = [[1, 0], [2, 2], [0, 2], [0, 3]]
    goals = [[2, 4], [2, 2], [2, 3], [1, 3]]
    env = MapfEnv(grid, starts, goals)
    env.reset()
    _, rewards, terminated, truncated, info = env.step([RIGHT, STAY, STAY, RIGHT])
    assert rewards.tolist() == pytest.approx([-0.075, 0.0, -0.075, -0.5])
    assert info["failed"].tolist() == [False, False, False, True]
    assert info["on_goal"].tolist() == [False, True, False, False]
    assert not terminated and not truncated
    # Collisions with agents cost -0.5 as well: 0 swaps with nobody, 2 walks into agent 1.
    _, rewards, *_ = env.step([STAY, STAY, DOWN, STAY])
    assert rewards.tolist() == pytest.approx([-0.075, 0.0, -0.075, -0.075])
    _, rewards, *_ = env.step([STAY, STAY, RIGHT, STAY])
    assert rewards.tolist() == pytest.approx([-0.075, 0.0, -0.075, -0.075])
    assert env.last_actions.tolist() == [STAY, STAY, RIGHT, STAY]


def test_failed_move_into_agent_costs_half():
    env = MapfEnv(np.zeros((1, 3), np.uint8), [[0, 0], [0, 1]], [[0, 2], [0, 1]])
    env.reset()
    _, rewards, *_ , info = env.step([RIGHT, STAY])
    assert rewards.tolist() == pytest.approx([-0.5, 0.0]) and info["failed"].tolist() == [True, False]


def test_finish_gives_three_to_everyone_and_ends_the_episode():
    env = MapfEnv(np.zeros((2, 3), np.uint8), [[0, 0], [1, 2]], [[0, 1], [1, 2]])
    env.reset()
    _, rewards, terminated, truncated, info = env.step([RIGHT, STAY])
    assert rewards.tolist() == [3.0, 3.0]
    assert terminated and not truncated and info["success"] and info["on_goal"].all()
    with pytest.raises(ValueError, match="ended"):
        env.step([STAY, STAY])
    # Being on the goal earlier and leaving again is no success: only the same step counts.
    env.reset()
    _, rewards, terminated, *_ = env.step([STAY, LEFT])
    assert not terminated and rewards.tolist() == pytest.approx([-0.075, -0.075])


def test_truncation_at_256_steps():
    env = MapfEnv(np.zeros((3, 3), np.uint8), [[0, 0]], [[2, 2]])
    env.reset()
    for t in range(1, 257):
        _, rewards, terminated, truncated, info = env.step([STAY])
        assert not terminated and truncated == (t == 256) and info["step"] == t
    assert rewards.tolist() == pytest.approx([-0.075]) and not info["success"]
    with pytest.raises(ValueError, match="ended"):
        env.step([STAY])
    env.reset()
    assert env.step_count == 0 and (env.positions == [[0, 0]]).all()


def test_success_on_the_last_allowed_step_is_not_truncated():
    env = MapfEnv(np.zeros((1, 3), np.uint8), [[0, 0]], [[0, 2]], max_steps=2)
    env.reset()
    env.step([RIGHT])
    _, _, terminated, truncated, _ = env.step([RIGHT])
    assert terminated and not truncated


def test_step_before_reset_is_an_error():
    env = MapfEnv(np.zeros((1, 2), np.uint8), [[0, 0]], [[0, 1]])
    with pytest.raises(ValueError, match="reset"):
        env.step([RIGHT])


def test_all_agents_starting_on_goals_is_solved_at_reset():
    env = MapfEnv(np.zeros((1, 2), np.uint8), [[0, 0]], [[0, 0]])
    _, info = env.reset()
    assert info["success"]
    with pytest.raises(ValueError):
        env.step([STAY])


def test_rectangular_map_episode():
    grid = grid_from_text("......#\n.#.....\n....#..")
    env = MapfEnv(grid, [[0, 0], [2, 6]], [[2, 6], [0, 0]], fov_size=5)
    obs, _ = env.reset()
    assert obs["fov"].shape == (2, 6, 5, 5) and env.dist.shape == (2, 3, 7)
    # Walk agent 0 along its shortest path while agent 1 waits: distances drop by one per step.
    for _ in range(8):
        d0 = env.dist[0][tuple(env.positions[0])]
        bits = obs["fov"][0, 2:, 2, 2]
        action = 1 + int(np.argmax(bits))
        assert bits.max() == 1
        obs, _, _, _, info = env.step([action, STAY])
        if info["failed"][0]:
            break
        assert env.dist[0][tuple(env.positions[0])] == d0 - 1
    assert info["failed"][0]  # agent 1 stands on agent 0's goal


def test_reset_reuses_the_distance_maps():
    rng = np.random.default_rng(11)
    grid, starts, goals = random_case(rng, 20, 20, 8)
    env = MapfEnv(grid, starts, goals)
    env.reset()
    first = env.dist
    env.step(rng.integers(0, 5, 8))
    obs, _ = env.reset()
    assert env.dist is first and (env.positions == starts).all()
    assert (obs["last_action"][:, 0] == 1).all()


@pytest.mark.parametrize(
    "starts, goals, pattern",
    [
        ([[0, 0], [1, 1]], [[0, 2], [2, 2]], r"starts: agent 1 cell \(1, 1\) is on an obstacle"),
        ([[0, 0], [3, 1]], [[0, 2], [2, 2]], r"starts: agent 1 cell \(3, 1\) is off the 3x3 map"),
        ([[0, 0], [0, 0]], [[0, 2], [2, 2]], r"starts: agents \[0, 1\] share cell"),
        ([[0, 0], [0, 1]], [[2, 2], [2, 2]], r"goals: agents \[0, 1\] share cell"),
        ([[0, 0], [0, 1]], [[2, 2], [1, 1]], r"goals: agent 1 cell \(1, 1\) is on an obstacle"),
        ([[0, 0], [0, 1]], [[2, 2]], "2 starts but 1 goals"),
    ],
)
def test_env_rejects_bad_cells(starts, goals, pattern):
    with pytest.raises(ValueError, match=pattern):
        MapfEnv(RING, starts, goals)


def test_env_rejects_unreachable_goal():
    grid = grid_from_text("..#..\n..#..")
    with pytest.raises(ValueError, match=r"agent 1: goal \[0, 4\] is unreachable from start \[1, 0\]"):
        MapfEnv(grid, [[0, 0], [1, 0]], [[0, 1], [0, 4]])


def test_env_rejects_bad_actions_and_options():
    env = MapfEnv(RING, [[0, 0], [2, 2]], [[0, 2], [2, 0]])
    env.reset()
    with pytest.raises(ValueError, match="expected 2 actions"):
        env.step([0])
    with pytest.raises(ValueError, match="agent 0: action 5"):
        env.step([5, 0])
    with pytest.raises(ValueError, match="integers"):
        env.step([0.5, 1])
    assert env.step_count == 0  # rejected steps change nothing
    with pytest.raises(ValueError, match="max_steps"):
        MapfEnv(RING, [[0, 0]], [[0, 2]], max_steps=0)
    with pytest.raises(ValueError, match="fov_size"):
        MapfEnv(RING, [[0, 0]], [[0, 2]], fov_size=4)


@pytest.mark.parametrize("heading", [False, True])
def test_deep_copy_plays_on_alone_and_shares_the_fixed_parts(heading):
    """copy.deepcopy(env) (the rollout search's copies): the copy and the original step apart, each as a fresh env
    replaying its own actions would; the map, distance maps and observation builder are shared, not copied. (A plain
    deep copy of the builder made its agent windows a frozen copy instead of a view of its scratch map: the copy's
    observations showed no other agents.)"""
    import copy

    rng = np.random.default_rng(7)
    grid, starts, goals = random_case(rng, 12, 15, 5)
    make = lambda: MapfEnv(grid, starts, goals, last_action="executed", heading=heading)  # noqa: E731
    env = make()
    env.reset()
    head = [rng.integers(0, 5, 5) for _ in range(6)]
    for a in head:
        env.step(a)
    twin = copy.deepcopy(env)
    tails = {id(env): [rng.integers(0, 5, 5) for _ in range(8)], id(twin): [rng.integers(0, 5, 5) for _ in range(8)]}
    # interleaved, so a shared scratch map or state would show up in the other env's observations
    for a, b in zip(tails[id(env)], tails[id(twin)]):
        got_env, got_twin = env.step(a), twin.step(b)
    for played, got in ((tails[id(env)], got_env), (tails[id(twin)], got_twin)):
        ref = make()
        ref.reset()
        for a in head + played:
            want = ref.step(a)
        for key in ("fov", "last_action", "position", "revisits"):
            np.testing.assert_array_equal(got[0][key], want[0][key])
        np.testing.assert_array_equal(got[1], want[1])
    assert env.step_count == twin.step_count == 14
    assert twin.observation_builder is env.observation_builder and twin.dist is env.dist and twin.grid is env.grid
    assert not np.array_equal(env.positions, twin.positions) or not np.array_equal(env.last_actions, twin.last_actions)


def test_a_deep_copy_of_the_builder_sees_the_agents():
    """ObservationBuilder's own deep copy: its windows look at its own maps (a plain deep copy froze them, and its
    agent channel stayed empty)."""
    import copy

    rng = np.random.default_rng(3)
    grid, starts, goals = random_case(rng, 11, 13, 4)
    builder = ObservationBuilder(grid, goals)
    twin = copy.deepcopy(builder)
    assert twin._agents is not builder._agents
    for key in ("fov", "last_action", "position"):
        np.testing.assert_array_equal(twin.build(starts, [STAY] * 4)[key], builder.build(starts, [STAY] * 4)[key])
    assert builder.build(starts, [STAY] * 4)["fov"][:, 1].any()  # the case has agents in each other's view


def test_revisits_count_a_loop_and_the_window_forgets():
    """revisits: how many of the agent's last REVISIT_WINDOW positions (before this step) held its current cell.
    A back-and-forth loop raises it on both cells, waiting raises it by one a step, and a visit that has left the
    window no longer counts; reset() clears it."""
    from mapf_world.env import REVISIT_WINDOW

    grid = grid_from_text("." * 20)
    env = MapfEnv(grid, [[0, 0]], [[0, 19]])
    obs, _ = env.reset()
    assert obs["revisits"].tolist() == [0]
    seen = [int(env.step([a])[0]["revisits"][0]) for a in [RIGHT, LEFT, RIGHT, LEFT, STAY, STAY]]
    assert seen == [0, 1, 1, 2, 3, 4]  # (0,1) new; (0,0) again; (0,1) again; ...; waiting on (0,0) adds one a step
    assert REVISIT_WINDOW == 16
    for out, back_count in ((8, 1), (9, 0)):  # to (0,1), `out` cells on and back: (0,1) was at step 1
        env.reset()
        for a in [RIGHT] * (1 + out) + [LEFT] * out:
            obs = env.step([a])[0]
        assert env.positions.tolist() == [[0, 1]] and env.step_count == 1 + 2 * out
        assert obs["revisits"].tolist() == [back_count]  # in the last 16 positions (steps 1-16), or not (3-18)
    env.reset()
    assert env.observe()["revisits"].tolist() == [0]


def test_joint_state_holds_the_capped_revisits_only_when_asked():
    """A memoryless policy that reads revisits (capped at c, revisit_cap=c) loops for ever only where positions, last
    actions and the capped counts repeat: joint_state holds them then; without a cap it holds no count at all."""
    grid = grid_from_text("." * 6)
    plain, capped = MapfEnv(grid, [[0, 0]], [[0, 5]]), MapfEnv(grid, [[0, 0]], [[0, 5]], revisit_cap=2)
    for env in (plain, capped):
        env.reset()
    keys = {id(plain): [], id(capped): []}
    for a in [RIGHT, LEFT, RIGHT, LEFT, RIGHT, LEFT, RIGHT, LEFT]:
        for env in (plain, capped):
            env.step([a])
            keys[id(env)].append(env.joint_state())
    assert keys[id(plain)][1] == keys[id(plain)][3]  # back on (0,0) after LEFT: the same key at once
    assert keys[id(capped)][1] != keys[id(capped)][3]  # counts 1, 2 differ
    assert keys[id(capped)][5] == keys[id(capped)][7]  # both capped at 2
    with pytest.raises(ValueError, match="revisit_cap"):
        MapfEnv(grid, [[0, 0]], [[0, 5]], revisit_cap=-1)
