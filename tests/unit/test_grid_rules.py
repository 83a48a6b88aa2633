"""The DHC step rules (resolve_moves) and the shared input checks of mapf_world.grid."""
from __future__ import annotations

import numpy as np
import pytest

from mapf_world.grid import (
    DELTAS,
    DOWN,
    LEFT,
    RIGHT,
    STAY,
    UP,
    check_actions,
    check_cells,
    check_grid,
    grid_from_text,
)
from mapf_world.rules import resolve_moves

OPEN5 = np.zeros((5, 5), dtype=np.uint8)


def step(grid, positions, actions):
    new, failed = resolve_moves(np.asarray(grid, dtype=np.uint8), np.array(positions), np.array(actions))
    return new.tolist(), failed.tolist()


# --- conventions ------------------------------------------------------------------------------
def test_action_constants_and_deltas():
    assert (STAY, UP, DOWN, LEFT, RIGHT) == (0, 1, 2, 3, 4)
    assert DELTAS.tolist() == [[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]]


# --- single agents ----------------------------------------------------------------------------
@pytest.mark.parametrize(
    "action, expected", [(STAY, [2, 2]), (UP, [1, 2]), (DOWN, [3, 2]), (LEFT, [2, 1]), (RIGHT, [2, 3])]
)
def test_single_moves(action, expected):
    assert step(OPEN5, [[2, 2]], [action]) == ([expected], [False])


@pytest.mark.parametrize("cell, action", [([0, 2], UP), ([4, 2], DOWN), ([2, 0], LEFT), ([2, 4], RIGHT)])
def test_move_off_map_fails(cell, action):
    assert step(OPEN5, [cell], [action]) == ([cell], [True])


def test_move_into_obstacle_fails_and_stay_never_fails():
    grid = grid_from_text(". # .\n. . .")
    assert step(grid, [[0, 0], [1, 1]], [RIGHT, UP]) == ([[0, 0], [1, 1]], [True, True])
    assert step(grid, [[0, 0], [1, 1]], [STAY, STAY]) == ([[0, 0], [1, 1]], [False, False])


def test_rectangular_map_bounds():
    grid = np.zeros((2, 6), dtype=np.uint8)
    assert step(grid, [[1, 5], [0, 0]], [DOWN, RIGHT]) == ([[1, 5], [0, 1]], [True, False])
    assert step(grid, [[1, 5]], [UP]) == ([[0, 5]], [False])


# --- agent-agent conflicts -------------------------------------------------------------------
def test_swap_both_stay():
    assert step(OPEN5, [[2, 2], [2, 3]], [RIGHT, LEFT]) == ([[2, 2], [2, 3]], [True, True])
    assert step(OPEN5, [[1, 1], [2, 1]], [DOWN, UP]) == ([[1, 1], [2, 1]], [True, True])


@pytest.mark.parametrize("order", [(0, 1), (1, 0)])
def test_vertex_conflict_lowest_index_wins(order):
    cells = [[2, 1], [2, 3]]  # both move into (2, 2)
    acts = [RIGHT, LEFT]
    pos = [cells[k] for k in order]
    act = [acts[k] for k in order]
    new, failed = step(OPEN5, pos, act)
    assert new == [[2, 2], pos[1]]
    assert failed == [False, True]


def test_vertex_conflict_of_four_lowest_index_wins():
    pos = [[1, 2], [2, 1], [3, 2], [2, 3]]
    acts = [DOWN, RIGHT, UP, LEFT]
    # Agent 2 has the lowest index among movers into (2, 2) only when 0 and 1 are made stayers.
    new, failed = step(OPEN5, pos, acts)
    assert new == [[2, 2], [2, 1], [3, 2], [2, 3]]
    assert failed == [False, True, True, True]
    new, failed = step(OPEN5, pos, [STAY, STAY, UP, LEFT])
    assert new == [[1, 2], [2, 1], [2, 2], [2, 3]]
    assert failed == [False, False, False, True]


def test_mover_into_a_staying_agent_fails():
    assert step(OPEN5, [[2, 1], [2, 2]], [RIGHT, STAY]) == ([[2, 1], [2, 2]], [True, False])


def test_blocked_by_stayer_all_movers_fail_even_the_lowest_index():
    # Agent 2 stays on (2, 2); agents 0 and 1 both move there: neither gets it.
    new, failed = step(OPEN5, [[2, 1], [2, 3], [2, 2]], [RIGHT, LEFT, STAY])
    assert new == [[2, 1], [2, 3], [2, 2]]
    assert failed == [True, True, False]


