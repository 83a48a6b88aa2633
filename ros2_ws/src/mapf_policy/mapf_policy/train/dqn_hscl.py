"""The second training design: DQN + HSCL that cooperate, from random weights, in one process.

    scripts/dqn_hscl --run-name r1 --stages 1x10 4x20 --total-steps 20000

Reads top to bottom like CleanRL's dqn.py: Args, the pieces it needs, then `train()`, whose loop is
play an episode -> store its rows -> a few gradient steps -> log / evaluate / checkpoint.

What differs from the first design (mapf_policy/train/learner.py), and why (models/README.md, "Second design"):
- Dueling split Q = V + A - mean(A) (NetworkConfig.dueling). HSCL acts on the zero-mean advantage A, so the
  cosine with a hot vector measures the ranking of actions and nothing else, while the DQN fits the level
  of Q through V. In the first design both terms pulled on the same 5 numbers: HSCL wants them proportional
  to onehot - tau, the DQN wants them at the (negative) returns.
- n-step returns (default 2), Huber loss, gradient clip 40, batch 192, target sync 2,000 (DHC's values).
- The loss weights are set by measured gradient share: every log step the gradient norms of the two weighted
  terms are measured apart, and with `dqn_share` > 0 the HSCL weight is steered so that the DQN term gets that
  share of the update (the first design's nominal 0.5/0.5 gave the DQN about 0.5 %).
- A curriculum of stages "AGENTSxSIZE"; a stage is passed when the greedy policy solves `advance_pass_rate` of
  the stage's validation cases (own seed stream; the ladder's held-out cases are another). The pass rate of
  the epsilon-greedy training episodes was tried first and passed 1 agent on 10x10 at a greedy 0.65: random
  actions break the loops that stop a greedy agent. Earlier stages keep a share of the episodes.
- Some episodes are driven by the expert (ODrM*), so that the DQN term sees team successes (+3) early.
- The last-action input can be the executed action (`--last-action executed`, MapfEnv).
- Beyond the paper, off by default and labelled in Args: among others a recurrent variant (`--recurrent`: a GRU memory
  per agent, trained on sequences from stored memories, `recurrent_batch`), and greedy actor episodes that end at
  the greedy team's fixed points with their exact value (`--stuck-value`).
Everything runs in this process; actions come from InferenceNet (the fast CPU forward of inference.py).
The rollout search that labels a looping greedy team's way out (stuck_rollout, mining) is in rollout.py.
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import os
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F
from tqdm import tqdm

from mapf_policy.config import ABLATIONS, EXPERT_ORDERS, STILL_KEYS, NetworkConfig
from mapf_policy.inference import FastForward, InferenceNet
from mapf_policy.losses import expert_agreement, hscl_loss, margin_loss
from mapf_policy.model_io import load_model, save_model
from mapf_policy.network import QNetwork, network_inputs, still_onehot
from mapf_policy.train.demos import ACTOR_STREAM, VALID_STREAM, generated_cases, instance_rng
from mapf_policy.train.expert import ExpertFailed, make_oracle
from mapf_policy.train.log import CsvLog, read_csv, truncate_log
from mapf_policy.train.rollout import best_deviation, greedy_gets_stuck, mining_envs
from mapf_policy.train.symmetry import SYMMETRIES, Augmenter, direction_blocks
from mapf_world.env import LAST_ACTION_MODES, MapfEnv
from mapf_world.grid import DELTAS, STAY
from mapf_world.heuristics import distance_maps
from mapf_world.instances import generate_instance
from mapf_world.planners.odrmstar import OBJECTIVES as EXPERT_OBJECTIVES


# Options retired after their ablations lost (issue 20; EXPERIMENTS.md, fortieth session), with the value that means
# "off": a run saved with another value cannot be resumed by this code.
RETIRED = {"rollout_yielding": False, "rollout_plan_best": False, "contact_weight": 1.0}


@dataclass(frozen=True)
class Args:
    """One run of the second design; saved as config.json in the run directory."""

    run_name: str = "dqn_hscl"
    """Run directory runs/<run_name>; the same command resumes it."""
    init_model: str = ""
    """Start a new run from these weights (a model file of this run's network, e.g. an imitation run's last.pt; the
    target network is a copy) instead of random weights; a resumed run ignores it. Empty: random weights."""
    seed: int = 0
    """Seeds torch, numpy and the generated worlds (own streams for training and validation)."""
    variant: str = "hscl"
    """'hscl' (the paper's network) or a Table III ablation ('hscl_no_self_attention', ...)."""
    dueling: bool = True
    """Dueling split Q = V + A - mean(A), HSCL on A (False: the paper's single head, HSCL on Q)."""
    last_action: str = "executed"
    """Observation's last action: 'executed' (stay when the move was refused) or 'requested' (MapfEnv)."""
    still_bins: int = 0
    """Beyond the paper: the network also reads a count of the agent's own recent steps, one-hot in this many bins
    (NetworkConfig.still_bins); 0: not (the paper's inputs)."""
    still_count: str = "cell"
    """What that count is (NetworkConfig.still_count): 'cell' (steps on the same cell), 'refused' (consecutive
    refused moves), 'contact' (steps standing still beside the same unmoved agents) or 'revisit' (times the agent's
    last 16 positions held its current cell; the only count the rollout search and mining allow, MapfEnv.joint_state
    holds it)."""
    heading: bool = False
    """Beyond the paper: the fov gets a seventh channel, the cells the other agents face (NetworkConfig.heading,
    MapfEnv(heading=True)); False: the paper's six channels."""
    heading_refused: bool = False
    """Beyond the paper, with `heading`: the channel marks only the cells that other agents' refused moves tried to
    enter (NetworkConfig.heading_refused): a pushed blocker sees the push, not a neighbour that just arrived."""
    priority: bool = False
    """Beyond the paper: one more fov channel, the other agents ahead of this one in the instance's agent order, the
    order in which the expert settles who gives way (NetworkConfig.priority, MapfEnv(priority=True))."""
    goal_dirs: bool = False
    """Beyond the paper: four more fov channels, which way each other agent in view has to go to its goal (its own
    heuristic bits at its cell; NetworkConfig.goal_dirs, MapfEnv(goal_dirs=True))."""
    recurrent: bool = False
    """Beyond the paper (DHC's design): a GRU memory per agent (NetworkConfig.recurrent), trained on sequences of
    `sequence_length` steps of one agent, each started from the memory its actor had there (R2D2's stored state).
    False: the paper's feed-forward network, trained on single rows."""
    sequence_length: int = 8
    """Steps per training sequence of a recurrent network (the batch holds batch_size / sequence_length of them)."""
    augment: bool = False
    """Beyond the paper: each training row is seen turned or mirrored by one of the square grid's eight symmetries,
    drawn per row and step (symmetry.py: fov pictures, direction channels, actions, labels and position turn
    together). The rules, rewards and expert do not depend on direction, so every turned row is a row of the turned
    instance: eight times the distinct rows for the same episodes. Held-out agreement at 16 agents is limited by
    distinct rows, not capacity (issue 20, thirty-first session). False: rows as played."""
    total_steps: int = 20_000
    """Learner gradient steps of the whole run."""
    session_minutes: float = 0.0
    """Stop with a checkpoint after this many minutes of this session (0: no limit)."""
    batch_size: int = 192
    """Rows per gradient step."""
    lr: float = 1e-4
    """Adam learning rate."""
    lr_end: float = 0.0
    """Beyond the paper's silence on a schedule: with lr_end > 0 the learning rate falls linearly from lr to lr_end
    over total_steps (DHC halves it twice instead), so that the end weights are not one noisy draw of a curve that
    wanders. 0: constant lr."""
    ema_decay: float = 0.0
    """Beyond the paper: with ema_decay > 0 an exponential moving average of the online weights (Polyak averaging,
    w_ema <- d w_ema + (1 - d) w after every gradient step) is kept beside them, validated greedy on the last stage at
    every evaluation (eval.csv `ema_success_rate`) and saved as ema.pt, so that the model shipped is the average of a
    curve that wanders, not its last draw. Actors and mining keep playing the online weights. 0: none."""
    gamma: float = 0.99
    """Discount factor."""
    n_step: int = 2
    """Rewards summed before bootstrapping from the target network (DHC: 2)."""
    huber_delta: float = 1.0
    """Huber loss threshold on the TD error (smooth L1)."""
    grad_clip: float = 40.0
    """Global gradient-norm bound."""
    target_update_every: int = 2_000
    """Learner steps between copies of the online network into the target network."""
    dqn_weight: float = 1.0
    """Weight of the DQN term."""
    hscl_weight: float = 0.1
    """Initial weight of the HSCL term (steered when dqn_share > 0)."""
    dqn_share: float = 0.4
    """Target share of the DQN term in the update's gradient norm, |g_dqn| / (|g_dqn| + |g_hscl|); 0: fixed weights."""
    double_dqn: bool = False
    """Double DQN targets (van Hasselt et al. 2016): the online network picks the bootstrap action, the target
    network values it, against the overestimate of max over one network's noisy values (r23: mean Q +0.28
    against a Monte Carlo return of -0.7 before its collapse). False: the max of the target network (DHC)."""
    advantage_learning: float = 0.0
    """Beyond the paper: the advantage-learning target of Baird (1999) and Bellemare et al. (2016), r + gamma^m V(s')
    - alpha (V(s) - Q(s, a)) with V = max over the target network, for alpha > 0. It widens the gap between the
    greedy action and the rest, which in r26's deadlocks is 0.04-0.09 (the refused push leads), against |TD| errors
    of 0.3-0.5: a greedy policy is only as robust as its action gaps. 0: the DQN target."""
    mc_lower_bound: bool = False
    """Beyond the paper: DQN target max(n-step target, the Monte Carlo return) on rows of solved episodes."""
    feasible_labels: bool = False
    """Beyond the paper: no HSCL label on a row whose labelled move leads into a cell another agent holds after
    the step (the joint plan expected it to move; infeasible_labels)."""
    blocking_penalty: float = 0.0
    """Beyond the paper (after PRIMAL's blocking penalty, Sartoretti et al. 2019): added to the reward of an agent
    that ends a step on its own goal while it blocks an agent in its field of view (blocking_agents); the paper's
    team reward reaches such a blocker only through long bootstrapping. 0: off (the paper's rewards)."""
    blocking_margin: int = 4
    """An agent blocks another when, with its cell as an obstacle, the other's shortest path to its goal gets more
    than this many steps longer, or there is none (going round an agent in the open costs 2)."""
    parked_labels: bool = True
    """Whether to keep HSCL labels that move into a cell held by an agent standing on its own goal. False (beyond
    the paper): no label there. ODrM*'s joint plan often has the parked agent step aside for such a move (it costs
    the plan what the mover's way round costs), so the mover's half of that plan is labelled and learned, and
    the parked agent's half, stepping off its goal, is not (r26, r33: most failed cases end in such a push)."""
    imitation: str = "hscl"
    """The imitation term: 'hscl' (the paper's eq. 13) or 'margin' (beyond the paper: DQfD's large-margin loss,
    losses.margin_loss, which only puts the expert's action `margin` above the rest and leaves their order to the
    DQN term; HSCL's optimum makes them equal), or 'ce' (beyond the paper: cross-entropy of the expert's action under
    softmax(A / temperature), behaviour cloning's loss). The log's hscl columns then hold that term."""
    margin: float = 0.1
    """Margin of the 'margin' imitation term (about the value of one wasted step, 2 x 0.075)."""
    tau_h: float = 0.1
    """Hot-vector offset of Table I."""
    temperature: float = 0.1
    """HSCL temperature T (eq. 13); also the 'ce' imitation term's (its logits are A / T)."""
    replay_capacity: int = 200_000
    """Rows kept in the replay (oldest overwritten)."""
    priority_alpha: float = 0.0
    """Prioritised replay (DHC: 0.6): a row is drawn with probability proportional to (|TD error| + 0.001)^alpha,
    new rows at the highest priority so far; 0: uniform."""
    priority_beta: float = 0.4
    """Importance-sampling exponent of prioritised replay (DHC: 0.4): the DQN term weights a row by
    (size * P(row))^-beta / max over the batch."""
    learning_starts: int = 2_000
    """Rows in the replay before the first gradient step."""
    resume_refill: int = 50_000
    """After a resume of either kind (the replay is never saved: a fresh machine has none, and it would be hundreds
    of MB), learning waits until the replay holds this many rows again (capped at replay_capacity) instead of
    learning_starts, so that the first steps after a resume do not fit a few thousand fresh rows (the
    twenty-third session's resumed runs fell back by 0.03-0.14 on rung 2). A schedule setting: it may change on
    a resume."""
    replay_ratio: float = 4.0
    """Rows drawn by the learner per row produced (sets the gradient steps after each episode)."""
    eps_start: float = 0.3
    """Exploration epsilon at step 0 (each agent independently)."""
    eps_end: float = 0.05
    """Epsilon after eps_decay_steps."""
    eps_decay_steps: int = 10_000
    """Learner steps of the linear epsilon decay."""
    agent_eps_spread: bool = False
    """Each agent of an episode draws its own epsilon, uniformly in [0, 2 eps] (capped at 1; the same mean), so that
    some agents play nearly greedy beside others that explore. With one epsilon for all, a greedy agent's push into
    a neighbour is soon broken by the neighbour's random step, so pushing and waiting look cheap in the replay,
    while at test time no one steps aside. False: one epsilon for every agent (DHC)."""
    goal_exploration: bool = True
    """Whether an agent standing on its own goal explores (epsilon) like the others. False (beyond the paper): it
    plays greedily there. In the greedy test a parked agent stays parked; in epsilon-greedy training it steps off
    at random every few steps, so a push into it often goes through and looks as good as going round (r26's
    deadlocks are mostly such pushes, their Q-value 0.05-0.3 above the runner-up)."""
    relabel_fraction: float = 1.0
    """Share of policy-driven episodes whose visited states get ODrM* labels for HSCL."""
    expert_drive_fraction: float = 0.1
    """Share of episodes in which the agents execute the expert's actions (with epsilon noise)."""
    greedy_fraction: float = 0.0
    """Share of the policy-driven episodes played without exploration (epsilon 0), so that the states where a
    greedy team deadlocks, which epsilon-greedy play leaves within a step, enter the replay."""
    stuck_steps: int = 0
    """In those greedy episodes, exploration (epsilon) starts once the joint positions have stayed the same for
    this many steps: the greedy fixed point (a deadlock) enters the replay with a few rows, not a whole episode
    of them, and so does what follows when an agent leaves it. 0: greedy to the end."""
    stuck_value: bool = False
    """Beyond the paper: a greedy actor episode (greedy_fraction, with stuck_steps k >= 2) ends where the team has
    stood still k steps, a fixed point of the deterministic greedy team (with the executed last action, every agent
    then sees the same observation each step); its last rows bootstrap from the exact value of staying there for ever
    under greedy play, r_i / (1 - gamma) with r_i agent i's last step reward (-7.5 for a wait off the goal, -50 for a
    refused move, 0 on the goal), instead of exploring out of it. False: exploration starts there (stuck_steps)."""
    stuck_rescue: bool = False
    """Beyond the paper (DAgger with the expert's way out): in a greedy actor episode (greedy_fraction, stuck_steps
    k >= 1), once the team has stood still k steps the expert drives it from that fixed point on, with no random
    steps, so the replay holds the greedy team's own deadlocks together with the expert's joint way out of them
    (its labels for HSCL, its outcome for the DQN term). False: exploration starts there (stuck_steps)."""
    stuck_rollout: int = 0
    """Beyond the paper (policy improvement by rollouts at the greedy team's fixed points): in a greedy actor episode
    (greedy_fraction, stuck_steps k >= 1), once the team has stood still k steps, every agent's other actions are
    tried on copies of the episode, one agent deviating for one step with the others greedy and greedy play after it
    for up to this many steps (best_deviation). The deviation whose copy is solved soonest, else the one that leaves
    the team closest to its goals, if closer than now, is played and becomes that agent's label at the step (in place
    of the expert's): a label of what gets this greedy team out, where the joint expert's labels at fixed points
    assume teammates that give way (issue 20). No deviation helps: exploration starts (stuck_steps). 0: off."""
    mine_episodes: int = 0
    """Beyond the paper, with stuck_rollout: after each actor episode this many extra greedy episodes of the same stage
    (their own seed stream, MINE_STREAM) play with stuck_rollout's search wherever the team is stuck, and end where no
    deviation helps; only the rows of the deviating agents at those steps, labelled with their deviation and with no
    expert label elsewhere, enter the replay. Rollout labels then come by the hundred, not one per greedy actor episode
    that gets stuck. 0: none."""
    mined_batch_share: float = 0.0
    """Beyond the paper, with mine_episodes: the mined rows go to a replay of their own (MINED_CAPACITY rows) and this
    share of every batch is drawn from it, the rest from the main replay. In the main replay they are 1-2 % of the
    rows (issue 20, r76-r77). 0: they share the main replay."""
    mine_stage: str = ""
    """Beyond the paper, with mine_episodes: once the curriculum is at its last stage, the mining episodes of that
    stage are played at this AGENTSxSIZE instead (e.g. 8x20 while training 4x20): a crowd gets stuck more often, so
    each mining episode yields more rollout labels of the conflicts a smaller team meets more rarely. "": the
    episode's own stage."""
    stuck_cycles: bool = False
    """Beyond the paper: a greedy actor team is stuck (stuck_steps' exploration, stuck_rescue, stuck_rollout) where its
    joint state (positions, executed and requested last actions: what every observation is built from) repeats one
    it was in earlier in the episode. The greedy team is deterministic, so it then loops for ever: a fixed point, or
    a cycle of agents stepping back and forth, which k still steps never catch. stuck_steps must still be >= 1 (it
    turns the mechanism on). False: k still steps."""
    blocker_weight: float = 1.0
    """Beyond the paper: with `imitation` 'ce', a labelled row of a pushed blocker (an agent that chose to stay on a cell
    another agent's refused move tried to enter, pushed_blockers) weighs this many times an ordinary labelled row in
    the imitation term, whatever its label. Such rows are about 1-3 % of the replay, and a greedy team's fixed points
    turn on them. 1: every labelled row alike."""
    meet_weight: float = 1.0
    """Beyond the paper: with `imitation` 'ce', a labelled row whose agent is off its goal with another agent in its
    field of view (meeting_rows) weighs this many times an ordinary labelled row in the imitation term (times
    blocker_weight where both apply). Such rows are about half the labelled rows at 4 agents on 20x20 (train.csv
    `meet_share`), and the held-out agreement with the expert there stays near 0.945 whatever the training data
    (issue 20, thirty-first session). 1: every labelled row alike."""
    ongoal_weight: float = 1.0
    """Beyond the paper: with `imitation` 'ce', an expert-labelled row whose agent stands on its goal with another agent
    in its field of view (ongoal_rows) weighs this many times an ordinary labelled row in the imitation term (times
    blocker_weight where both apply); the rollout search's labels (the mined replay, mined_batch_share) keep weight 1.
    The per-step expert labels such rows "stay" 99 % of the time, yet a greedy team at 16 agents finishes only where
    an agent on its goal yields; fitting those labels harder costs rung 3 half its cases (issue 20, forty-second
    session). 0: no expert label there, the yield is left to the reward term and the search. 1: every row alike."""
    expert: str = "odrmstar"
    """'odrmstar' (the paper's), 'prioritized' (beyond the paper: prioritized planning in index order, ODrM* where it
    finds no plan; with `priority` its give-way rule is in the observation: train/expert.py), or 'shortest_path' (a
    stand-in for tests)."""
    expert_order: str = "index"
    """The order in which ODrM* takes the agents, which decides who gives way where moves tie (train/expert.py):
    'index' (the instance's, which no agent can observe), 'reversed', or 'position' (by cell, row first, which
    each agent can work out from its position input and the agents it sees; beyond the paper)."""
    expert_epsilon: float = 10.0
    """ODrM* inflation."""
    expert_objective: str = "free_goal_wait"
    """ODrM*'s objective (mapf_world.planners.odrmstar): 'free_goal_wait' (waits on one's goal are free; the paper's
    expert), 'sum_of_costs', or 'goal_keeping' (beyond the paper: a move off one's goal also costs 1 more, so where an agent on its goal
    stepping aside ties with another going round, the labels go round; it decides such ties only at
    expert_epsilon 1: with an inflated heuristic the search follows the mover's shorter distance first)."""
    expert_time_limit: float = 2.0
    """Seconds per ODrM* planning call."""
    relabel_time_budget: float = 5.0
    """Seconds of expert planning per episode; later states stay unlabelled."""
    stages: tuple = ("1x10", "2x10", "4x20", "8x20", "8x40", "16x40", "32x40", "64x40")
    """Curriculum stages AGENTSxSIZE, in order."""
    density: float = 0.3
    """Obstacle density of the generated worlds."""
    advance_pass_rate: float = 0.95
    """Greedy success on the current stage's validation cases (at an evaluation) that moves to the next stage."""
    review_fraction: float = 0.2
    """Share of episodes drawn from earlier stages (uniformly)."""
    max_episode_steps: int = 256
    """Episode step limit (the benchmark's)."""
    eval_every: int = 1_000
    """Learner steps between greedy evaluations on the validation cases (0: never)."""
    eval_cases: int = 40
    """Validation cases per stage (stages up to the current one and the next); they also decide the curriculum."""
    log_every: int = 100
    """Learner steps between train.csv rows (and gradient-share measurements)."""
    checkpoint_minutes: float = 5.0
    """Minutes between checkpoints."""
    keep_ema_at: tuple = ()
    """Learner steps at which to keep a copy of the averaged weights, ema_at<STEP>.pt (published too): a learning
    curve along one long run, laddered afterwards. Needs ema_decay > 0."""
    publish_dir: str = ""
    """Also copy last.pt, best.pt, state.json, config, logs and plot here at each checkpoint (a committed folder, so a
    fresh machine resumes from the weights); empty: don't."""
    threads: int = 1
    """torch threads."""
    bf16: bool = False
    """Autocast the learner's forward pass to bfloat16 (AMX-BF16 CPUs: about 1.3x per step at batch 192; the
    actors and evaluations stay float32)."""

    def validate(self) -> None:
        def need(cond, msg):
            if not cond:
                raise ValueError(msg)
        need(self.variant in ("hscl",) + tuple(ABLATIONS), f"variant must be hscl or one of {tuple(ABLATIONS)}, got {self.variant!r}")
        need(self.last_action in LAST_ACTION_MODES, f"last_action must be one of {LAST_ACTION_MODES}, got {self.last_action!r}")
        need(self.stuck_steps >= 0, f"stuck_steps must be >= 0, got {self.stuck_steps}")
        need(not self.stuck_value or (self.stuck_steps >= 2 and self.greedy_fraction > 0),
             "stuck_value needs greedy_fraction > 0 and stuck_steps >= 2 (a fixed point of the greedy team)")
        need(self.stuck_rollout >= 0, f"stuck_rollout must be >= 0, got {self.stuck_rollout}")
        need(self.mine_episodes >= 0, f"mine_episodes must be >= 0, got {self.mine_episodes}")
        countable = not self.still_bins or self.still_count == "revisit"  # joint_state holds only that count
        need(not self.mine_episodes or (self.stuck_rollout > 0 and countable and not self.recurrent),
             "mine_episodes needs stuck_rollout > 0 (its labeller), and no memory and no still input but the revisit "
             "count (stuck_cycles)")
        need(0 <= self.mined_batch_share < 1, f"mined_batch_share must be in [0, 1), got {self.mined_batch_share}")
        need(not self.mined_batch_share or self.mine_episodes > 0, "mined_batch_share needs mine_episodes > 0")
        need(not self.stuck_rollout or (self.stuck_steps >= 1 and self.greedy_fraction > 0 and not self.stuck_value
                                        and not self.stuck_rescue and not self.recurrent),
             "stuck_rollout needs greedy_fraction > 0 and stuck_steps >= 1, and none of stuck_value, stuck_rescue, "
             "recurrent")
        need(not self.stuck_cycles or (self.stuck_steps >= 1 and self.greedy_fraction > 0 and countable
                                       and not self.recurrent),
             "stuck_cycles needs greedy_fraction > 0 and stuck_steps >= 1, and no memory and no still input but the "
             "revisit count (the others' observations are not a function of the joint state)")
        need(not self.stuck_rescue or (self.stuck_steps >= 1 and self.greedy_fraction > 0 and not self.stuck_value),
             "stuck_rescue needs greedy_fraction > 0 and stuck_steps >= 1, and not stuck_value (which ends the episode there)")
        need(self.blocking_penalty <= 0, f"blocking_penalty is a penalty: must be <= 0, got {self.blocking_penalty}")
        need(self.blocking_margin >= 0, f"blocking_margin must be >= 0, got {self.blocking_margin}")
        need(self.still_bins == 0 or self.still_bins >= 2, f"still_bins must be 0 or >= 2, got {self.still_bins}")
        need(not (self.recurrent and self.priority_alpha > 0), "recurrent training samples sequences uniformly: "
             "priority_alpha must be 0 with recurrent")
        need(self.sequence_length >= 1 and self.sequence_length <= self.batch_size,
             f"sequence_length must lie in 1..batch_size, got {self.sequence_length}")
        need(self.still_count in STILL_KEYS, f"still_count must be one of {tuple(STILL_KEYS)}, got {self.still_count!r}")
        for name in ("total_steps", "batch_size", "n_step", "target_update_every", "replay_capacity",
                     "max_episode_steps", "eval_cases", "log_every", "threads"):
            need(int(getattr(self, name)) >= 1, f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("eps_start", "eps_end", "relabel_fraction", "expert_drive_fraction", "greedy_fraction",
                     "advance_pass_rate", "review_fraction", "dqn_share", "priority_alpha", "priority_beta"):
            need(0.0 <= getattr(self, name) <= 1.0, f"{name} must lie in [0, 1], got {getattr(self, name)}")
        need(self.dqn_share < 1.0, "dqn_share must be < 1")
        need(0.0 < self.gamma <= 1.0, f"gamma must lie in (0, 1], got {self.gamma}")
        need(self.dqn_weight >= 0 and self.hscl_weight >= 0 and self.dqn_weight + self.hscl_weight > 0,
             "dqn_weight and hscl_weight must be >= 0, not both 0")
        need(self.imitation in ("hscl", "margin", "ce"), f"imitation must be hscl, margin or ce, got {self.imitation!r}")
        need(self.margin > 0, f"margin must be > 0, got {self.margin}")
        need(self.blocker_weight > 0, f"blocker_weight must be > 0, got {self.blocker_weight}")
        need(self.blocker_weight == 1.0 or (self.imitation == "ce" and not self.recurrent),
             "blocker_weight != 1 needs imitation 'ce' and a feed-forward network")
        need(self.meet_weight > 0, f"meet_weight must be > 0, got {self.meet_weight}")
        need(self.meet_weight == 1.0 or (self.imitation == "ce" and not self.recurrent),
             "meet_weight != 1 needs imitation 'ce' and a feed-forward network")
        need(self.ongoal_weight >= 0, f"ongoal_weight must be >= 0, got {self.ongoal_weight}")
        need(self.ongoal_weight == 1.0 or (self.imitation == "ce" and not self.recurrent),
             "ongoal_weight != 1 needs imitation 'ce' and a feed-forward network")
        need(0.0 < self.tau_h < 0.2, f"tau_h must lie in (0, 0.2), got {self.tau_h}")
        need(self.lr_end >= 0, f"lr_end must be >= 0, got {self.lr_end}")
        need(0 <= self.ema_decay < 1, f"ema_decay must be in [0, 1), got {self.ema_decay}")
        need(not self.keep_ema_at or self.ema_decay > 0, "keep_ema_at needs ema_decay > 0 (it keeps averaged weights)")
        need(all(0 < k <= self.total_steps for k in self.keep_ema_at),
             f"keep_ema_at steps must lie in 1..total_steps ({self.total_steps}), got {list(self.keep_ema_at)}")
        need(self.resume_refill >= 0, f"resume_refill must be >= 0, got {self.resume_refill}")
        need(0 <= self.advantage_learning < 1, f"advantage_learning must lie in [0, 1), got {self.advantage_learning}")
        need(not (self.recurrent and self.advantage_learning > 0), "advantage_learning is not implemented for recurrent")
        need(not (self.recurrent and self.augment), "augment turns single rows: a recurrent network's sequences would "
             "need one symmetry per sequence, which is not implemented")
        for name in ("lr", "grad_clip", "temperature", "replay_ratio", "huber_delta", "expert_time_limit"):
            need(getattr(self, name) > 0, f"{name} must be > 0, got {getattr(self, name)}")
        need(self.expert_order in EXPERT_ORDERS, f"expert_order must be one of {EXPERT_ORDERS}, got {self.expert_order!r}")
        need(self.expert in ("odrmstar", "prioritized", "shortest_path"),
             f"expert must be odrmstar, prioritized or shortest_path, got {self.expert!r}")
        need(self.expert != "prioritized" or self.expert_order == "index",
             f"the prioritized expert plans in index order only, got expert_order {self.expert_order!r}")
        need(self.expert_objective in EXPERT_OBJECTIVES,
             f"expert_objective must be one of {sorted(EXPERT_OBJECTIVES)}, got {self.expert_objective!r}")
        need(self.expert_epsilon >= 1, f"expert_epsilon must be >= 1, got {self.expert_epsilon}")
        need(not self.init_model or Path(self.init_model).is_file(), f"init_model {self.init_model!r} is not a file")
        need(len(self.stages) >= 1, "stages must name at least one stage")
        for s in self.stages:
            parse_stage(s)
        if self.mine_stage:
            parse_stage(self.mine_stage)
            need(self.mine_episodes > 0, "mine_stage needs mine_episodes > 0")

    def network_config(self) -> NetworkConfig:
        return NetworkConfig(dueling=self.dueling, still_bins=self.still_bins, still_count=self.still_count,
                             recurrent=self.recurrent, heading=self.heading,
                             heading_refused=self.heading_refused, priority=self.priority, goal_dirs=self.goal_dirs,
                             **ABLATIONS.get(self.variant, {}))

    def priority_channel(self) -> int:
        """The fov channel that marks the earlier agents (with `priority`): after the base channels and the heading."""
        ncfg = self.network_config()
        return ncfg.in_channels + int(ncfg.heading)


def learning_rate(args: Args, step: int) -> float:
    """The learning rate of gradient step `step`: lr, or with lr_end > 0 linear from lr to lr_end over total_steps."""
    if args.lr_end <= 0:
        return args.lr
    return args.lr + min(1.0, step / args.total_steps) * (args.lr_end - args.lr)


def parse_stage(text: str) -> tuple[int, int]:
    """'4x20' -> (4 agents, 20x20 map); ValueError naming the stage otherwise."""
    try:
        agents, size = (int(x) for x in str(text).lower().split("x"))
    except ValueError:
        raise ValueError(f"stage {text!r} is not AGENTSxSIZE (for example 4x20)") from None
    if agents < 1 or size < 2 or 2 * agents > size * size:
        raise ValueError(f"stage {text!r}: need 1 <= agents and 2 * agents <= size^2")
    return agents, size


# --- episodes -> replay rows --------------------------------------------------------------------------------
ROW_SPECS = {  # one agent's n-step transition; fov values are 0/1 (7 channels with Args.heading: Replay widens it)
    "fov": (np.uint8, (6, 9, 9)), "last_action": (np.int8, ()), "position": (np.int16, (2,)),
    "action": (np.int8, ()), "ret": (np.float32, ()), "boot_gamma": (np.float32, ()),
    "next_fov": (np.uint8, (6, 9, 9)), "next_last_action": (np.int8, ()), "next_position": (np.int16, (2,)),
    "expert": (np.int8, ()), "mc_return": (np.float32, ()), "refused": (np.bool_, ()), "solved": (np.bool_, ()),
    "blocker": (np.bool_, ()),  # pushed_blockers: stayed on a cell another agent's refused move tried to enter
    "still": (np.int16, ()), "next_still": (np.int16, ()),  # the count Args.still_count names, for still_bins > 0
    # Where the row sits, for sequences (recurrent): row (t, i) of episode e is followed by row (t + 1, i) of e,
    # n_agents rows later; m is its bootstrap's distance (next_* is the observation at t + m).
    "episode": (np.int64, ()), "m": (np.int8, ()), "n_agents": (np.int16, ()),
    "map_shape": (np.int16, (2,)),  # (height, width) of the row's map, for Args.augment; 0, 0 where not given
}
# A recurrent network's rows also hold "h_in", the memory before the step (float16, (hidden_features,)).


def blocking_agents(grid: np.ndarray, positions: np.ndarray, goals: np.ndarray, dist: np.ndarray, margin: int,
                    radius: int = 4) -> np.ndarray:
    """(N,) bool: agent i stands on its goal and blocks an agent j within `radius` cells (Chebyshev; the 9x9 field
    of view), off its own goal: with i's cell as an obstacle, j's shortest path to its goal is more than `margin`
    steps longer than dist[j] (the obstacle-only distance), or there is none. Other agents are no obstacles."""
    n = len(positions)
    out = np.zeros(n, dtype=bool)
    on_goal = np.all(positions == goals, axis=1)
    here = dist[np.arange(n), positions[:, 0], positions[:, 1]]
    for i in np.flatnonzero(on_goal):
        near = np.abs(positions - positions[i]).max(axis=1) <= radius
        js = np.flatnonzero(near & ~on_goal)
        if len(js) == 0:
            continue
        blocked = grid.copy()
        blocked[tuple(positions[i])] = 1
        d = distance_maps(blocked, goals[js])[np.arange(len(js)), positions[js, 0], positions[js, 1]]
        out[i] = bool(np.any(d > here[js] + margin))  # UNREACHABLE is far above any margin
    return out


class RecurrentActor:
    """A recurrent network (NetworkConfig.recurrent) as an acting function for play_episode: each call is one step of
    every agent, whose memories it carries in `h` (zeros after `reset`); `q` holds the last call's Q-values."""

    def __init__(self, net: QNetwork):
        if not net.cfg.recurrent:
            raise ValueError("RecurrentActor needs a recurrent network (NetworkConfig.recurrent)")
        self.net, self.fast, self.h, self.q = net, InferenceNet(net), None, None

    @property
    def cfg(self) -> NetworkConfig:
        return self.net.cfg

    def reset(self, n_agents: int) -> None:
        self.h = torch.zeros(n_agents, self.net.cfg.hidden_features)

    def __call__(self, *inputs) -> torch.Tensor:
        if self.h is None or self.h.shape[0] != inputs[0].shape[0]:
            raise ValueError(f"RecurrentActor: reset(n_agents) first (memories for "
                             f"{None if self.h is None else self.h.shape[0]} agents, inputs for {inputs[0].shape[0]})")
        with torch.inference_mode():
            self.q, self.h = self.net.remember(self.fast.embed(*inputs), self.h)
        return self.q


def acting(net: QNetwork):
    """The acting function of a network: InferenceNet, or RecurrentActor for a recurrent one."""
    return RecurrentActor(net) if net.cfg.recurrent else InferenceNet(net)


def play_episode(forward, env: MapfEnv, epsilon: float | np.ndarray, rng, oracle=None, budget: float = 0.0,
                 expert_drives: bool = False, greedy_until_stuck: int = 0,
                 blocking: tuple[float, int] = (0.0, 0), goal_exploration: bool = True,
                 stuck_ends: bool = False, stuck_rescue: bool = False, stuck_rollout: int = 0,
                 stuck_cycles: bool = False) -> tuple[dict, dict]:
    """One episode, every agent acting on its own observation (all in one batch).

    Actions: argmax Q (the paper's greedy rule; ties to the lowest index), or the expert's when
    `expert_drives`; then each agent acts uniformly at random with probability `epsilon` (one for all, or
    (N,) one per agent), or, with
    `greedy_until_stuck` k > 0, with probability 0 until the joint positions have stayed the same for k steps
    (a greedy deadlock) and `epsilon` from then on; with `goal_exploration` False, never while on its own goal.
    With `oracle`,
    states are labelled until it fails or `budget` seconds are spent. Returns per-step arrays
    (T steps, N agents; obs has T + 1 entries) and stats. The network's inputs follow `forward.cfg`
    (network_inputs); a plain function stands for a network with the paper's inputs. `blocking` (penalty, margin)
    adds the penalty to the reward of every agent that blocking_agents finds after a step (beyond the paper). With
    `stuck_ends`, the episode ends instead where exploration would start (stats["fixed_point"]); with `stuck_rescue`
    (and `oracle`), the expert drives from there on, with no random steps (stats["rescued"]); with `stuck_rollout` H,
    best_deviation's move is played there and labels its agent's row (stats["deviations"]), random steps only where
    no deviation helps (at most MAX_DEVIATION_SEARCHES searches an episode). With `stuck_cycles`, the team is stuck
    where its joint state (MapfEnv.joint_state) repeats one it was in before in the episode, a cycle of any period of
    the deterministic greedy team, instead of after k still steps."""
    cfg = getattr(forward, "cfg", NetworkConfig())
    recurrent = isinstance(forward, RecurrentActor)
    obs, _ = env.reset()
    steps = {"obs": [obs], "action": [], "reward": [], "expert": [], "failed": []}
    if recurrent:
        forward.reset(env.n_agents)
        steps["h_in"] = []
    spent, labelled, done, terminated, blocked = 0.0, 0, False, False, 0
    still, eps_now, rescued, deviations, searches = 0, (0.0 if greedy_until_stuck > 0 else epsilon), False, 0, 0
    stuck, seen = False, {env.joint_state()}
    while not done:
        expert = np.full(env.n_agents, -1, dtype=np.int64)
        if oracle is not None and spent < budget:
            t0 = time.perf_counter()
            try:
                expert = oracle.actions(env.positions)
                labelled += env.n_agents
            except ExpertFailed:
                oracle = None
            spent += time.perf_counter() - t0
        if recurrent:  # the memory follows every observation, also while the expert drives
            steps["h_in"].append(forward.h.numpy().astype(np.float16))
        if rescued and expert[0] < 0:  # the expert failed or its budget is spent: explore out instead
            eps_now = epsilon
        if expert_drives and expert[0] >= 0:
            actions = expert.copy()
            if recurrent:
                forward(*network_inputs(obs, cfg))
        else:
            with torch.inference_mode():
                q = forward(*network_inputs(obs, cfg)).numpy()
            actions = q.argmax(axis=1)
            if stuck_rollout and stuck and eps_now == 0.0:
                searches += 1
                dev = (best_deviation(forward, env, actions, stuck_rollout, greedy_until_stuck, stuck_cycles)
                       if searches <= MAX_DEVIATION_SEARCHES else None)
                if dev is None:
                    eps_now = epsilon  # no single step of one agent gets the team moving: explore, as stuck_steps does
                    if epsilon == 0.0:  # nothing would ever change: the episode is over
                        break
                else:
                    actions[dev[0]] = expert[dev[0]] = dev[1]
                    deviations += 1
        explore = rng.random(env.n_agents) < eps_now
        if not goal_exploration:
            explore &= ~np.all(env.positions == env.goals, axis=1)
        actions[explore] = rng.integers(0, 5, int(explore.sum()))
        before = env.positions  # a copy
        obs, reward, terminated, truncated, info = env.step(actions)
        if blocking[0] and not terminated:
            blockers = blocking_agents(env.grid, env.positions, env.goals, env.dist, blocking[1])
            reward, blocked = reward + blocking[0] * blockers, blocked + int(blockers.sum())
        still = still + 1 if np.array_equal(before, env.positions) else 0
        state_now = env.joint_state()
        stuck = greedy_until_stuck > 0 and (state_now in seen if stuck_cycles else still >= greedy_until_stuck)
        seen.add(state_now)
        fixed_point = stuck and not terminated
        if fixed_point and stuck_rescue and oracle is not None:
            expert_drives = rescued = True
        elif fixed_point and not rescued and not stuck_rollout:
            eps_now = epsilon
        for k, v in (("obs", obs), ("action", actions), ("reward", reward), ("expert", expert), ("failed", info["failed"])):
            steps[k].append(v)
        done = terminated or truncated or (fixed_point and stuck_ends)
    return steps, {"success": bool(terminated), "steps": env.step_count, "n_agents": env.n_agents,
                   "fixed_point": bool(fixed_point and stuck_ends),
                   "labelled": labelled, "oracle_s": spent, "expert_drove": expert_drives and labelled > 0, "rescued": rescued,
                   "blocked": blocked, "deviations": deviations}


def mine(forward, envs: list[MapfEnv], horizon: int, rng) -> list[tuple[dict, dict]]:
    """Mining (Args.mine_episodes): (steps, stats) of play_episode, greedy with the rollout search of `horizon` steps
    wherever the team loops, for the envs whose teams get stuck at all; the others, screened in lockstep by
    greedy_gets_stuck, can yield no label and are not played again."""
    return [play_episode(forward, env, 0.0, rng, greedy_until_stuck=1, stuck_rollout=horizon, stuck_cycles=True)
            for env, hit in zip(envs, greedy_gets_stuck(forward, envs)) if hit]


MAX_DEVIATION_SEARCHES = 8  # best_deviation calls an episode (each costs up to 4 N rollouts of `horizon` steps)


def _labelled_moves_into(positions: np.ndarray, expert: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(T, N, N) bool: agent i's labelled move (expert (T, N), -1: none) from positions[:-1] leads into cells[t, j],
    j != i; stays and unlabelled rows never do."""
    target = positions[:-1] + DELTAS[np.clip(expert, 0, 4)]  # (T, N, 2)
    hit = np.all(target[:, :, None, :] == cells[:, None, :, :], axis=3) & (expert > 0)[:, :, None]
    hit[:, np.arange(hit.shape[1]), np.arange(hit.shape[1])] = False
    return hit


def infeasible_labels(positions: np.ndarray, expert: np.ndarray) -> np.ndarray:
    """(T, N) bool: the expert's move leads into a cell that another agent holds after the step.

    positions (T + 1, N, 2) as played, expert (T, N) labels (-1: none). The joint plan behind a label expects
    the others to move as planned; where one of them stood still or took that cell, the labelled move would
    have been refused. Such a label teaches the push that deadlocks a greedy team (issue 20, finding 3)."""
    return _labelled_moves_into(positions, expert, positions[1:]).any(axis=2)


def pushed_blockers(positions: np.ndarray, actions: np.ndarray, failed: np.ndarray) -> np.ndarray:
    """(T, N) bool: agent j chose to stay on a cell another agent's refused move tried to enter (the stuck report's
    blockers, at every step). positions (T + 1, N, 2) as played, actions (T, N) as chosen, failed (T, N) refused."""
    refused_moves = np.where(failed, actions, -1)
    into = _labelled_moves_into(positions, refused_moves, positions[:-1])  # (T, i, j): i's refused move hits j's cell
    return into.any(axis=1) & (actions == STAY)


def parked_push_labels(positions: np.ndarray, goals: np.ndarray, expert: np.ndarray) -> np.ndarray:
    """(T, N) bool: the expert's move leads into a cell that another agent, standing on its own goal, holds before
    the step. positions (T + 1, N, 2) as played, goals (N, 2), expert (T, N) labels (-1: none)."""
    parked = np.all(positions[:-1] == goals[None], axis=2)  # (T, N)
    return (_labelled_moves_into(positions, expert, positions[:-1]) & parked[:, None, :]).any(axis=2)


def distinct_observations(rows: dict, mask: np.ndarray) -> int:
    """How many distinct observations (fov, last action, position) the rows under `mask` hold. A greedy fixed point
    repeats one observation per agent until the time limit, so its rows are many copies of a few states."""
    return len({(rows["fov"][i].tobytes(), int(rows["last_action"][i]), rows["position"][i].tobytes())
                for i in np.flatnonzero(mask)})


def episode_rows(steps: dict, terminated: bool, gamma: float, n_step: int, feasible_labels: bool = False,
                 still_key: str = "still", goals: np.ndarray | None = None, episode: int = 0,
                 fixed_point: bool = False, map_shape: tuple = (0, 0)) -> dict:
    """Replay rows of every agent and step: n-step return, bootstrap state and discount, Monte Carlo return.

    Row (t, i): ret = sum_{k<m} gamma^k r[t+k, i] with m = min(n, T - t); bootstrap from obs[t + m] with
    discount gamma^m, or 0 when the episode terminated at t + m = T. A time-limit end is no terminal state.
    Rows "still"/"next_still" hold the observation's count `still_key` (NetworkConfig.still_count). With `goals`,
    labels that push into an agent parked on its goal are dropped (parked_push_labels). `episode` numbers the rows'
    episode (for sequences); a recurrent actor's steps also give "h_in", the memory before each step. With
    `fixed_point` (the episode ended at a fixed point of the greedy team, Args.stuck_value), the rows whose bootstrap
    state is the last one bootstrap from its exact value instead: each agent's last reward r repeated for ever,
    r / (1 - gamma), added to the return with the bootstrap's discount, and no network bootstrap. `map_shape`: the
    map's (height, width), which turning a position needs (Args.augment)."""
    reward = np.stack(steps["reward"]).astype(np.float64)  # (T, N)
    t_len, n_agents = reward.shape
    mc = np.zeros_like(reward)
    acc = np.zeros(n_agents)
    for t in range(t_len - 1, -1, -1):
        acc = reward[t] + gamma * acc
        mc[t] = acc
    ret = np.zeros_like(reward)
    for k in range(min(n_step, t_len)):  # an episode shorter than n_step sums what it has
        ret[: t_len - k] += gamma ** k * reward[k:]
    m = np.minimum(n_step, t_len - np.arange(t_len))  # (T,)
    boot_gamma = gamma ** m.astype(np.float64)
    if terminated:
        boot_gamma[np.arange(t_len) + m == t_len] = 0.0
    if fixed_point and not terminated and gamma < 1:
        last = np.arange(t_len) + m == t_len
        ret[last] += boot_gamma[last, None] * reward[-1][None, :] / (1.0 - gamma)
        boot_gamma[last] = 0.0
    obs = steps["obs"]
    fov = np.stack([o["fov"] for o in obs]).astype(np.uint8)  # (T+1, N, 6, l, l)
    last = np.stack([o["last_action"].argmax(axis=1) for o in obs]).astype(np.int8)
    pos = np.stack([o["position"] for o in obs]).astype(np.int16)
    still = np.stack([o[still_key] for o in obs]).astype(np.int16)
    nxt = np.arange(t_len) + m
    expert = np.stack(steps["expert"]).astype(np.int8)
    if feasible_labels:
        expert = np.where(infeasible_labels(pos.astype(np.int64), expert.astype(np.int64)), -1, expert).astype(np.int8)
    if goals is not None:
        expert = np.where(parked_push_labels(pos.astype(np.int64), np.asarray(goals, np.int64), expert.astype(np.int64)),
                          -1, expert).astype(np.int8)
    flat = lambda a: a.reshape((t_len * n_agents,) + a.shape[2:])  # noqa: E731 (row order: step-major)
    extra = {"h_in": flat(np.stack(steps["h_in"]))} if "h_in" in steps else {}
    return extra | {
        "fov": flat(fov[:-1]), "last_action": flat(last[:-1]), "position": flat(pos[:-1]),
        "action": flat(np.stack(steps["action"]).astype(np.int8)), "ret": flat(ret.astype(np.float32)),
        "boot_gamma": flat(np.repeat(boot_gamma[:, None], n_agents, 1).astype(np.float32)),
        "next_fov": flat(fov[nxt]), "next_last_action": flat(last[nxt]), "next_position": flat(pos[nxt]),
        "expert": flat(expert), "mc_return": flat(mc.astype(np.float32)),
        "refused": flat(np.stack(steps["failed"]).astype(bool)),
        "blocker": flat(pushed_blockers(pos.astype(np.int64), np.stack(steps["action"]), np.stack(steps["failed"]))),
        "solved": np.full(t_len * n_agents, bool(terminated)),  # mc_return is a whole episode's return
        "still": flat(still[:-1]), "next_still": flat(still[nxt]),
        "episode": np.full(t_len * n_agents, episode, dtype=np.int64),
        "m": flat(np.repeat(m[:, None], n_agents, 1).astype(np.int8)),
        "n_agents": np.full(t_len * n_agents, n_agents, dtype=np.int16),
        "map_shape": np.tile(np.asarray(map_shape, dtype=np.int16), (t_len * n_agents, 1)),
    }


class Replay:
    """Ring buffer of ROW_SPECS rows; uniform sampling, or prioritised by |TD error| (alpha > 0)."""

    def __init__(self, capacity: int, alpha: float = 0.0, beta: float = 0.4, hidden: int = 0, channels: int = 6):
        """`hidden` > 0: rows also keep a recurrent actor's memory "h_in" of that width (sample_sequences).
        `channels`: of the stored fov (NetworkConfig.fov_channels)."""
        self.capacity, self.size, self.cursor = capacity, 0, 0
        self.alpha, self.beta = alpha, beta
        fov = (np.uint8, (channels,) + ROW_SPECS["fov"][1][1:])
        self.specs = ROW_SPECS | {"fov": fov, "next_fov": fov} | ({"h_in": (np.float16, (hidden,))} if hidden else {})
        self.data = {k: np.zeros((capacity,) + shape, dtype=dt) for k, (dt, shape) in self.specs.items()}
        self.priority = np.zeros(capacity)  # (|TD| + 0.001)^alpha of each row
        self.max_priority = 1.0

    def add(self, rows: dict) -> None:
        n = len(rows["action"])
        if n > self.capacity:
            rows, n = {k: v[-self.capacity:] for k, v in rows.items()}, self.capacity
        idx = (self.cursor + np.arange(n)) % self.capacity
        for k in self.specs:
            self.data[k][idx] = rows[k]
        self.priority[idx] = self.max_priority  # a new row is drawn at least once soon
        self.cursor, self.size = (self.cursor + n) % self.capacity, min(self.capacity, self.size + n)

    def sample(self, n: int, rng) -> dict:
        """A batch of n rows as tensors; "index" (for update_priorities) and "weight" (importance sampling,
        all 1 when uniform) come with it."""
        if self.alpha > 0:
            cum = np.cumsum(self.priority[: self.size])
            idx = np.minimum(np.searchsorted(cum, rng.random(n) * cum[-1], side="right"), self.size - 1)
            w = (self.size * self.priority[idx] / cum[-1]) ** -self.beta
            weight = torch.from_numpy((w / w.max()).astype(np.float32))
        else:
            idx, weight = rng.integers(0, self.size, n), torch.ones(n)
        return self._tensors(idx, weight)

    def sample_sequences(self, n: int, length: int, n_step: int, rng) -> tuple[dict, torch.Tensor]:
        """n sequences of one agent's consecutive rows, drawn uniformly by their first row: (batch, valid).

        A sequence covers `length` training steps plus the n_step - 1 after them, whose memories the bootstrap
        of the last ones needs (next_* of row t is the observation at t + m, read with the memory after row
        t + m - 1). batch: the rows as by sample, flattened sequence-major, (n * (length + n_step - 1), ...);
        valid (n, length + n_step - 1): the row is in the same episode (a sequence can run past its end)."""
        width = length + n_step - 1
        start = rng.integers(0, self.size, n)
        idx = (start[:, None] + np.arange(width)[None, :] * self.data["n_agents"][start][:, None].astype(np.int64))
        idx %= self.capacity
        # Episode numbers are unique, so a row of another episode (a later one, or an older one where the ring
        # wrapped) ends the sequence; rows past the filled part are zeros.
        valid = (self.data["episode"][idx] == self.data["episode"][start][:, None]) & (idx < self.size)
        valid = np.cumprod(valid, axis=1).astype(bool)  # a sequence ends at its first row of another episode
        return self._tensors(idx.reshape(-1), torch.ones(idx.size)), torch.from_numpy(valid)

    def _tensors(self, idx: np.ndarray, weight: torch.Tensor) -> dict:
        eye = torch.eye(5)
        b = {k: torch.from_numpy(v[idx]) for k, v in self.data.items()}
        t = {"action": b["action"].long(), "expert": b["expert"].long(), "refused": b["refused"], "solved": b["solved"],
             "blocker": b["blocker"], "still": b["still"].long(), "next_still": b["next_still"].long(), "index": idx,
             "weight": weight, "m": b["m"].long(), "episode": b["episode"], "map_shape": b["map_shape"].long()}
        if "h_in" in b:
            t["h_in"] = b["h_in"].float()
        for k in ("ret", "boot_gamma", "mc_return"):
            t[k] = b[k]
        for pre in ("", "next_"):
            t[pre + "fov"] = b[pre + "fov"].float().contiguous(memory_format=torch.channels_last)
            t[pre + "last_action"] = eye[b[pre + "last_action"].long()]
            t[pre + "position"] = b[pre + "position"].float()
        return t

    def update_priorities(self, idx: np.ndarray, td: torch.Tensor) -> None:
        if self.alpha > 0:
            p = (td.abs().double().numpy() + 1e-3) ** self.alpha
            self.priority[idx] = p
            self.max_priority = max(self.max_priority, float(p.max()))


MINED_CAPACITY = 50_000  # rows of the mined replay (Args.mined_batch_share): 3,000 learner steps mine about 2,700


def mixed_sample(replay: Replay, mined: Replay | None, n: int, share: float, rng) -> tuple[dict, int]:
    """A batch of n rows, round(share * n) of them from `mined` (last in the batch) once it holds that many, the
    rest from `replay`: (batch, rows from replay). "index" is meaningful for the first rows only (update_priorities)."""
    k = int(round(share * n)) if mined is not None else 0
    if k == 0 or mined.size < k:
        return replay.sample(n, rng), n
    a, b = replay.sample(n - k, rng), mined.sample(k, rng)
    return {key: (np.concatenate([a[key], b[key]]) if isinstance(a[key], np.ndarray) else torch.cat([a[key], b[key]]))
            for key in a}, n - k


def recurrent_batch(net: QNetwork, target: QNetwork, online_fast, target_fast, act_fast, replay: Replay, args: Args,
                    rng) -> tuple:
    """A recurrent network's batch: (rows, q, next_q_target, next_q_online or None), the rows those of losses().

    batch_size / sequence_length sequences of one agent each (Replay.sample_sequences); both networks unroll their
    memory over a sequence from the memory its actor stored at its first row (R2D2's stored state, no burn-in).
    The training rows are the first sequence_length steps of each sequence that lie in its episode. Row t
    bootstraps from its next_* observation (t + m) read with the memory after row t + m - 1."""
    length, width = args.sequence_length, args.sequence_length + args.n_step - 1
    n_seq, hid = max(1, args.batch_size // length), net.cfg.hidden_features
    seq, valid = replay.sample_sequences(n_seq, length, args.n_step, rng)

    def first(v):  # (S * W, ...) rows -> the first `length` steps of each sequence, (S * L, ...)
        return v.reshape(n_seq, width, *v.shape[1:])[:, :length].reshape(-1, *v.shape[1:])

    def inputs(pre: str, pick=lambda v: v) -> tuple:
        out = tuple(pick(seq[pre + k]) for k in ("fov", "last_action", "position"))
        if args.still_bins:
            out += (still_onehot(pick(seq[pre + "still"]), args.still_bins),)
        return out

    def unroll(model: QNetwork, fast, h: torch.Tensor) -> torch.Tensor:
        e = fast.embed(*inputs("")).reshape(n_seq, width, hid)
        memories = []
        for k in range(width):
            h = model.gru(e[:, k], h)
            memories.append(h)
        return torch.stack(memories, dim=1)  # (S, W, H): the memory after each step

    h0 = seq["h_in"].view(n_seq, width, hid)[:, 0]
    hs = unroll(net, online_fast, h0)
    q = net.q_values(hs[:, :length].reshape(-1, hid))
    keep = first(valid.reshape(-1))
    pos = torch.arange(length).repeat(n_seq)
    which = torch.arange(n_seq).repeat_interleave(length)
    prev = pos + first(seq["m"]) - 1  # <= width - 1 since m <= n_step
    prev = prev.clamp(0, width - 1)  # rows past their episode (masked) may hold anything
    nxt = inputs("next_", first)
    with torch.inference_mode():
        ht = unroll(target, target_fast, h0)
        next_q = target.q_values(target.gru(target_fast.embed(*nxt), ht[which, prev]))
        next_online = None
        if args.double_dqn:
            next_online = net.q_values(net.gru(act_fast.embed(*nxt), hs.detach()[which, prev]))
    rows = {}
    for k, v in seq.items():
        if isinstance(v, torch.Tensor) and v.dim() >= 1 and v.shape[0] == n_seq * width:
            rows[k] = first(v)[keep]
    rows["index"] = first(seq["index"])[keep.numpy()]
    return (rows, q[keep], next_q[keep].clone(), None if next_online is None else next_online[keep].clone())


# --- losses and what to look at -----------------------------------------------------------------------------
def off_goal(fov: torch.Tensor) -> torch.Tensor:
    """(B,) bool: the row's agent is off its goal (a heuristic bit, channels 2-5, set at its own cell)."""
    c = fov.shape[-1] // 2
    return fov[:, 2:6, c, c].amax(1) > 0


def sees_another(fov: torch.Tensor) -> torch.Tensor:
    """(B,) bool: another agent is in the row's field of view (channel 1)."""
    return fov[:, 1].flatten(1).amax(1) > 0


def meeting_rows(fov: torch.Tensor) -> torch.Tensor:
    """(B,) bool: rows whose agent is off its goal (a heuristic bit set at its own cell, channels 2-5) with another
    agent in its field of view (channel 1): where the labels depend on the others (issue 20, thirty-first session)."""
    return sees_another(fov) & off_goal(fov)


def ongoal_rows(fov: torch.Tensor) -> torch.Tensor:
    """(B,) bool: rows whose agent stands on its goal (no heuristic bit at its own cell, channels 2-5) with another
    agent in its field of view (channel 1): where a greedy team's fixed points wait for a yield (Args.ongoal_weight)."""
    return sees_another(fov) & ~off_goal(fov)


def contact_rows(fov: torch.Tensor, priority_channel: int) -> torch.Tensor:
    """(B,) bool: rows whose agent is off its goal with an earlier agent (marked in the priority channel, at index
    `priority_channel` of the fov) in one of its four neighbour cells: it touches the agent the give-way order says
    it makes way for. Held out at 16 agents these are the interacting rows that agree least with the expert (0.75-0.80
    against 0.83-0.98; issue 20, thirty-fourth session)."""
    c = fov.shape[-1] // 2
    touch = fov[:, priority_channel, [c - 1, c + 1, c, c], [c, c, c - 1, c + 1]].amax(1) > 0
    return touch & off_goal(fov)


def losses(q: torch.Tensor, next_q_target: torch.Tensor, batch: dict, args: Args,
           next_q_online: torch.Tensor | None = None, q_target: torch.Tensor | None = None,
           n_main: int | None = None) -> tuple:
    """(DQN term, HSCL term, TD errors): Huber on the n-step TD error; HSCL on the advantage (dueling) or on Q.
    With `next_q_online` (double DQN) the bootstrap is the target network's value of the online argmax. With
    `q_target`, the target network's Q(s, .) of the rows' own states, the target is advantage learning's
    (Args.advantage_learning). Rows from `n_main` on came from the mined replay (mixed_sample; None: none did)."""
    q_taken = q.gather(1, batch["action"][:, None]).squeeze(1)
    if next_q_online is None:
        boot = next_q_target.max(dim=1).values
    else:
        boot = next_q_target.gather(1, next_q_online.argmax(dim=1, keepdim=True)).squeeze(1)
    target = batch["ret"] + batch["boot_gamma"] * boot
    if q_target is not None and args.advantage_learning > 0:
        gap = q_target.max(dim=1).values - q_target.gather(1, batch["action"][:, None]).squeeze(1)
        target = target - args.advantage_learning * gap
    if args.mc_lower_bound:
        # Beyond the paper: the return a solved episode actually got from (s, a) is a lower bound on Q*(s, a),
        # so the team reward reaches early states without waiting for target syncs (the bound of
        # "optimality tightening" and self-imitation learning). Unsolved episodes' returns are cut off: no bound.
        target = torch.where(batch["solved"], torch.maximum(target, batch["mc_return"]), target)
    td = target - q_taken
    huber = F.huber_loss(q_taken, target, delta=args.huber_delta, reduction="none")
    l_dqn = (batch["weight"] * huber).mean() if "weight" in batch else huber.mean()  # importance weights
    labelled = batch["expert"] >= 0
    if labelled.any():
        scores = q - q.mean(dim=1, keepdim=True) if args.dueling else q  # the advantage A of the dueling split
        if args.imitation == "margin":
            l_hscl = margin_loss(scores[labelled], batch["expert"][labelled], args.margin)
        elif args.imitation == "ce":
            ce = F.cross_entropy(scores[labelled] / args.temperature, batch["expert"][labelled], reduction="none")
            w = torch.ones_like(ce)
            if args.blocker_weight != 1.0:
                w = torch.where(batch["blocker"][labelled], args.blocker_weight, w)
            if args.meet_weight != 1.0:
                w = torch.where(meeting_rows(batch["fov"][labelled]), w * args.meet_weight, w)
            if args.ongoal_weight != 1.0:
                expert_row = torch.arange(len(q)) < (len(q) if n_main is None else n_main)  # not the search's
                w = torch.where((ongoal_rows(batch["fov"]) & expert_row)[labelled], w * args.ongoal_weight, w)
            l_hscl = (w * ce).sum() / w.sum().clamp_min(1e-12)  # 0 where every labelled row weighs 0
        else:
            l_hscl = hscl_loss(scores[labelled], batch["expert"][labelled], args.tau_h, args.temperature)
    else:
        l_hscl = q.sum() * 0.0
    return l_dqn, l_hscl, td.detach()


def grad_norm(loss: torch.Tensor, params) -> float:
    grads = torch.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
    return float(torch.sqrt(sum((g.float() ** 2).sum() for g in grads if g is not None)))


def correlation(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.double() - a.double().mean(), b.double() - b.double().mean()
    den = float(a.norm() * b.norm())
    return float((a * b).sum()) / den if den > 0 else float("nan")


def greedy_outcomes(forward, cases, last_action: str, max_steps: int, epsilon: float = 0.0) -> list[tuple[bool, int]]:
    """(success, steps) per case with argmax Q and no exploration; a failure counts max_steps. With `epsilon` > 0
    (a diagnostic, not the paper's rule) each agent acts at random with that probability (seeded per case).
    The observation has the heading channel when forward's network reads it (forward.cfg.heading)."""
    outcomes = []
    for k, inst in enumerate(cases):
        cfg = getattr(forward, "cfg", NetworkConfig())
        env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=max_steps, last_action=last_action,
                      **cfg.env_channels())
        _, stats = play_episode(forward, env, epsilon, np.random.default_rng(k if epsilon > 0 else 0))
        outcomes.append((stats["success"], stats["steps"] if stats["success"] else max_steps))
    return outcomes


def greedy_success(forward, cases: list, last_action: str, max_steps: int) -> tuple[float, float]:
    """Success rate and average step of greedy_outcomes."""
    outcomes = greedy_outcomes(forward, cases, last_action, max_steps)
    return float(np.mean([s for s, _ in outcomes])), float(np.mean([t for _, t in outcomes]))


TRAIN_COLUMNS = ("step", "stage", "episodes", "l_dqn", "l_hscl", "hscl_weight", "dqn_share", "td_abs", "td_refused",
                 "refused_minus_stay", "refused_rows", "adv_norm", "q_mean", "mc_return_mean", "q_return_corr", "agreement",
                 "agreement_meet", "meet_share", "ongoal_share", "agreement_contact", "contact_share", "train_success", "train_steps",
                 "mean_team", "samples_per_s", "learner_steps_per_s", "env_rows_per_s",
                 "epsilon", "blocked_share", "rescued_episodes", "blocker_rows", "blocker_move_labels", "blocker_states",
                 "deviations", "mined_labels", "pp_label_share", "elapsed_s")
EVAL_COLUMNS = ("step", "stage", "agents", "size", "success_rate", "average_step", "ema_success_rate", "ema_average_step")


# --- the run ---------------------------------------------------------------------------------------------
def train(args: Args, run_dir: Path, progress: bool = True) -> dict:
    args.validate()
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(dataclasses.asdict(args), indent=1))
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(np.random.SeedSequence([args.seed, 11]))
    stages = [parse_stage(s) for s in args.stages]
    ncfg = args.network_config()
    net = QNetwork(ncfg).to(memory_format=torch.channels_last)
    target = QNetwork(ncfg).to(memory_format=torch.channels_last)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    state = {"step": 0, "stage": 0, "episodes": 0, "elapsed": 0.0, "hscl_weight": args.hscl_weight}
    ema = QNetwork(ncfg).to(memory_format=torch.channels_last) if args.ema_decay > 0 else None
    source = _resume(run_dir, Path(args.publish_dir) if args.publish_dir else None, net, target, opt, state, ncfg)
    resumed = source is not None
    if not resumed and args.init_model:
        loaded, cfg, _ = load_model(args.init_model)
        if cfg != ncfg:
            raise ValueError(f"--init-model {args.init_model}: its network {cfg} differs from this run's {ncfg}")
        net.load_state_dict(loaded.state_dict())
        print(f"started from the weights of {args.init_model}")
    if not resumed:
        target.load_state_dict(net.state_dict())
    starts = min(args.replay_capacity, max(args.learning_starts, args.resume_refill)) if resumed else args.learning_starts
    if resumed and starts > args.learning_starts:
        print(f"refilling the replay to {starts} rows before learning goes on (--resume-refill)")
    if ema is not None:  # the averaged weights saved beside the resumed ones, else a copy of the online weights
        ema.load_state_dict(_load_ema(source / "ema.pt", ncfg) if resumed and (source / "ema.pt").is_file()
                            else net.state_dict())
    truncate_log(run_dir / "train.csv", state["step"])
    truncate_log(run_dir / "eval.csv", state["step"])
    add_log_columns(run_dir / "train.csv", TRAIN_COLUMNS)
    add_log_columns(run_dir / "eval.csv", EVAL_COLUMNS)
    online_q, target_q, act_q = FastForward(net), InferenceNet(target), acting(net)
    params = [p for p in net.parameters()]
    ema_params = list(ema.parameters()) if ema is not None else []
    replay = Replay(args.replay_capacity, args.priority_alpha, args.priority_beta,
                    hidden=ncfg.hidden_features if args.recurrent else 0, channels=ncfg.fov_channels)
    mined_replay = Replay(MINED_CAPACITY, channels=ncfg.fov_channels) if args.mined_batch_share > 0 else None
    augmenter = Augmenter(ncfg.fov_size, ncfg.fov_channels, direction_blocks(ncfg)) if args.augment else None
    valid = {k: generated_cases(args.seed, VALID_STREAM, [a], args.eval_cases, s, args.density)
             for k, (a, s) in enumerate(stages)}
    train_log, eval_log = CsvLog(run_dir / "train.csv", TRAIN_COLUMNS), CsvLog(run_dir / "eval.csv", EVAL_COLUMNS)
    window = {"rows": 0, "steps": 0, "t": time.monotonic(), "m": collections.defaultdict(list), "eps": []}
    session_t0, last_ckpt, owed = time.monotonic(), time.monotonic(), 0.0
    deadline = session_t0 + 60 * args.session_minutes if args.session_minutes > 0 else float("inf")
    stop = {"now": False}
    signal.signal(signal.SIGTERM, lambda *_: stop.update(now=True))
    bar = tqdm(total=args.total_steps, initial=state["step"], desc=run_dir.name, unit="step", disable=not progress,
               mininterval=1.0 if sys.stderr.isatty() else 60.0)
    eps_at = lambda step: args.eps_start + min(1.0, step / max(1, args.eps_decay_steps)) * (args.eps_end - args.eps_start)  # noqa: E731
    try:
        while state["step"] < args.total_steps and not stop["now"] and time.monotonic() < deadline:
            # 1. One episode: the current stage, or an earlier one for review; expert- or policy-driven.
            k = state["stage"]
            if k > 0 and rng.random() < args.review_fraction:
                k = int(rng.integers(0, k))
            agents, size = stages[k]
            ep_rng = instance_rng(args.seed, ACTOR_STREAM, state["episodes"])
            inst = generate_instance(ep_rng, size=size, density=args.density, n_agents=agents)
            env = MapfEnv(inst.grid, inst.starts, inst.goals, max_steps=args.max_episode_steps, last_action=args.last_action,
                          **ncfg.env_channels())
            drive = ep_rng.random() < args.expert_drive_fraction
            relabel = drive or ep_rng.random() < args.relabel_fraction
            greedy = not drive and ep_rng.random() < args.greedy_fraction
            oracle = None
            if relabel or (greedy and args.stuck_rescue):  # the expert's way out needs the expert too
                oracle = make_oracle(args.expert, env.grid, env.goals, env.dist, args.expert_epsilon,
                                     min(args.expert_time_limit, args.relabel_time_budget), order=args.expert_order,
                                     objective=args.expert_objective)
            epsilon = 0.0 if greedy and not args.stuck_steps else eps_at(state["step"])
            if args.agent_eps_spread:
                epsilon = np.minimum(1.0, 2.0 * epsilon * rng.random(agents))
            steps, stats = play_episode(act_q, env, epsilon, rng, oracle, args.relabel_time_budget, drive,
                                        greedy_until_stuck=args.stuck_steps if greedy else 0,
                                        blocking=(args.blocking_penalty, args.blocking_margin),
                                        goal_exploration=args.goal_exploration,
                                        stuck_ends=args.stuck_value and greedy, stuck_rescue=args.stuck_rescue and greedy,
                                        stuck_rollout=args.stuck_rollout if greedy else 0,
                                        stuck_cycles=args.stuck_cycles)
            rows = episode_rows(steps, stats["success"], args.gamma, args.n_step, args.feasible_labels,
                                STILL_KEYS[args.still_count], goals=None if args.parked_labels else env.goals,
                                episode=state["episodes"], fixed_point=stats["fixed_point"], map_shape=env.grid.shape)
            stats["pp_states"] = getattr(oracle, "pp_states", 0)
            stats["odrm_states"] = getattr(oracle, "odrm_states", 0)
            # Look inside: the blockers' rows as stored, and how many carry a move label (the expert's way out).
            stats["blocker_rows"] = int(rows["blocker"].sum())
            stats["blocker_move_labels"] = int((rows["expert"][rows["blocker"]] > 0).sum())
            stats["blocker_states"] = distinct_observations(rows, rows["blocker"])
            replay.add(rows)
            # Beyond the paper (mine_episodes): greedy episodes whose only rows are the rollout search's deviations.
            stats["mined_labels"] = 0
            m_agents, m_size = (parse_stage(args.mine_stage) if args.mine_stage and k == len(stages) - 1
                                else (agents, size))
            m_envs = mining_envs(args.seed, state.get("mined", 0), args.mine_episodes, m_agents, m_size, args.density,
                                 args.max_episode_steps, args.last_action, ncfg)
            state["mined"] = state.get("mined", 0) + args.mine_episodes
            for m_steps, m_stats in mine(act_q, m_envs, args.stuck_rollout, rng):
                if m_stats["deviations"]:
                    m_rows = episode_rows(m_steps, m_stats["success"], args.gamma, args.n_step, False,
                                          STILL_KEYS[args.still_count], episode=state["episodes"],
                                          map_shape=(m_size, m_size))
                    keep = m_rows["expert"] >= 0
                    (replay if mined_replay is None else mined_replay).add({k: v[keep] for k, v in m_rows.items()})
                    stats["mined_labels"] += int(keep.sum())
            state["episodes"] += 1
            window["rows"] += len(rows["action"])
            window["eps"].append(stats)
            if replay.size < starts:
                continue
            # 2. Gradient steps: replay_ratio rows drawn per row produced.
            owed += len(rows["action"]) * args.replay_ratio / args.batch_size
            while owed >= 1.0 and state["step"] < args.total_steps and not stop["now"]:
                owed -= 1.0
                if args.recurrent:
                    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=args.bf16):
                        batch, q, next_q, next_online = recurrent_batch(net, target, online_q, target_q, act_q.fast,
                                                                        replay, args, rng)
                    q, q_target, n_main = q.float(), None, len(batch["index"])
                else:
                    batch, n_main = mixed_sample(replay, mined_replay, args.batch_size, args.mined_batch_share, rng)
                    if augmenter is not None:  # beyond the paper: each row in one of the grid's 8 orientations
                        batch = augmenter(batch, torch.from_numpy(rng.integers(0, len(SYMMETRIES), len(batch["action"]))))
                    still = (still_onehot(batch["still"], args.still_bins),) if args.still_bins else ()
                    next_still = (still_onehot(batch["next_still"], args.still_bins),) if args.still_bins else ()
                    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=args.bf16):
                        q = online_q(batch["fov"], batch["last_action"], batch["position"], *still).float()
                    with torch.no_grad():
                        next_q = target_q(batch["next_fov"], batch["next_last_action"], batch["next_position"], *next_still)
                        next_online = (act_q(batch["next_fov"], batch["next_last_action"], batch["next_position"],
                                             *next_still) if args.double_dqn else None)
                        q_target = (target_q(batch["fov"], batch["last_action"], batch["position"], *still)
                                    if args.advantage_learning > 0 else None)
                l_dqn, l_hscl, td = losses(q, next_q, batch, args, next_online, q_target, n_main)
                loss = args.dqn_weight * l_dqn + state["hscl_weight"] * l_hscl
                state["step"] += 1
                if args.lr_end > 0:
                    for group in opt.param_groups:
                        group["lr"] = learning_rate(args, state["step"])
                logging = state["step"] % args.log_every == 0
                if logging:  # 3. Look inside: each term's gradient, TD errors where moves were refused, Q vs return.
                    g_dqn = grad_norm(args.dqn_weight * l_dqn, params)
                    g_hscl = grad_norm(state["hscl_weight"] * l_hscl, params) if l_hscl.requires_grad else 0.0
                    share = g_dqn / max(1e-12, g_dqn + g_hscl)
                    if args.dqn_share > 0 and g_hscl > 0 and g_dqn > 0:
                        # Steer the HSCL weight toward the target share (a gentle multiplicative step, clipped).
                        wanted = g_dqn * (1 - args.dqn_share) / args.dqn_share / (g_hscl / state["hscl_weight"])
                        state["hscl_weight"] = float(np.clip(state["hscl_weight"] * (wanted / state["hscl_weight"]) ** 0.3,
                                                             1e-4, 100.0))
                    q_taken = q.detach().gather(1, batch["action"][:, None]).squeeze(1)
                    ref = batch["refused"]
                    lab = batch["expert"] >= 0
                    m = window["m"]
                    m["dqn_share"].append(share)
                    m["td_abs"].append(float(td.abs().mean()))
                    m["adv_norm"].append(float((q.detach() - q.detach().mean(dim=1, keepdim=True)).norm(dim=1).mean()))
                    m["refused_rows"].append(int(ref.sum()))
                    if ref.any():
                        m["td_refused"].append(float(td[ref].abs().mean()))
                        # A refused move leads where staying leads (executed last action), at -0.5 instead of
                        # -0.075: learned values put it 0.425 below staying.
                        qd = q.detach()[ref]
                        m["refused_minus_stay"].append(float((qd.gather(1, batch["action"][ref][:, None]).squeeze(1)
                                                              - qd[:, 0]).mean()))
                    m["q_mean"].append(float(q_taken.mean()))
                    m["mc_return_mean"].append(float(batch["mc_return"].mean()))
                    m["q_return_corr"].append(correlation(q_taken, batch["mc_return"]))
                    if lab.any():
                        m["agreement"].append(expert_agreement(q.detach()[lab], batch["expert"][lab]))
                    meet = lab & meeting_rows(batch["fov"])
                    m["meet_share"].append(float(meet.sum()) / max(1, int(lab.sum())))
                    ongoal = (lab & ongoal_rows(batch["fov"]))[:n_main]  # the expert's rows, not the search's
                    m["ongoal_share"].append(float(ongoal.sum()) / max(1, int(lab[:n_main].sum())))
                    if meet.any():
                        m["agreement_meet"].append(expert_agreement(q.detach()[meet], batch["expert"][meet]))
                    if ncfg.priority:  # rows touching an earlier agent: their share and agreement (contact_rows)
                        touch = lab & contact_rows(batch["fov"], args.priority_channel())
                        m["contact_share"].append(float(touch.sum()) / max(1, int(lab.sum())))
                        if touch.any():
                            m["agreement_contact"].append(expert_agreement(q.detach()[touch], batch["expert"][touch]))
                window["m"]["l_dqn"].append(l_dqn.item())
                window["m"]["l_hscl"].append(l_hscl.item())
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(params, args.grad_clip)
                opt.step()
                if ema is not None:
                    with torch.no_grad():
                        for averaged, p in zip(ema_params, params):
                            averaged.lerp_(p, 1.0 - args.ema_decay)
                replay.update_priorities(batch["index"][:n_main], td[:n_main])  # mined rows (last) keep none
                window["steps"] += 1
                bar.update(1)
                if state["step"] % args.target_update_every == 0:
                    target.load_state_dict(net.state_dict())
                if state["step"] in args.keep_ema_at:
                    _keep_ema(args, run_dir, ema, state["step"])
                if logging:
                    row = _log_row(args, state, window, session_t0, eps_at(state["step"]))
                    train_log.write(row)
                    bar.set_postfix(stage=args.stages[state["stage"]], share=f"{row['dqn_share']:.2f}",
                                    agree=f"{row['agreement']:.2f}", sr=f"{row['train_success']:.2f}")
                    window.update(rows=0, steps=0, t=time.monotonic(), m=collections.defaultdict(list), eps=[])
                if args.eval_every and state["step"] % args.eval_every == 0:
                    # 4. Greedy on validation cases; the curriculum moves on when the current stage passes.
                    current = state["stage"]
                    for j in range(min(len(stages), current + 2)):
                        sr, avg = greedy_success(act_q, valid[j], args.last_action, args.max_episode_steps)
                        ema_sr, ema_avg = (greedy_success(acting(ema), valid[j], args.last_action, args.max_episode_steps)
                                           if ema is not None and j == len(stages) - 1 else ("", ""))
                        eval_log.write({"step": state["step"], "stage": args.stages[j], "agents": stages[j][0],
                                        "size": stages[j][1], "success_rate": sr, "average_step": avg,
                                        "ema_success_rate": ema_sr, "ema_average_step": ema_avg})
                        if j == len(stages) - 1 and sr > state.get("best_success", -1.0):
                            # The best validation snapshot of the last stage (validation cases, never the ladder's):
                            # a run's last weights are one draw of a curve that wanders by +-0.1 at 40 cases.
                            state.update(best_success=sr, best_step=state["step"])
                            save_model(run_dir / "best.pt", net, ncfg,
                                       {"step": state["step"], "recipe": "dqn_hscl", "last_action": args.last_action,
                                        "validation_success": sr, "train_args": _plain(args)})
                        if j == current and sr >= args.advance_pass_rate and current + 1 < len(stages):
                            state["stage"] = current + 1
                            save_model(run_dir / f"passed_{args.stages[current]}.pt", net, ncfg,
                                       {"step": state["step"], "recipe": "dqn_hscl", "last_action": args.last_action})
                            tqdm.write(f"step {state['step']}: stage {args.stages[current]} passed (greedy {sr:.3f}), "
                                       f"now {args.stages[current + 1]}")
            if time.monotonic() - last_ckpt > 60 * args.checkpoint_minutes:
                _checkpoint(args, run_dir, net, target, opt, state, session_t0, ema)
                last_ckpt = time.monotonic()
    except KeyboardInterrupt:
        tqdm.write(f"interrupted at step {state['step']}")
    finally:
        bar.close()
        _checkpoint(args, run_dir, net, target, opt, state, session_t0, ema)
    return state


