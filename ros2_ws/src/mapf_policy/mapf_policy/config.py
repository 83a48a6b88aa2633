"""Typed configurations of the learned policy: the network (`NetworkConfig`) and training (`TrainConfig`).

Every field has a docstring; `validate()` raises ValueError naming the bad field. Both configs round-trip
through plain dicts (`asdict` / `from_dict`), which is how they are stored in model files and run dirs.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from mapf_world.observation import ExtraChannels

# Orders in which the expert's oracle hands the agents to ODrM* (TrainConfig.expert_order); what each
# means and why it matters: mapf_policy/train/expert.py, agent_order.
EXPERT_ORDERS = ("index", "reversed", "position")
# NetworkConfig.still_count -> the MapfEnv observation key it reads.
STILL_KEYS = {"cell": "still", "refused": "refused_run", "contact": "contact_run", "revisit": "revisits"}


def _from_dict(cls, data: dict, what: str):
    """Build dataclass `cls` from `data`; unknown keys are an error (a typo must not pass silently)."""
    if not isinstance(data, dict):
        raise ValueError(f"{what} must be a dict, got {type(data).__name__}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{what} has unknown fields {unknown}; known: {sorted(names)}")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name in data:
            value = data[f.name]
            # JSON and torch round trips turn tuples into lists; the configs use tuples.
            kwargs[f.name] = tuple(value) if isinstance(value, list) else value
    obj = cls(**kwargs)
    obj.validate()
    return obj


@dataclass(frozen=True)
class NetworkConfig:
    """Architecture of `QNetwork` (paper section III-E, Fig. 2).

    The defaults give 1,004,443 parameters, the paper's count (see network.py for how each width was chosen).
    """

    fov_size: int = 9
    """Side l of the l x l field of view; the conv trunk (no padding) shrinks it by 2 per conv, 9 -> 1."""
    in_channels: int = 6
    """Observation channels: obstacles, other agents, 4 heuristic channels (section III-B)."""
    conv_channels: tuple = (64, 128, 192, 256)
    """Output channels of the four 3x3 stride-1 convolutions (paper: 64, 128, 192, 256)."""
    self_attention: bool = True
    """Use the self-attention module on the raw observation (False: the Table III ablation)."""
    channel_attention: bool = True
    """Use CBAM channel attention after the conv trunk (False: ablation)."""
    spatial_attention: bool = True
    """Use CBAM spatial attention after channel attention (False: ablation)."""
    attention_eta: float = 1.0
    """Coefficient eta of y = x + eta * o (eq. 4); the paper fixes it to 1 (a constant, not learned)."""
    cbam_reduction: int = 16
    """Reduction ratio r of the channel-attention MLP: 256 -> 256 / r -> 256 (CBAM's default 16)."""
    spatial_kernel: int = 7
    """Kernel size of the spatial-attention convolution over [channel-mean, channel-max] (CBAM's 7)."""
    action_features: int = 512
    """Width of the fully connected layer applied to the one-hot last action."""
    position_features: int = 64
    """Width of the fully connected layer applied to the (normalised) position."""
    hidden_features: int = 300
    """Width of the first of the two fully connected layers that map the concatenation to Q-values."""
    position_scale: float = 40.0
    """Raw (row, col) positions are divided by this inside the network (the 40x40 training worlds)."""
    n_actions: int = 5
    """Number of actions (stay, up, down, left, right)."""
    dueling: bool = False
    """Dueling split of the output (second design, models/README.md): Q = V + A - mean(A), with one extra
    FC 300 -> 1 for V (301 parameters). HSCL then acts on the advantage A and the DQN fits the level through V.
    False: the paper's single FC 300 -> 5 (every model before the second design)."""
    still_bins: int = 0
    """Beyond the paper: an input of how many steps the agent has stood on the same cell (0 after a move),
    one-hot in this many bins, the last meaning "this many minus one or more" (still_onehot), through an
    FC still_bins -> still_features. A memoryless greedy team whose cells do not change sees the same
    observations and repeats the same actions for ever (the fixed points of issue 20); with this input the
    observations change while it waits. 0: no such input (the paper's network, every earlier model)."""
    still_features: int = 64
    """Width of the fully connected layer applied to the still input (when still_bins > 0)."""
    recurrent: bool = False
    """Beyond the paper (DHC's design): a GRU cell hidden_features -> hidden_features between the first fully
    connected layer and the output, so each agent keeps a memory of its own observations across steps
    (QNetwork.step; 3 x 2 x (300 x 300 + 300) = 541,800 more parameters). A memoryless greedy agent at a fixed
    point sees the same observation each step and repeats itself (issue 20); with memory it can tell a neighbour
    that has waited beside it for several steps from one passing by. False: the paper's feed-forward network."""
    still_count: str = "cell"
    """What the still input counts (MapfEnv): 'cell', the steps the agent has stood on the same cell (observation
    key 'still'), 'refused', its consecutive refused moves (key 'refused_run'; 0 after a stay or a move), or
    'contact', the steps it has stood still with the same neighbour cells held by agents (key 'contact_run'), or
    'revisit', how often its last 16 positions held its current cell (key 'revisits'): a loop of any period raises
    it, a first visit does not (the thirty-third session's experiment)."""

    heading: bool = False
    """Beyond the paper: a seventh fov channel, the cells the other agents face (each one's cell plus its last
    requested move; MapfEnv(heading=True)). A parked agent cannot tell a neighbour that needs its cell from one
    passing by (issue 20's greedy fixed points); a neighbour that keeps facing its cell tells it, with no
    communication. Adds 64 x 9 weights to the first conv and widens the self-attention to 7 channels.
    False: the paper's six channels (every model before it)."""
    heading_refused: bool = False
    """Beyond the paper, with `heading`: the channel marks only the cells that other agents' refused moves tried to
    enter (MapfEnv(heading_refused=True)). The requested heading of a neighbour that has just stepped up beside an
    agent marks the agent's cell just as a refused push does; this one marks the push alone. False: every move."""
    priority: bool = False
    """Beyond the paper: one more fov channel after the heading channel (if any), the cells of the other agents ahead
    of this one in the instance's agent order (MapfEnv(priority=True)). Two agents in a head-on see mirror images
    and the joint expert's labels tell both to push (issue 20, finding 3); the expert settles who gives way by this
    order, which a ground station can show every robot. False: not (every earlier model)."""
    goal_dirs: bool = False
    """Beyond the paper: four more fov channels, last, with which way each other agent in view has to go to its goal
    (at its cell, its own heuristic bits; MapfEnv(goal_dirs=True)). The expert's labels in a meeting depend on the
    others' goals, which the paper's observation does not show (issue 20, twenty-seventh session: drawing the goals
    of the agents ahead anew changes the label at 0.39-0.53 of the loop steps a greedy team gets wrong, 0.04-0.17 when
    the draws keep these bits). False: not (every earlier model)."""

    @property
    def fov_channels(self) -> int:
        """Channels of the fov the network reads: the paper's six, plus the heading, priority and goal-direction
        channels if any."""
        return self.in_channels + self.extra_channels().count

    def env_channels(self) -> dict:
        """MapfEnv keyword arguments that give observations with the channels this network reads, and a joint state
        (MapfEnv.joint_state) that holds the revisits count as far as this network reads it."""
        revisit_cap = self.still_bins - 1 if self.still_bins and self.still_count == "revisit" else 0
        return {"heading": self.heading, "heading_refused": self.heading_refused, "priority": self.priority,
                "goal_dirs": self.goal_dirs, "revisit_cap": revisit_cap}

    def extra_channels(self) -> ExtraChannels:
        """The fov channels beyond the paper's six that this network reads (mapf_world.observation.ExtraChannels:
        its `names`, in fov order, are what the world node must publish; `count` is 0 for the paper's network)."""
        return ExtraChannels(self.heading, self.heading_refused, self.priority, self.goal_dirs)

    def validate(self) -> None:
        if self.fov_size < 9 or self.fov_size % 2 == 0:
            raise ValueError(f"fov_size must be an odd integer >= 9 (four 3x3 convs), got {self.fov_size}")
        if self.in_channels != 6:
            raise ValueError(f"in_channels must be 6 (section III-B), got {self.in_channels}")
        if len(self.conv_channels) != 4 or any(int(c) < 1 for c in self.conv_channels):
            raise ValueError(f"conv_channels must be four positive ints, got {self.conv_channels}")
        if self.conv_channels[-1] % self.cbam_reduction != 0 or self.cbam_reduction < 1:
            raise ValueError(f"cbam_reduction {self.cbam_reduction} must divide {self.conv_channels[-1]}")
        if self.spatial_kernel < 1 or self.spatial_kernel % 2 == 0:
            raise ValueError(f"spatial_kernel must be odd and positive, got {self.spatial_kernel}")
        for name in ("action_features", "position_features", "hidden_features"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not self.position_scale > 0:
            raise ValueError(f"position_scale must be > 0, got {self.position_scale}")
        if self.n_actions != 5:
            raise ValueError(f"n_actions must be 5, got {self.n_actions}")
        if self.heading_refused and not self.heading:
            raise ValueError("heading_refused needs heading (it says what the heading channel marks)")
        if self.still_count not in STILL_KEYS:
            raise ValueError(f"still_count must be one of {tuple(STILL_KEYS)}, got {self.still_count!r}")
        if self.still_bins < 0 or self.still_bins == 1 or self.still_features < 1:
            raise ValueError(f"still_bins must be 0 (no input) or >= 2, and still_features >= 1; got "
                             f"{self.still_bins}, {self.still_features}")

    def asdict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "NetworkConfig":
        return _from_dict(cls, data, "NetworkConfig")


# The three ablations of Table III, by solver-registry name.
ABLATIONS = {
    "hscl_no_self_attention": {"self_attention": False},
    "hscl_no_channel_attention": {"channel_attention": False},
    "hscl_no_spatial_attention": {"spatial_attention": False},
}

VARIANTS = ("hscl",) + tuple(ABLATIONS)


@dataclass(frozen=True)
class TrainConfig:
    """One training run (scripts/train). Saved as config.json in the run directory.

    Step counts are learner gradient steps. Episodes are generated by `actors` actor processes.
    """

    # --- run bookkeeping ---
    run_name: str = ""
    """Run directory name under runs_dir; empty: derived from what runs (variant, map, agents, seed)."""
    runs_dir: str = "runs"
    """Where run directories live (relative paths are relative to the repository root)."""
    cache_dir: str = "cache"
    """Where cached expert demonstration shards live (relative to the repository root)."""
    seed: int = 0
    """Seeds torch, numpy and every generated instance (actor, demos and validation use separate streams)."""
    device: str = "cpu"
    """Learner device: 'cpu' or 'cuda' (actors always run on CPU)."""
    learner_threads: int = 1
    """torch threads of the learner process."""
    actor_threads: int = 1
    """torch threads of each actor process."""
    actors: int = 1
    """Actor processes generating episodes (one per spare core; on a GPU machine, cores minus one)."""
    session_minutes: float = 0.0
    """Stop with a checkpoint after this many wall-clock minutes of this session (0: no limit), for time-boxed jobs."""
    total_steps: int = 200_000
    """Learner gradient steps of the whole run (a resumed run continues up to this)."""
    checkpoint_minutes: float = 5.0
    """Wall-clock minutes between checkpoints (model, target, optimizer, counters, RNG states)."""
    log_every: int = 100
    """Learner steps between CSV log rows."""
    init_model: str = ""
    """Model file whose weights start a new run (fine-tuning); empty: random init. Unused on resume."""
    # --- network and losses ---
    variant: str = "hscl"
    """Architecture: 'hscl' (full) or an ablation ('hscl_no_self_attention', ...)."""
    batch_size: int = 128
    """Transitions per gradient step (online and demonstration samples together)."""
    demo_fraction: float = 0.5
    """Share of each batch drawn from expert demonstrations (the rest from the actors' replay)."""
    lr: float = 1e-4
    """Adam learning rate."""
    grad_clip: float = 10.0
    """Global gradient-norm bound (torch clip_grad_norm_), for stability of the bootstrapped targets."""
    gamma: float = 0.99
    """Discount factor of the DQN target (eq. 8)."""
    target_update_every: int = 2000
    """Learner steps between copies of the online network into the target network."""
    delta: float = 0.5
    """Weight of the DQN loss L1 (eq. 14)."""
    phi: float = 0.5
    """Weight of the HSCL loss L2 (eq. 14)."""
    tau_h: float = 0.1
    """Hot-vector offset tau of Table I, 0 < tau_h < 0.2."""
    temperature: float = 0.1
    """Temperature T of HSCL (eq. 13)."""
    # --- replay and actors ---
    replay_capacity: int = 200_000
    """Transitions kept in the actors' replay buffer (oldest overwritten)."""
    demo_capacity: int = 400_000
    """At most this many demonstration transitions are loaded from the cache (evenly subsampled)."""
    demo_goal_keep: float = 0.1
    """Share kept of the demonstration rows where an agent waits on its goal (about 2/3 of raw rows)."""
    online_goal_keep: float = 1.0
    """Share kept of the actors' rows where an agent waits on its goal and the expert says stay (demos.on_goal_stays),
    when they enter the replay; terminal rows are always kept. 1: all (the paper; every run before the eighth
    session). In large teams most rows are such waits, where the policy already agrees with the expert; the
    crowded rows, where it often does not, get a larger share of each batch when fewer waits are kept."""
    learning_starts: int = 2_000
    """Online transitions received from the actors (before the online_goal_keep filter) before online samples
    enter batches."""
    replay_ratio: float = 2.0
    """Target (online samples drawn by the learner) / (online samples produced); the actor waits above it."""
    max_replay_ratio: float = 0.0
    """Learner-side cap on (online samples drawn) / (online samples produced) in this session; the learner
    waits above it (0: no cap). For a GPU learner that outruns its actors and would overfit a small replay."""
    weights_sync_every: int = 200
    """Learner steps between publishing weights to the actor."""
    eps_start: float = 0.3
    """Epsilon of the epsilon-greedy actor at step 0."""
    eps_end: float = 0.05
    """Epsilon after eps_decay_steps (kept constant afterwards)."""
    eps_decay_steps: int = 50_000
    """Learner steps of the linear epsilon decay."""
    actor_action_temperature: float = 0.0
    """Actors' choice of the non-random actions: 0 = argmax (epsilon-greedy, the paper); T > 0 = draws from
    softmax(Q / T) with settled agents greedy, as the evaluated policy does (action_selection.py), so that
    training visits the states the sampled policy meets. Epsilon applies on top."""
    relabel_fraction: float = 0.5
    """Share of actor episodes whose visited states get expert (ODrM*) labels for HSCL."""
    relabel_time_budget: float = 5.0
    """Seconds of expert planning per relabelled episode; the rest of the episode stays unlabelled."""
    # --- worlds ---
    map_size: int = 40
    """Side of the square training worlds."""
    density: float = 0.3
    """Obstacle density of the training worlds."""
    min_agents: int = 1
    """Smallest team size drawn per episode."""
    max_agents: int = 64
    """Largest team size drawn per episode (after the curriculum)."""
    curriculum_start_agents: int = 8
    """Largest team size at step 0; it grows linearly to max_agents over curriculum_steps."""
    curriculum_steps: int = 40_000
    """Learner steps of the team-size curriculum (0: none)."""
    fov_size: int = 9
    """Field of view l."""
    max_episode_steps: int = 256
    """Episode step limit (the benchmark's 256)."""
    # --- expert ---
    expert: str = "odrmstar"
    """Expert: 'odrmstar' (C++ ODrM*, the paper's) or 'shortest_path' (per-agent BFS, a test stand-in)."""
    expert_epsilon: float = 10.0
    """Inflation epsilon of ODrM* (paper: 10)."""
    expert_time_limit: float = 10.0
    """Seconds per ODrM* planning call."""
    expert_order: str = "index"
    """Order in which the relabelling oracle hands the agents to ODrM* (EXPERT_ORDERS above): 'index'
    (the instance's, the paper), 'reversed', or 'position' (by current cell, row first, at every call: an order
    each agent can work out from its own view). The demonstration cache is planned in index order."""
    demo_instances: int = 1000
    """Training instances solved by the expert into the demonstration cache (never benchmark cases)."""
    demo_shard_size: int = 50
    """Instances per cached .npz shard (the unit of resumable generation)."""
    data_workers: int = 1
    """Processes generating demonstration shards."""
    # --- validation (generated instances, never the benchmark) ---
    eval_minutes: float = 15.0
    """Wall-clock minutes between greedy validation runs in actor 0 (0: never)."""
    eval_sizes: tuple = (8, 32, 64)
    """Team sizes of the validation instances."""
    eval_instances: int = 8
    """Validation instances per team size."""

    def validate(self) -> None:
        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise ValueError(msg)

        need(self.variant in VARIANTS, f"variant must be one of {VARIANTS}, got {self.variant!r}")
        need(self.device in ("cpu", "cuda") or self.device.startswith("cuda:"), f"device must be cpu or cuda, got {self.device!r}")
        for name in ("learner_threads", "actor_threads", "actors", "total_steps", "log_every", "batch_size", "target_update_every",
                     "replay_capacity", "demo_capacity", "weights_sync_every", "map_size", "min_agents", "max_agents",
                     "curriculum_start_agents", "max_episode_steps", "demo_shard_size", "data_workers", "eval_instances"):
            need(int(getattr(self, name)) >= 1, f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("learning_starts", "eps_decay_steps", "curriculum_steps", "demo_instances"):
            need(int(getattr(self, name)) >= 0, f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("demo_fraction", "demo_goal_keep", "online_goal_keep", "eps_start", "eps_end", "relabel_fraction", "density"):
            need(0.0 <= getattr(self, name) <= 1.0, f"{name} must lie in [0, 1], got {getattr(self, name)}")
        need(self.density < 0.6, f"density must be < 0.6 for solvable worlds, got {self.density}")
        need(0.0 < self.tau_h < 0.2, f"tau_h must lie in (0, 0.2) (Table I), got {self.tau_h}")
        for name in ("lr", "grad_clip", "temperature", "replay_ratio", "expert_time_limit", "checkpoint_minutes"):
            need(getattr(self, name) > 0, f"{name} must be > 0, got {getattr(self, name)}")
        need(0.0 < self.gamma <= 1.0, f"gamma must lie in (0, 1], got {self.gamma}")
        need(self.delta >= 0 and self.phi >= 0 and self.delta + self.phi > 0, "delta and phi must be >= 0, not both 0")
        need(self.min_agents <= self.max_agents, f"min_agents {self.min_agents} > max_agents {self.max_agents}")
        need(self.expert in ("odrmstar", "shortest_path"), f"expert must be odrmstar or shortest_path, got {self.expert!r}")
        need(self.expert_order in EXPERT_ORDERS, f"expert_order must be one of {EXPERT_ORDERS}, got {self.expert_order!r}")
        need(self.eval_minutes >= 0, f"eval_minutes must be >= 0, got {self.eval_minutes}")
        need(self.max_replay_ratio >= 0, f"max_replay_ratio must be >= 0, got {self.max_replay_ratio}")
        need(math.isfinite(self.actor_action_temperature) and self.actor_action_temperature >= 0,
             f"actor_action_temperature must be a finite number >= 0, got {self.actor_action_temperature}")
        need(self.session_minutes >= 0, f"session_minutes must be >= 0, got {self.session_minutes}")
        need(len(self.eval_sizes) >= 1 and all(int(n) >= 1 for n in self.eval_sizes), f"bad eval_sizes {self.eval_sizes}")
        need(self.fov_size >= 9 and self.fov_size % 2 == 1, f"fov_size must be odd and >= 9, got {self.fov_size}")
        need(self.map_size >= 4, f"map_size must be >= 4, got {self.map_size}")

    def network_config(self) -> NetworkConfig:
        return NetworkConfig(fov_size=self.fov_size, **ABLATIONS.get(self.variant, {}))

    def resolved_run_name(self) -> str:
        """The run name, saying what runs, so the same command finds (and resumes) the same run."""
        if self.run_name:
            return self.run_name
        return f"{self.variant}_m{self.map_size}_a{self.min_agents}-{self.max_agents}_{self.expert}_s{self.seed}"

    def asdict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "TrainConfig":
        return _from_dict(cls, data, "TrainConfig")
