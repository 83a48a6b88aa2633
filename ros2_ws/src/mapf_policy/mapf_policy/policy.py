"""Policy: actions for a batch of agents, each from its own observation only.

The Q-values become actions by an ActionRule (action_selection.py): greedy argmax (the paper's,
PAPER_RULE) or, by default, a draw from softmax(Q / T) with obstacle moves excluded and a penalty on
moving back. A Policy owns its random generator and each row's previous cell, so rows are agents and
their order must stay fixed during an episode; `reset` starts a new one. One Policy per robot, or one
per team with one row per agent (the evaluation solver): rows never see each other's state.

Inputs are numpy arrays or tensors: fov (B, C, l, l) with the channels the network reads (the paper's six, then
any beyond-the-paper channels of its NetworkConfig), last_action (B, 5) one-hot, position (B, 2) raw (row, col),
and for a network with a still input (NetworkConfig.still_bins) its (B, still_bins) one-hot. A single agent may also be
passed without the batch dimension. Output: (B,) int64 actions. `act_obs` takes MapfEnv's observation dict; the
environment must then be built with the network's `NetworkConfig.env_channels()` (the evaluation harness does).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from mapf_policy.action_selection import ActionChooser, ActionRule
from mapf_policy.config import NetworkConfig
from mapf_policy.inference import InferenceNet
from mapf_policy.model_io import load_model
from mapf_policy.network import QNetwork, still_input


class Policy:
    """Wraps a QNetwork for inference. `model` is a model file path or a QNetwork; with a QNetwork, `meta` is its
    file's metadata (load_model's third value), which says, for example, the last-action mode it was trained with."""

    def __init__(self, model, num_threads: int | None = 1, device: str = "cpu",
                 rule: ActionRule | None = None, seed: int | None = 0, per_agent_seeds: bool = False,
                 meta: dict | None = None):
        if isinstance(model, QNetwork):
            self.net, self.cfg, self.meta = model, model.cfg, dict(meta or {})
        elif isinstance(model, (str, Path)):
            self.net, self.cfg, self.meta = load_model(model)
        else:
            raise ValueError(f"model must be a model file path or a QNetwork, got {type(model).__name__}")
        if self.cfg.recurrent:
            raise ValueError("Policy acts step by step without memory; a recurrent network (NetworkConfig.recurrent) "
                             "needs the training code's RecurrentActor")
        if num_threads is not None:
            if num_threads < 1:
                raise ValueError(f"num_threads must be >= 1, got {num_threads}")
            # Process-wide in torch; one thread is fastest for the small batches of this network.
            torch.set_num_threads(int(num_threads))
        self.device = torch.device(device)
        self.net = self.net.to(self.device).eval()
        # On CPU, the same function computed faster (inference.py); elsewhere the network itself.
        self.forward = InferenceNet(self.net) if self.device.type == "cpu" else self.net
        # the rule, its generator(s) and each row's previous cell
        self.chooser = ActionChooser(rule, seed, per_agent_seeds)
        self.rule = self.chooser.rule

    @property
    def action_temperature(self) -> float:
        return self.rule.action_temperature

    def reset(self, seed: int | None) -> None:
        """Start an episode: restart the sampling generator (an int seed makes runs repeatable; None draws
        one) and forget every row's previous cell."""
        self.chooser.reset(seed)

    @property
    def network_config(self) -> NetworkConfig:
        return self.cfg

    def _tensor(self, x, name: str, dims: int) -> torch.Tensor:
        t = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x, dtype=torch.float32)
        if t.dim() == dims - 1:  # one agent without a batch dimension
            t = t.unsqueeze(0)
        if t.dim() != dims:
            raise ValueError(f"{name} must have {dims - 1} or {dims} dimensions, got shape {tuple(t.shape)}")
        return t.to(self.device)

    def q_values(self, fov, last_action, position, still=None) -> torch.Tensor:
        """(B, 5) Q-values; shape errors name the offending input. `still`: the (B, still_bins) one-hot still
        input, for a network that reads one (and only then)."""
        f = self._tensor(fov, "fov", 4)
        a = self._tensor(last_action, "last_action", 2)
        p = self._tensor(position, "position", 2)
        if bool(self.cfg.still_bins) != (still is not None):
            raise ValueError(f"this network {'reads' if self.cfg.still_bins else 'has no'} still input "
                             f"(NetworkConfig.still_bins {self.cfg.still_bins}); still was "
                             f"{'not ' if still is None else ''}given")
        s = None if still is None else self._tensor(still, "still", 2)
        with torch.inference_mode():
            # A network without a still input is called with three inputs, as any forward replacing it expects
            # (scripts/bench_inference swaps in other forward passes).
            return self.forward(f, a, p) if s is None else self.forward(f, a, p, s)

    def act(self, fov, last_action, position, still=None) -> np.ndarray:
        """(B,) int64 actions by the rule; greedy ties go to the lowest index (stay). Remembers `position`
        as each row's previous cell for the next call."""
        q = self.q_values(fov, last_action, position, still).cpu().numpy()
        f = fov.cpu().numpy() if isinstance(fov, torch.Tensor) else np.asarray(fov)
        # The rule reads the paper's six channels (obstacles, agents, goal-direction bits); any channels beyond
        # them come after those six (MapfEnv), so the rule sees the first six.
        f = f[..., :self.cfg.in_channels, :, :]
        pos = position.cpu().numpy() if isinstance(position, torch.Tensor) else np.asarray(position)
        return self.chooser.choose(q, f, pos)

    def act_obs(self, obs: dict) -> np.ndarray:
        """Actions for an observation dict of MapfEnv (keys fov, last_action, position, and the still counts for
        a network that reads them)."""
        missing = [k for k in ("fov", "last_action", "position") if k not in obs]
        if missing:
            raise ValueError(f"observation dict lacks {missing}")
        still = still_input(obs, self.cfg) if self.cfg.still_bins else None
        return self.act(obs["fov"], obs["last_action"], obs["position"], still)