def test_blocked_by_agent_whose_own_move_failed():
    # Agent 1 tries to walk into the wall and stays, so agent 0 following it fails too.
    grid = grid_from_text(". . #")
    assert step(grid, [[0, 0], [0, 1]], [RIGHT, RIGHT]) == ([[0, 0], [0, 1]], [True, True])


def test_cascade_through_a_chain():
    # 0 -> 1's cell -> 2's cell -> 3's cell; agent 3 is blocked by the map edge: all fail.
    pos = [[0, 0], [0, 1], [0, 2], [0, 3]]
    grid = np.zeros((1, 4), dtype=np.uint8)
    assert step(grid, pos, [RIGHT] * 4) == (pos, [True] * 4)


def test_cascade_from_a_lost_vertex_conflict():
    # Agents 0 and 1 both enter (2, 2): 1 loses and stays on (2, 3), so agent 2, which wanted
    # to follow 1 into (2, 3), fails in the next round; agent 0 keeps (2, 2).
    pos = [[1, 2], [2, 3], [2, 4]]
    new, failed = step(OPEN5, pos, [DOWN, LEFT, LEFT])
    assert new == [[2, 2], [2, 3], [2, 4]]
    assert failed == [False, True, True]


def test_cascade_back_onto_the_winner():
    # A 4-cycle 1 -> 2 -> 3 -> 4 -> 1 through (1,1), (1,2), (2,2), (2,1); agent 0 also wants (1,1)
    # and agent 5 also wants (2,1). Round 1: 0 beats 4 for (1,1), 3 beats 5 for (2,1). Agent 4
    # now stays on (2,1), so 3 fails, then 2, then 1; 1 stays on (1,1), so the winner 0 fails too.
    pos = [[0, 1], [1, 1], [1, 2], [2, 2], [2, 1], [3, 1]]
    acts = [DOWN, RIGHT, DOWN, LEFT, UP, UP]
    assert step(OPEN5, pos, acts) == (pos, [True] * 6)


def test_following_chain_moves_together():
    pos = [[2, 0], [2, 1], [2, 2], [2, 3]]
    new, failed = step(OPEN5, pos, [RIGHT] * 4)
    assert new == [[2, 1], [2, 2], [2, 3], [2, 4]]
    assert failed == [False] * 4


def test_rotation_of_three_around_a_free_cell():
    # A 4-connected grid has no 3-cycles; three agents rotate through a 2x2 block by each
    # entering the cell the next one leaves (the last enters the free cell).
    pos = [[0, 0], [0, 1], [1, 1]]
    new, failed = step(np.zeros((2, 2), np.uint8), pos, [RIGHT, DOWN, LEFT])
    assert new == [[0, 1], [1, 1], [1, 0]]
    assert failed == [False] * 3


def test_rotation_of_four_is_allowed():
    pos = [[0, 0], [0, 1], [1, 1], [1, 0]]
    new, failed = step(np.zeros((2, 2), np.uint8), pos, [RIGHT, DOWN, LEFT, UP])
    assert new == [[0, 1], [1, 1], [1, 0], [0, 0]]
    assert failed == [False] * 4


def test_rotation_of_eight_around_an_obstacle():
    grid = grid_from_text("...\n.#.\n...")
    ring = [[0, 0], [0, 1], [0, 2], [1, 2], [2, 2], [2, 1], [2, 0], [1, 0]]
    acts = [RIGHT, RIGHT, DOWN, DOWN, LEFT, LEFT, UP, UP]
    new, failed = step(grid, ring, acts)
    assert new == ring[1:] + ring[:1]
    assert not any(failed)


# --- the rules restated as a slow reference, compared on random crowded cases -----------------
def reference_step(grid, pos, acts):
    h, w = grid.shape
    pos = [tuple(p) for p in pos]
    nxt = []
    failed = [False] * len(pos)
    for i, (p, a) in enumerate(zip(pos, acts)):
        q = (p[0] + DELTAS[a][0], p[1] + DELTAS[a][1])
        if a != 0 and not (0 <= q[0] < h and 0 <= q[1] < w and grid[q] == 0):
            q, failed[i] = p, True
        nxt.append(q)
    moving = [nxt[i] != pos[i] for i in range(len(pos))]
    for i in range(len(pos)):
        for j in range(i + 1, len(pos)):
            if moving[i] and moving[j] and nxt[i] == pos[j] and nxt[j] == pos[i]:
                for k in (i, j):
                    nxt[k], moving[k], failed[k] = pos[k], False, True
    changed = True
    while changed:
        changed = False
        for cell in {nxt[i] for i in range(len(pos)) if moving[i]}:
            movers = [i for i in range(len(pos)) if moving[i] and nxt[i] == cell]
            stayer = any(not moving[j] and pos[j] == cell for j in range(len(pos)))
            losers = movers if stayer else movers[1:]
            for k in losers:
                nxt[k], moving[k], failed[k] = pos[k], False, True
                changed = True
            if changed:
                break
    return [list(q) for q in nxt], failed