def _log_row(args: Args, state: dict, window: dict, session_t0: float, epsilon: float) -> dict:
    dt = max(1e-9, time.monotonic() - window["t"])
    mean = lambda k: float(np.mean(window["m"][k])) if window["m"][k] else float("nan")  # noqa: E731
    eps = window["eps"]
    return {"step": state["step"], "stage": args.stages[state["stage"]], "episodes": state["episodes"],
            "l_dqn": mean("l_dqn"), "l_hscl": mean("l_hscl"), "hscl_weight": state["hscl_weight"],
            "dqn_share": mean("dqn_share"), "td_abs": mean("td_abs"), "td_refused": mean("td_refused"),
            "refused_minus_stay": mean("refused_minus_stay"),
            "refused_rows": int(sum(window["m"]["refused_rows"])), "adv_norm": mean("adv_norm"), "q_mean": mean("q_mean"),
            "mc_return_mean": mean("mc_return_mean"), "q_return_corr": mean("q_return_corr"), "agreement": mean("agreement"),
            "agreement_meet": mean("agreement_meet"), "meet_share": mean("meet_share"), "ongoal_share": mean("ongoal_share"),
            "agreement_contact": mean("agreement_contact"), "contact_share": mean("contact_share"),
            "train_success": float(np.mean([e["success"] for e in eps if not e["expert_drove"]] or [np.nan])),
            "train_steps": float(np.mean([e["steps"] for e in eps] or [np.nan])),
            "mean_team": float(np.mean([e["n_agents"] for e in eps] or [np.nan])),
            "samples_per_s": window["steps"] * args.batch_size / dt, "learner_steps_per_s": window["steps"] / dt,
            "env_rows_per_s": window["rows"] / dt, "epsilon": epsilon,
            "blocked_share": sum(e["blocked"] for e in eps) / max(1, sum(e["steps"] * e["n_agents"] for e in eps)),
            "rescued_episodes": sum(e["rescued"] for e in eps),
            "blocker_rows": sum(e.get("blocker_rows", 0) for e in eps),
            "blocker_move_labels": sum(e.get("blocker_move_labels", 0) for e in eps),
            "blocker_states": sum(e.get("blocker_states", 0) for e in eps),
            "deviations": sum(e.get("deviations", 0) for e in eps),
            "mined_labels": sum(e.get("mined_labels", 0) for e in eps),
            # expert 'prioritized': the share of labelled states the prioritized plan answered (the rest: ODrM*)
            "pp_label_share": (sum(e.get("pp_states", 0) for e in eps)
                               / max(1, sum(e.get("pp_states", 0) + e.get("odrm_states", 0) for e in eps))),
            "elapsed_s": round(state["elapsed"] + time.monotonic() - session_t0, 1)}


