"""Choosing an action from an agent's Q-values: greedy (the paper) or Boltzmann sampling (an extension).

Why sampling. A greedy policy is a fixed function of the observation, and the observation holds no
memory beyond the last action. When two agents meet head-on in a one-cell corridor, each sees the same
observation at every step, picks the same move into the other, both moves fail (the benchmark's swap
rule), and nothing ever changes: the case runs to the step limit. The same happens when an agent
standing on its goal blocks the only way to another agent's goal, and when an agent toggles between two
cells. These three patterns were every failure of the shipped model on held-out 4-agent cases and most
failures at 16 agents (models/README.md, "Deadlocks").

Sampling a ~ softmax(Q(s, .) / T) with a small action temperature T keeps the expert-like first choice
most of the time and gives each agent of a stuck pair a chance, at every step, to do something else,
which breaks the symmetry. Each agent draws from its own generator: nothing is shared between agents,
so the policy stays decentralized and communication-free. T = 0 is the paper's greedy argmax.

Settled agents stay greedy. An agent that stands on its goal with no other agent in its four neighbour
cells has nothing to make way for, so it keeps its greedy action (in practice: stays). Sampling there
only made agents wander off their goals, which matters most with 64 agents, where every agent must be
on its goal at the same step (held-out 64-agent cases, models/README.md). Both facts come from the
agent's own observation: it is on its goal when no heuristic channel marks its own cell (no neighbour is
closer to the goal), and the agent channel shows its neighbours.

Sampling uses the Gumbel-max trick: argmax(Q / T + G) with G i.i.d. standard Gumbel is an exact draw
from softmax(Q / T), vectorized over a batch of agents.
"""
from __future__ import annotations

import math

import numpy as np

GREEDY = 0.0
# The default of every entry point (evaluation solver, policy node, demo). Chosen on held-out generated
# cases of the COMPARE seed stream, never on the benchmark: models/README.md, "Deadlocks".
DEFAULT_ACTION_TEMPERATURE = 0.04


def check_action_temperature(value) -> float:
    """T >= 0 as a float; 0 means greedy. Anything else is an error naming the value."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"action_temperature must be a number >= 0 (0 = greedy), got {value!r}")
    t = float(value)
    if not math.isfinite(t) or t < 0:
        raise ValueError(f"action_temperature must be a finite number >= 0 (0 = greedy), got {value!r}")
    return t


def settled(fov: np.ndarray) -> np.ndarray:
    """(B,) bool from (B, 6, l, l) observations: on its own goal with no agent in a 4-neighbour cell."""
    fov = np.asarray(fov)
    if fov.ndim != 4 or fov.shape[1] != 6 or fov.shape[2] != fov.shape[3] or fov.shape[2] < 3:
        raise ValueError(f"fov must have shape (batch, 6, l, l) with l >= 3, got {fov.shape}")
    c = fov.shape[2] // 2
    on_goal = fov[:, 2:6, c, c].sum(axis=1) == 0  # channels 2..5: heuristic up/down/left/right
    agents = fov[:, 1]
    neighbour = (agents[:, c - 1, c] + agents[:, c + 1, c] + agents[:, c, c - 1] + agents[:, c, c + 1]) > 0
    return on_goal & ~neighbour


def select_actions(q: np.ndarray, action_temperature: float, rng: np.random.Generator | None,
                   greedy_rows: np.ndarray | None = None) -> np.ndarray:
    """(B,) int64 actions from (B, A) Q-values.

    T = 0: argmax, ties to the lowest index (stay first). T > 0: one draw per row from softmax(Q / T),
    which needs `rng`, except rows marked in `greedy_rows` (for example `settled(fov)`), which take argmax.
    """
    q = np.asarray(q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] < 1:
        raise ValueError(f"Q-values must have shape (batch, actions), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError("Q-values contain NaN or infinity; the model or its input is broken")
    t = check_action_temperature(action_temperature)
    if t == GREEDY:
        return q.argmax(axis=1).astype(np.int64)
    if rng is None:
        raise ValueError(f"action_temperature {t} samples actions and needs a random generator")
    actions = (q / t + rng.gumbel(size=q.shape)).argmax(axis=1).astype(np.int64)
    if greedy_rows is not None:
        greedy_rows = np.asarray(greedy_rows, dtype=bool)
        if greedy_rows.shape != (q.shape[0],):
            raise ValueError(f"greedy_rows must have shape ({q.shape[0]},), got {greedy_rows.shape}")
        actions[greedy_rows] = q[greedy_rows].argmax(axis=1)
    return actions