def test_matches_reference_on_random_crowded_cases():
    rng = np.random.default_rng(12345)
    n_conflicts = 0
    for _ in range(400):
        h, w = rng.integers(2, 7, size=2)
        grid = (rng.random((h, w)) < 0.2).astype(np.uint8)
        free = np.argwhere(grid == 0)
        n = int(rng.integers(1, len(free) + 1))
        pos = free[rng.choice(len(free), n, replace=False)]
        acts = rng.integers(0, 5, n)
        got = step(grid, pos, acts)
        want = reference_step(grid, pos, acts)
        assert got == want, (grid.tolist(), pos.tolist(), acts.tolist())
        new = np.array(got[0])
        assert len({tuple(c) for c in new.tolist()}) == n  # never two agents on one cell
        n_conflicts += sum(got[1])
    assert n_conflicts > 100  # the cases were crowded enough to exercise the conflict rules


def test_resolve_moves_is_pure():
    pos = np.array([[2, 1], [2, 2]])
    acts = np.array([RIGHT, RIGHT])
    before = pos.copy()
    resolve_moves(OPEN5, pos, acts)
    assert (pos == before).all() and acts.tolist() == [RIGHT, RIGHT]


# --- input checks -----------------------------------------------------------------------------
def test_check_grid_accepts_bool_and_ints_and_rejects_the_rest():
    assert check_grid([[True, False]]).dtype == np.uint8
    assert check_grid(np.array([[0, 1]], dtype=np.int64)).tolist() == [[0, 1]]
    with pytest.raises(ValueError, match="2-D"):
        check_grid(np.zeros(4))
    with pytest.raises(ValueError, match=r"cell \(0, 1\) is 2"):
        check_grid([[0, 2]])
    with pytest.raises(ValueError, match="empty"):
        check_grid(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="dtype"):
        check_grid(np.array([["a", "b"]]))


@pytest.mark.parametrize(
    "cells, pattern",
    [
        ([[0, 0], [5, 0]], r"agent 1 cell \(5, 0\) is off the 5x5 map"),
        ([[-1, 0]], r"agent 0 cell \(-1, 0\) is off"),
        ([[0, 0], [1, 1], [1, 1]], r"agents \[1, 2\] share cell \(1, 1\)"),
        ([[0, 0], [2, 2]], r"agent 1 cell \(2, 2\) is on an obstacle"),
        ([[0.5, 1]], "integer"),
        ([0, 1], r"\(N, 2\)"),
        (np.zeros((0, 2)), "at least one"),
    ],
)
def test_check_cells_errors_name_agent_and_problem(cells, pattern):
    grid = OPEN5.copy()
    grid[2, 2] = 1
    with pytest.raises(ValueError, match=pattern):
        check_cells(grid, cells, what="starts")


def test_check_cells_names_what():
    with pytest.raises(ValueError, match="^goals: agent 0"):
        check_cells(OPEN5, [[9, 9]], what="goals")


@pytest.mark.parametrize(
    "actions, pattern",
    [
        ([0, 1], "expected 3 actions"),
        ([0, 1, 2, 3], "expected 3 actions"),
        ([0, 5, 1], "agent 1: action 5 is outside 0..4"),
        ([0, 1, -1], "agent 2: action -1"),
        ([0.5, 1, 2], "integers"),
        ([True, False, True], "integers"),
        ([[0, 1, 2]], "expected 3 actions"),
    ],
)
def test_check_actions_errors(actions, pattern):
    with pytest.raises(ValueError, match=pattern):
        check_actions(np.array(actions), 3)


def test_grid_from_text():
    assert grid_from_text(". #\n# .").tolist() == [[0, 1], [1, 0]]
    with pytest.raises(ValueError, match="row 1 has 1 cells"):
        grid_from_text("..\n.")
    with pytest.raises(ValueError, match="unknown characters"):
        grid_from_text(".x")


def test_resolve_moves_checks_actions():
    with pytest.raises(ValueError, match="action 7"):
        resolve_moves(OPEN5, np.array([[1, 1]]), np.array([7]))
    assert check_actions([1.0, 2.0], 2).tolist() == [1, 2]
