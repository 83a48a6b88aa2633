"""The ladder's stuck report: a plurality stay over moves that together outweigh it."""
import numpy as np

from mapf_policy.train.ladder import moves_outweigh_stay
from mapf_world.grid import STAY


def _q(stay: float, moves: list[float]) -> np.ndarray:
    q = np.array(moves[:STAY] + [stay] + moves[STAY:], dtype=np.float32)
    assert q[STAY] == stay
    return q


def test_a_stay_ahead_of_four_close_moves_is_a_plurality_over_a_split_majority():
    # At T = 0.1: stay e^0 = 1 against 4 e^-0.5 = 2.43: the moves together outweigh it.
    assert moves_outweigh_stay(_q(0.0, [-0.05, -0.05, -0.05, -0.05]), 0.1)


def test_a_stay_far_ahead_or_not_the_argmax_is_not():
    assert not moves_outweigh_stay(_q(0.0, [-1.0, -1.0, -1.0, -1.0]), 0.1)  # 4 e^-10: the stay dominates
    assert not moves_outweigh_stay(_q(0.0, [0.1, -1.0, -1.0, -1.0]), 0.1)  # a move is the argmax
    # The temperature decides it: the same values, colder, leave the stay ahead of the moves together.
    assert not moves_outweigh_stay(_q(0.0, [-0.05, -0.05, -0.05, -0.05]), 0.01)


def test_trajectory_period_finds_the_loop_a_team_ends_in():
    from mapf_policy.train.ladder import trajectory_period

    still = np.zeros((12, 2, 2), dtype=np.int64)  # nobody moves: a fixed point
    assert trajectory_period(still) == 1
    back_and_forth = np.array([[[0, k % 2], [3, 3]] for k in range(12)])  # one agent steps right, left, right...
    assert trajectory_period(back_and_forth) == 2
    loop = [[0, 0], [0, 1], [1, 1], [1, 0]]  # one agent round a 2x2 block, a loop of period 4
    assert trajectory_period(np.array([[loop[k % 4]] for k in range(20)])) == 4
    walk = np.array([[[0, k]] for k in range(20)])  # a straight walk never repeats
    assert trajectory_period(walk) is None
    assert trajectory_period(np.array([[loop[k % 4]] for k in range(6)])) is None  # too short to show period 4


def test_interacting_agents_are_off_their_goal_with_another_in_view():
    from mapf_policy.train.ladder import interacting

    positions = np.array([[0, 0], [4, 4], [8, 8], [20, 20]])
    goals = np.array([[5, 5], [4, 4], [0, 0], [0, 1]])
    # 0 and 2 are 4 from 1 (in a 9x9 view), 8 from each other; 1 stands on its goal; 3 sees no one.
    assert interacting(positions, goals, 4).tolist() == [True, False, True, False]
    assert interacting(positions, goals, 3).tolist() == [False, False, False, False]