# --- checkpoints and resuming -------------------------------------------------------------------------------
def add_log_columns(path: Path, columns: tuple) -> None:
    """A log written before a column was added (a resumed run) gets it, empty in its old rows; the columns are
    then `columns` in that order. Any other difference is left for CsvLog to refuse."""
    import csv

    if not path.is_file():
        return
    with path.open() as f:
        header = next(csv.reader(f), None)
        rows = list(csv.DictReader(f, fieldnames=header)) if header else []
    if header is None or tuple(header) == tuple(columns) or not set(header) < set(columns):
        return
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(rows)
def _checkpoint(args: Args, run_dir: Path, net, target, opt, state: dict, session_t0: float, ema=None) -> None:
    """runs/<name>/checkpoint.pt (with the optimizer, for this machine) and last.pt + state.json (weights and
    counters only: what publish_dir carries to a fresh machine), and ema.pt with ema_decay."""
    st = {**state, "elapsed": state["elapsed"] + time.monotonic() - session_t0}
    meta = {"step": st["step"], "recipe": "dqn_hscl", "last_action": args.last_action, "train_args": _plain(args)}
    tmp = run_dir / "checkpoint.pt.tmp"
    torch.save({"state": st, "target": target.state_dict(), "optimizer": opt.state_dict()}, tmp)
    os.replace(tmp, run_dir / "checkpoint.pt")
    save_model(run_dir / "last.pt", net, args.network_config(), meta)
    if ema is not None:
        save_model(run_dir / "ema.pt", ema, args.network_config(), {**meta, "ema_decay": args.ema_decay})
    (run_dir / "state.json").write_text(json.dumps(st, indent=1))
    plot_run(run_dir)
    if args.publish_dir:
        pub = Path(args.publish_dir)
        pub.mkdir(parents=True, exist_ok=True)
        for name in ("last.pt", "ema.pt", "best.pt", "state.json", "config.json", "train.csv", "eval.csv", "training.png"):
            if (run_dir / name).is_file():
                data = (run_dir / name).read_bytes()
                (pub / (name + ".tmp")).write_bytes(data)
                os.replace(pub / (name + ".tmp"), pub / name)


