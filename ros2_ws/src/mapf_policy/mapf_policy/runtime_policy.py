"""RuntimePolicy: the robot's policy without torch, an exported model (runtime_net.py) and an ActionRule.

The same actions as Policy (policy.py) for the same model, rule and seed: the Q-values come from the numpy
forward pass of the exported file instead of torch, and the rule is the same ActionChooser. Imports numpy,
the typed config and the action rule only (no torch, no training code): what a robot installs
(docs/FLEET.md, "What a robot installs").
"""
from __future__ import annotations

import numpy as np

from mapf_policy.action_selection import ActionChooser, ActionRule
from mapf_policy.runtime_net import RuntimeNet, still_onehot


class RuntimePolicy:
    """`RuntimePolicy(path_to_export, rule, seed).act(fov, last_action, position[, still]) -> (B,) int64 actions`."""

    def __init__(self, model, rule: ActionRule | None = None, seed: int | None = 0):
        self.net = model if isinstance(model, RuntimeNet) else RuntimeNet.load(model)
        self.cfg = self.net.cfg
        self.chooser = ActionChooser(rule, seed)
        self.rule = self.chooser.rule

    @property
    def header(self) -> dict:
        """The exported file's header: network_config, meta, source (file, sha256), weights_sha256."""
        return self.net.header

    @property
    def last_action_mode(self) -> str:
        """The observation's last action the model was trained with (its metadata; older models: 'requested')."""
        return str(self.header.get("meta", {}).get("last_action", "requested"))

    def check_servable(self) -> None:
        """ValueError unless AgentObservation carries everything this network reads: the still input must count
        revisits (the one count the world node publishes)."""
        if self.cfg.still_bins and self.cfg.still_count != "revisit":
            raise ValueError(f"the network's still input counts {self.cfg.still_count!r} (NetworkConfig.still_count); "
                             "AgentObservation carries the 'revisit' count only")

    def message_inputs(self, msg) -> tuple:
        """(fov, last_action, position, still) of one robot, batch of 1, from an AgentObservation (any object with its
        fields); ValueError naming what does not fit this model: the field of view's size or channels, the
        channels after the paper's six, the last-action mode. `still` is None for a network without the input."""
        cfg, l = self.cfg, self.cfg.fov_size
        want = list(cfg.extra_channels().names)
        if msg.fov_size != l or msg.fov_channels != cfg.fov_channels or list(msg.extra_channels) != want:
            raise ValueError(f"observation has fov_size {msg.fov_size}, {msg.fov_channels} channels, extra channels "
                             f"{list(msg.extra_channels)}; the model reads fov_size {l}, {cfg.fov_channels} channels, "
                             f"extra channels {want} (the world node's parameters fov_size and extra_channels)")
        if len(msg.fov) != cfg.fov_channels * l * l:
            raise ValueError(f"observation fov holds {len(msg.fov)} values, not {cfg.fov_channels} x {l} x {l}")
        if msg.last_action_mode != self.last_action_mode:
            raise ValueError(f"observation's last action is {msg.last_action_mode or 'of an unnamed mode'!r}, the "
                             f"model was trained with {self.last_action_mode!r} (the world node's parameter last_action)")
        fov = np.asarray(msg.fov, dtype=np.float32).reshape(1, cfg.fov_channels, l, l)
        last_action = np.asarray(msg.last_action, dtype=np.float32).reshape(1, 5)
        position = np.asarray(msg.position, dtype=np.float32).reshape(1, 2)
        still = still_onehot(np.array([int(msg.revisits)]), cfg.still_bins) if cfg.still_bins else None
        return fov, last_action, position, still

    def reset(self, seed: int | None) -> None:
        self.chooser.reset(seed)

    def q_values(self, fov, last_action, position, still=None) -> np.ndarray:
        """(B, 5) float32 Q-values; a single agent may be passed without the batch dimension. `still`: the (B,
        still_bins) one-hot still input (runtime_net.still_onehot), for a network that reads one and only then."""
        fov, last_action, position = (np.asarray(x, dtype=np.float32) for x in (fov, last_action, position))
        if fov.ndim == 3:
            fov, last_action, position = fov[None], last_action.reshape(1, -1), position.reshape(1, -1)
            still = None if still is None else np.asarray(still, dtype=np.float32).reshape(1, -1)
        return self.net(fov, last_action, position, still)

    def act(self, fov, last_action, position, still=None) -> np.ndarray:
        """(B,) int64 actions by the rule (see ActionChooser.choose). The rule reads the paper's six channels, which
        come first; any channels beyond them (NetworkConfig.extra_channels) follow."""
        q = self.q_values(fov, last_action, position, still)
        f = np.asarray(fov).reshape(q.shape[0], *np.shape(fov)[-3:])[:, :self.cfg.in_channels]
        return self.chooser.choose(q, f, np.asarray(position).reshape(q.shape[0], 2))
