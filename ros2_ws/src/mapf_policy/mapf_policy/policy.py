"""Policy: actions for a batch of agents, each from its own observation only.

Greedy argmax_a Q(s, a) (the paper) with `action_temperature` 0, or a draw from softmax(Q / T) with
T > 0 (see action_selection.py for why). A Policy owns its random generator: one Policy per robot.

Inputs are numpy arrays or tensors: fov (B, 6, l, l), last_action (B, 5) one-hot, position (B, 2) raw
(row, col). A single agent may also be passed without the batch dimension. Output: (B,) int64 actions.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from mapf_policy.action_selection import DEFAULT_ACTION_TEMPERATURE, check_action_temperature, select_actions, settled
from mapf_policy.config import NetworkConfig
from mapf_policy.model_io import load_model
from mapf_policy.network import QNetwork


class Policy:
    """Wraps a QNetwork for inference. `model` is a model file path or a QNetwork."""

    def __init__(self, model, num_threads: int | None = 1, device: str = "cpu",
                 action_temperature: float = DEFAULT_ACTION_TEMPERATURE, seed: int | None = 0,
                 settled_greedy: bool = True):
        if isinstance(model, QNetwork):
            self.net, self.cfg, self.meta = model, model.cfg, {}
        elif isinstance(model, (str, Path)):
            self.net, self.cfg, self.meta = load_model(model)
        else:
            raise ValueError(f"model must be a model file path or a QNetwork, got {type(model).__name__}")
        if num_threads is not None:
            if num_threads < 1:
                raise ValueError(f"num_threads must be >= 1, got {num_threads}")
            # Process-wide in torch; one thread is fastest for the small batches of this network.
            torch.set_num_threads(int(num_threads))
        self.device = torch.device(device)
        # channels_last makes the CPU convolutions about 25% faster on this network (measured,
        # scripts/bench_inference); results are identical up to float rounding.
        self.net = self.net.to(self.device, memory_format=torch.channels_last).eval()
        self.action_temperature = check_action_temperature(action_temperature)
        # False samples every agent, settled ones too: only for the ablation in scripts/compare_models.
        self.settled_greedy = bool(settled_greedy)
        self.reseed(seed)

    def reseed(self, seed: int | None) -> None:
        """Restart the action-sampling generator (an int seed makes runs repeatable; None draws one)."""
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
            raise ValueError(f"seed must be an integer >= 0 or None, got {seed!r}")
        self.rng = np.random.default_rng(seed)

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

    def q_values(self, fov, last_action, position) -> torch.Tensor:
        """(B, 5) Q-values; shape errors name the offending input."""
        f = self._tensor(fov, "fov", 4).contiguous(memory_format=torch.channels_last)
        a = self._tensor(last_action, "last_action", 2)
        p = self._tensor(position, "position", 2)
        with torch.inference_mode():
            return self.net(f, a, p)

    def act(self, fov, last_action, position) -> np.ndarray:
        """(B,) int64 actions: greedy (ties go to the lowest index, i.e. stay) or sampled, per action_temperature."""
        q = self.q_values(fov, last_action, position).cpu().numpy()
        rows = None
        if self.action_temperature > 0 and self.settled_greedy:  # greedy needs no settled mask
            f = fov.cpu().numpy() if isinstance(fov, torch.Tensor) else np.asarray(fov)
            rows = settled(f.reshape(q.shape[0], *f.shape[-3:]))
        return select_actions(q, self.action_temperature, self.rng, greedy_rows=rows)

    def act_obs(self, obs: dict) -> np.ndarray:
        """Actions for an observation dict of MapfEnv (keys fov, last_action, position)."""
        missing = [k for k in ("fov", "last_action", "position") if k not in obs]
        if missing:
            raise ValueError(f"observation dict lacks {missing}")
        return self.act(obs["fov"], obs["last_action"], obs["position"])