def _keep_ema(args: Args, run_dir: Path, ema, step: int) -> None:
    """ema_at<step>.pt in the run folder and in publish_dir (Args.keep_ema_at)."""
    name = f"ema_at{step}.pt"
    meta = {"step": step, "recipe": "dqn_hscl", "last_action": args.last_action, "ema_decay": args.ema_decay,
            "train_args": _plain(args)}
    save_model(run_dir / name, ema, args.network_config(), meta)
    if args.publish_dir:  # written whole, then renamed, as _checkpoint publishes
        pub = Path(args.publish_dir)
        pub.mkdir(parents=True, exist_ok=True)
        (pub / (name + ".tmp")).write_bytes((run_dir / name).read_bytes())
        os.replace(pub / (name + ".tmp"), pub / name)


def _plain(args: Args) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(args).items()}


def _resume(run_dir: Path, publish: Path | None, net, target, opt, state: dict, ncfg: NetworkConfig) -> Path | None:
    """Full resume from runs/<name>/checkpoint.pt; else weights-only from publish_dir (fresh optimizer, target =
    online); else nothing (a new run). Returns the folder it resumed from (run_dir or publish), or None."""
    ck = run_dir / "checkpoint.pt"
    if ck.is_file() and (run_dir / "last.pt").is_file():
        loaded, cfg, _ = load_model(run_dir / "last.pt")
        if cfg != ncfg:
            raise ValueError(f"{run_dir}: the saved network {cfg} differs from this run's {ncfg}")
        payload = torch.load(ck, map_location="cpu", weights_only=True)
        net.load_state_dict(loaded.state_dict())
        target.load_state_dict(payload["target"])
        opt.load_state_dict(payload["optimizer"])
        state.update(payload["state"])
        print(f"resumed {run_dir} at step {state['step']} (stage {state['stage']})")
        return run_dir
    if publish is not None and (publish / "last.pt").is_file() and (publish / "state.json").is_file():
        loaded, cfg, _ = load_model(publish / "last.pt")
        if cfg != ncfg:
            raise ValueError(f"{publish}: the published network {cfg} differs from this run's {ncfg}")
        net.load_state_dict(loaded.state_dict())
        target.load_state_dict(loaded.state_dict())
        state.update(json.loads((publish / "state.json").read_text()))
        for name in ("train.csv", "eval.csv", "best.pt"):
            if (publish / name).is_file() and not (run_dir / name).is_file():
                (run_dir / name).write_bytes((publish / name).read_bytes())
        print(f"resumed weights from {publish} at step {state['step']} (fresh optimizer)")
        return publish
    return None


