"""Choosing an action from an agent's Q-values: greedy (the paper) or Boltzmann sampling (an extension).

Why sampling. A greedy policy is a fixed function of the observation, and the observation holds no
memory beyond the last action. When two agents meet head-on in a one-cell corridor, each sees the same
observation at every step, picks the same move into the other, both moves fail (the benchmark's swap
rule), and nothing ever changes: the case runs to the step limit. The same happens when an agent
standing on its goal blocks the only way to another agent's goal, and when an agent toggles between two
cells. These three patterns were every failure of the shipped model on held-out 4-agent cases and most
failures at 16 agents (models/README.md, "Action selection").

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

Two more rules, also beyond the paper and also from the agent's own knowledge only:
- Moves into a static obstacle or off the map are never chosen (`mask_obstacle_moves`): the obstacle
  channel of the observation shows them, and such a move always fails and wastes the step. With
  sampling, a wall move whose Q-value is close to the best one would otherwise be drawn now and then.
- The move back into the cell the agent occupied at the previous step loses `backtrack_penalty` from
  its Q-value. This needs one cell of memory per agent (Policy keeps it); it damps the two-cell
  oscillations that sampled agents fall into in crowds, and shortens paths at 16 to 64 agents.
An ablation, off by default: `goal_stay_bonus` adds to the Q-value of staying for an agent on its goal.
On held-out 64-agent cases it halved how often agents beside others leave their goals, but solved no more
cases, and a larger bonus solved far fewer (models/EXPERIMENTS.md, "How the held-out 32- and 64-agent
cases fail").
All five settings form one typed ActionRule. PAPER_RULE (greedy, no mask, no penalty) is the paper's
action selection; the default rule was chosen on held-out generated cases, never on the benchmark
(models/README.md, "Action selection").

"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from mapf_world.grid import DELTAS

GREEDY = 0.0
# The default of every entry point (evaluation solver, policy node, demo). Chosen on held-out generated
# cases of the COMPARE seed stream, never on the benchmark: models/README.md, "Action selection".
DEFAULT_ACTION_TEMPERATURE = 0.04
# In Q-value units (a step costs 0.075 in the rules' rewards). Chosen like the temperature.
DEFAULT_BACKTRACK_PENALTY = 0.05


def _non_negative(value, name: str, zero: str) -> float:
    """value >= 0 as a float; anything else is an error naming `name`, the value and what 0 means."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number >= 0 (0 = {zero}), got {value!r}")
    v = float(value)
    if not math.isfinite(v) or v < 0:
        raise ValueError(f"{name} must be a finite number >= 0 (0 = {zero}), got {value!r}")
    return v


def check_action_temperature(value) -> float:
    """T >= 0 as a float; 0 means greedy."""
    return _non_negative(value, "action_temperature", "greedy")


def check_backtrack_penalty(value) -> float:
    """penalty >= 0 as a float (Q-value units); 0 turns the rule off."""
    return _non_negative(value, "backtrack_penalty", "off")


def _check_fov(fov) -> np.ndarray:
    fov = np.asarray(fov)
    if fov.ndim != 4 or fov.shape[1] != 6 or fov.shape[2] != fov.shape[3] or fov.shape[2] < 3:
        raise ValueError(f"fov must have shape (batch, 6, l, l) with l >= 3, got {fov.shape}")
    return fov


def on_goal(fov: np.ndarray) -> np.ndarray:
    """(B,) bool from (B, 6, l, l) observations: the agent stands on its own goal.

    Channels 2..5 (heuristic up/down/left/right) mark the moves that get closer to the goal; on the goal
    none does, so all four bits of the centre cell are 0. Anywhere else reachable at least one is 1.
    """
    fov = _check_fov(fov)
    c = fov.shape[2] // 2
    return fov[:, 2:6, c, c].sum(axis=1) == 0


def settled(fov: np.ndarray) -> np.ndarray:
    """(B,) bool from (B, 6, l, l) observations: on its own goal with no agent in a 4-neighbour cell."""
    fov = _check_fov(fov)
    c = fov.shape[2] // 2
    agents = fov[:, 1]
    neighbour = (agents[:, c - 1, c] + agents[:, c + 1, c] + agents[:, c, c - 1] + agents[:, c, c + 1]) > 0
    return on_goal(fov) & ~neighbour