def _load_ema(path: Path, ncfg: NetworkConfig) -> dict:
    """The state dict of averaged weights saved at `path` (Args.ema_decay), refused if its network is not ncfg."""
    loaded, cfg, _ = load_model(path)
    if cfg != ncfg:
        raise ValueError(f"{path}: the averaged network {cfg} differs from this run's {ncfg}")
    return loaded.state_dict()


def plot_run(run_dir: Path) -> Path | None:
    """training.png: the terms and their gradient shares, TD errors, Q vs returns, greedy validation per stage."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not (run_dir / "train.csv").is_file():
        return None
    log = _read_log(run_dir / "train.csv")
    if not log:
        return None
    ev = _read_log(run_dir / "eval.csv") if (run_dir / "eval.csv").is_file() else {}
    s = log["step"]
    fig, ax = plt.subplots(2, 4, figsize=(18, 7.5), constrained_layout=True)
    ax[0, 0].plot(s, log["l_dqn"], lw=1, label="DQN (Huber)")
    ax[0, 0].plot(s, log["l_hscl"], lw=1, label="HSCL")
    ax[0, 0].set_yscale("log"), ax[0, 0].set_title("loss terms"), ax[0, 0].legend(fontsize=7)
    ax[0, 1].plot(s, log["dqn_share"], lw=1, label="DQN share of |grad|")
    ax[0, 1].plot(s, log["hscl_weight"], lw=1, label="HSCL weight")
    ax[0, 1].set_title("gradient share"), ax[0, 1].legend(fontsize=7)
    ax[0, 2].plot(s, log["td_abs"], lw=1, label="|TD| all rows")
    ax[0, 2].plot(s, log["td_refused"], lw=1, label="|TD| refused-move rows")
    if "refused_minus_stay" in log:
        ax[0, 2].plot(s, log["refused_minus_stay"], lw=1, label="Q(refused move) - Q(stay)")
        ax[0, 2].axhline(-0.425, color="grey", lw=0.8, ls=":")
    ax[0, 2].set_title("TD error"), ax[0, 2].legend(fontsize=7)
    ax[0, 3].plot(s, log["q_mean"], lw=1, label="mean Q(s,a)")
    ax[0, 3].plot(s, log["mc_return_mean"], lw=1, label="mean MC return")
    ax[0, 3].plot(s, log["q_return_corr"], lw=1, label="corr(Q, MC return)")
    if "adv_norm" in log:
        ax[0, 3].plot(s, log["adv_norm"], lw=1, label="|A|, advantage norm")
    ax[0, 3].set_title("Q against returns"), ax[0, 3].legend(fontsize=7)
    ax[1, 0].plot(s, log["agreement"], lw=1, label="labelled rows")
    if "agreement_meet" in log:
        ax[1, 0].plot(s, log["agreement_meet"], lw=1, label="off goal, another agent in view")
    if "agreement_contact" in log and np.isfinite(log["agreement_contact"]).any():
        ax[1, 0].plot(s, log["agreement_contact"], lw=1, label="off goal, touching an earlier agent")
    for key, label in (("meet_share", "share of labelled rows: off goal, another in view"),
                       ("ongoal_share", "share of expert rows: on goal, another in view")):
        if key in log and np.isfinite(log[key]).any():
            ax[1, 0].plot(s, log[key], ":", lw=1, label=label)
    ax[1, 0].set_title("argmax Q = expert label (batch)"), ax[1, 0].legend(fontsize=6)
    ax[1, 1].plot(s, log["train_success"], lw=1, label="training episodes (eps-greedy)")
    if ev:
        for st in sorted(set(ev["stage"])):
            sel = ev["stage"] == st
            ax[1, 1].plot(ev["step"][sel], ev["success_rate"][sel], "o-", ms=3, lw=1, label=f"greedy validation {st}")
            if "ema_success_rate" in ev and np.isfinite(ev["ema_success_rate"][sel]).any():
                ax[1, 1].plot(ev["step"][sel], ev["ema_success_rate"][sel], "s--", ms=3, lw=1,
                              label=f"greedy validation {st}, averaged weights")
    ax[1, 1].set_title("success rate"), ax[1, 1].legend(fontsize=6)
    ax[1, 2].plot(s, log["stage_index"], lw=1, label="curriculum stage (index)")
    if "blocked_share" in log and np.nansum(log["blocked_share"]) > 0:
        ax[1, 2].plot(s, 100 * log["blocked_share"], lw=1, label="% agent-steps charged the blocking penalty")
    ax[1, 2].set_title("curriculum, blocking"), ax[1, 2].legend(fontsize=7)
    ax[1, 3].plot(s, log["learner_steps_per_s"], lw=1, label="learner steps/s")
    ax[1, 3].plot(s, log["env_rows_per_s"] / 100, lw=1, label="env rows/s / 100")
    ax[1, 3].set_title("speed"), ax[1, 3].legend(fontsize=7)
    for a in ax.flat:
        a.set_xlabel("learner step"), a.grid(alpha=0.3)
    out = run_dir / "training.png"
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


def _read_log(path: Path) -> dict:
    """read_csv, with the 'stage' column kept as text (and its order as stage_index)."""
    import csv

    with path.open() as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return {}
    out = {}
    for key in rows[0]:
        if key == "stage":
            out[key] = np.array([r[key] for r in rows])
        else:
            out[key] = np.array([float(r[key]) if r[key] != "" else np.nan for r in rows])
    if "stage" in out:
        order = list(dict.fromkeys(out["stage"]))
        out["stage_index"] = np.array([order.index(v) for v in out["stage"]], dtype=float)
    return out


# --- command line ---------------------------------------------------------------------------------------
def main(argv=None) -> int:
    from mapf_policy.train.__main__ import field_docs

    parser = argparse.ArgumentParser(prog="scripts/dqn_hscl", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    docs = field_docs(Args)
    for f in dataclasses.fields(Args):
        flag, helptext = "--" + f.name.replace("_", "-"), f"{docs.get(f.name, '')} (default: {f.default!r})"
        helptext = helptext.replace("%", "%%")  # argparse formats help with %
        if isinstance(f.default, bool):
            parser.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction, default=f.default, help=helptext)
        elif isinstance(f.default, tuple):
            parser.add_argument(flag, dest=f.name, nargs="+", default=f.default, help=helptext)
        else:
            parser.add_argument(flag, dest=f.name, type=type(f.default), default=f.default, help=helptext)
    parser.add_argument("--runs-dir", default="runs", help="where run directories live (default: runs)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    ns = parser.parse_args(argv)
    values = {f.name: getattr(ns, f.name) for f in dataclasses.fields(Args)}
    values["stages"] = tuple(values["stages"])
    try:
        bad = [k for k in values["keep_ema_at"] if not str(k).isdigit()]
        if bad:
            raise ValueError(f"keep_ema_at takes learner steps (whole numbers), got {bad}")
        values["keep_ema_at"] = tuple(int(k) for k in values["keep_ema_at"])
        args = Args(**values)
        args.validate()
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    run_dir = Path(ns.runs_dir) / args.run_name
    saved = run_dir / "config.json"
    if saved.is_file():
        old = json.loads(saved.read_text())
        schedule = {"total_steps", "session_minutes", "resume_refill", "eval_every", "log_every", "checkpoint_minutes", "publish_dir", "threads",
                    "keep_ema_at"}
        defaults = _plain(Args())  # a field added after the run started has its default there
        differ = sorted(k for k, v in _plain(args).items() if k not in schedule and old.get(k, defaults[k]) != v)
        if differ:
            print(f"error: run {run_dir} exists with other values of {differ}; resume without them or pick another "
                  f"--run-name", file=sys.stderr)
            return 2
        retired = sorted(k for k, off in RETIRED.items() if old.get(k, off) != off)
        if retired:
            print(f"error: run {run_dir} was trained with the retired options {retired} (their ablations lost; "
                  f"models/EXPERIMENTS.md); this code cannot resume it", file=sys.stderr)
            return 2
    if args.init_model and not (run_dir / "last.pt").is_file():
        _, init_cfg, _ = load_model(args.init_model)
        if init_cfg != args.network_config():
            print(f"error: --init-model {args.init_model} holds the network {init_cfg}, this run builds "
                  f"{args.network_config()}", file=sys.stderr)
            return 2
    pub = Path(args.publish_dir) if args.publish_dir else None
    if (pub is not None and not (run_dir / "checkpoint.pt").is_file() and (pub / "state.json").is_file()
            and not (pub / "last.pt").is_file()):
        # A published run without its online weights (last.pt kept out of git, say) cannot resume, and starting
        # afresh would overwrite its committed logs without a word.
        step = json.loads((pub / "state.json").read_text()).get("step", "?")
        print(f"error: {pub} holds a run at step {step} but no last.pt, so it cannot resume: commit last.pt with "
              f"the run, or move {pub} away to start it afresh", file=sys.stderr)
        return 2
    print(f"run {run_dir}\n" + json.dumps(_plain(args), indent=1))
    state = train(args, run_dir, progress=not ns.no_progress)
    print(f"stopped at step {state['step']}, stage {args.stages[state['stage']]}; model {run_dir / 'last.pt'}")
    if "best_step" in state:
        print(f"best validation of stage {args.stages[-1]}: {state['best_success']:.3f} at step {state['best_step']}; "
              f"model {run_dir / 'best.pt'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