def select_actions(q: np.ndarray, action_temperature: float, rng: np.random.Generator | None,
                   greedy_rows: np.ndarray | None = None, excluded: np.ndarray | None = None) -> np.ndarray:
    """(B,) int64 actions from (B, A) Q-values.

    T = 0: argmax, ties to the lowest index (stay first). T > 0: one draw per row from softmax(Q / T),
    which needs `rng`, except rows marked in `greedy_rows` (for example `settled(fov)`), which take argmax.
    `excluded` (B, A) bool marks actions never chosen (for example `obstacle_moves(fov)`); action 0 (stay)
    cannot be excluded, so every row keeps a choice.
    """
    q = np.asarray(q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] < 1:
        raise ValueError(f"Q-values must have shape (batch, actions), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError("Q-values contain NaN or infinity; the model or its input is broken")
    t = check_action_temperature(action_temperature)
    if excluded is not None:
        excluded = np.asarray(excluded, dtype=bool)
        if excluded.shape != q.shape:
            raise ValueError(f"excluded must have the shape of the Q-values {q.shape}, got {excluded.shape}")
        if excluded[:, 0].any():
            raise ValueError("action 0 (stay) cannot be excluded: it is always possible")
        q = np.where(excluded, -np.inf, q)
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


@dataclass(frozen=True)
class ActionRule:
    """How an agent turns its Q-values into an action (validated on construction)."""

    action_temperature: float = DEFAULT_ACTION_TEMPERATURE
    """0: argmax (the paper); > 0: one draw from softmax(Q / T)."""
    backtrack_penalty: float = DEFAULT_BACKTRACK_PENALTY
    """Subtracted from the Q-value of the move back into the previous step's cell (0: off)."""
    mask_obstacle_moves: bool = True
    """Never choose a move into a static obstacle or off the map."""
    settled_greedy: bool = True
    """Agents on their goal with no agent beside them take the argmax even when sampling."""
    goal_stay_bonus: float = 0.0
    """Added to the Q-value of staying for an agent on its own goal (0: off)."""

    def __post_init__(self):
        object.__setattr__(self, "action_temperature", check_action_temperature(self.action_temperature))
        object.__setattr__(self, "backtrack_penalty", check_backtrack_penalty(self.backtrack_penalty))
        object.__setattr__(self, "goal_stay_bonus", _non_negative(self.goal_stay_bonus, "goal_stay_bonus", "off"))
        for name in ("mask_obstacle_moves", "settled_greedy"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")
            object.__setattr__(self, name, bool(getattr(self, name)))

    def asdict(self) -> dict:
        return dataclasses.asdict(self)


# The paper's action selection: greedy argmax of the Q-values and nothing else.
PAPER_RULE = ActionRule(action_temperature=0.0, backtrack_penalty=0.0, mask_obstacle_moves=False)
RULES = {"default": ActionRule(), "paper": PAPER_RULE}
RULE_FIELDS = tuple(f.name for f in dataclasses.fields(ActionRule))


def make_rule(base: str | ActionRule = "default", **overrides) -> ActionRule:
    """A named rule (`default` or `paper`) or an ActionRule, with some fields replaced."""
    if isinstance(base, str):
        if base not in RULES:
            raise ValueError(f"unknown action rule {base!r}; known: {sorted(RULES)}")
        base = RULES[base]
    unknown = sorted(set(overrides) - set(RULE_FIELDS))
    if unknown:
        raise ValueError(f"unknown action-rule fields {unknown} (known: {list(RULE_FIELDS)})")
    return dataclasses.replace(base, **overrides)


def obstacle_moves(fov: np.ndarray) -> np.ndarray:
    """(B, 5) bool: the move's target cell is a static obstacle or off the map (fov channel 0). Stay: False."""
    fov = _check_fov(fov)
    c = fov.shape[2] // 2
    out = np.zeros((fov.shape[0], len(DELTAS)), dtype=bool)
    for a, (dr, dc) in enumerate(DELTAS[1:], start=1):
        out[:, a] = fov[:, 0, c + dr, c + dc] > 0
    return out


def backtrack_moves(position: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """(B, 5) bool: the move from `position` into `previous` (both (B, 2) cells). All False for an agent
    that did not move, or whose previous cell is not a neighbour (a new episode, a teleport)."""
    position = np.asarray(position)
    previous = np.asarray(previous)
    if position.ndim != 2 or position.shape[1] != 2 or previous.shape != position.shape:
        raise ValueError(f"position and previous must both have shape (batch, 2), got {position.shape} "
                         f"and {previous.shape}")
    step = np.rint(previous - position).astype(np.int64)  # (B, 2)
    out = (step[:, None, :] == DELTAS[None, :, :]).all(axis=2)
    out[:, 0] = False
    return out


class RowGenerators:
    """One generator per row, row i seeded with seed + i, drawing like one generator would for a batch:
    `gumbel(size=(B, A))` stacks row i's own (A,) draw. A team evaluated this way draws what a fleet draws,
    where robot i's policy node has its own generator seeded with its id (policy_node seed -1)."""

    def __init__(self, seed: int):
        self.seed, self.rows = seed, []

    def gumbel(self, size) -> np.ndarray:
        batch, width = size
        while len(self.rows) < batch:
            self.rows.append(np.random.default_rng(self.seed + len(self.rows)))
        return np.stack([self.rows[i].gumbel(size=width) for i in range(batch)])


class ActionChooser:
    """One ActionRule applied to Q-values, with the state the rule needs: its own sampling generator and each
    row's previous cell. Rows are agents, in a fixed order during an episode; `reset` starts a new one.
    Numpy only: the torch Policy (policy.py) and the robot's RuntimePolicy (runtime_policy.py) share it.
    `per_agent_seeds`: row i samples from its own generator, seeded with seed + i (RowGenerators), so that a
    team's draws equal those of a fleet whose robots each seed their own generator with their id."""

    def __init__(self, rule: ActionRule | None = None, seed: int | None = 0, per_agent_seeds: bool = False):
        if rule is None:
            rule = ActionRule()
        if not isinstance(rule, ActionRule):
            raise ValueError(f"rule must be an ActionRule, got {type(rule).__name__}")
        self.rule = rule
        self.per_agent_seeds = bool(per_agent_seeds)
        self.reset(seed)

    def reset(self, seed: int | None) -> None:
        """Restart the sampling generator (an int seed makes runs repeatable; None draws one) and forget every
        row's previous cell."""
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
            raise ValueError(f"seed must be an integer >= 0 or None, got {seed!r}")
        if self.per_agent_seeds and seed is None:
            raise ValueError("per_agent_seeds needs an integer seed (row i uses seed + i)")
        self.rng = RowGenerators(seed) if self.per_agent_seeds else np.random.default_rng(seed)
        self.previous = None  # (B, 2) cells of the last choose() call

    def choose(self, q: np.ndarray, fov: np.ndarray, position: np.ndarray) -> np.ndarray:
        """(B,) int64 actions from Q-values (B, 5), observations (B, 6, l, l) and cells (B, 2); greedy ties go
        to the lowest index (stay). Remembers `position` as each row's previous cell for the next call."""
        rule = self.rule
        q = np.asarray(q, dtype=np.float64)
        batch = q.shape[0]
        f = np.asarray(fov).reshape(batch, *np.shape(fov)[-3:])
        pos = np.asarray(position).reshape(batch, 2)
        if rule.backtrack_penalty > 0 and self.previous is not None and self.previous.shape == pos.shape:
            q = q - rule.backtrack_penalty * backtrack_moves(pos, self.previous)
        self.previous = pos.copy()
        if rule.goal_stay_bonus > 0:
            q = q.copy()
            q[:, 0] += rule.goal_stay_bonus * on_goal(f)
        rows = settled(f) if rule.action_temperature > 0 and rule.settled_greedy else None
        excluded = obstacle_moves(f) if rule.mask_obstacle_moves else None
        return select_actions(q, rule.action_temperature, self.rng, greedy_rows=rows, excluded=excluded)
