"""RuntimePolicy: the robot's policy without torch, an exported model (runtime_net.py) and an ActionRule.

The same actions as Policy (policy.py) for the same model, rule and seed: the Q-values come from the numpy
forward pass of the exported file instead of torch, and the rule is the same ActionChooser. Imports numpy,
the typed config and the action rule only (no torch, no training code): what a robot installs
(docs/FLEET.md, "What a robot installs").
"""
from __future__ import annotations

import numpy as np

from mapf_policy.action_selection import ActionChooser, ActionRule
from mapf_policy.runtime_net import RuntimeNet


class RuntimePolicy:
    """`RuntimePolicy(path_to_export, rule, seed).act(fov, last_action, position) -> (B,) int64 actions`."""

    def __init__(self, model, rule: ActionRule | None = None, seed: int | None = 0):
        self.net = model if isinstance(model, RuntimeNet) else RuntimeNet.load(model)
        self.cfg = self.net.cfg
        self.chooser = ActionChooser(rule, seed)
        self.rule = self.chooser.rule

    @property
    def header(self) -> dict:
        """The exported file's header: network_config, meta, source (file, sha256), weights_sha256."""
        return self.net.header

    def reset(self, seed: int | None) -> None:
        self.chooser.reset(seed)

    def q_values(self, fov, last_action, position) -> np.ndarray:
        """(B, 5) float32 Q-values; a single agent may be passed without the batch dimension."""
        fov, last_action, position = (np.asarray(x, dtype=np.float32) for x in (fov, last_action, position))
        if fov.ndim == 3:
            fov, last_action, position = fov[None], last_action.reshape(1, -1), position.reshape(1, -1)
        return self.net(fov, last_action, position)

    def act(self, fov, last_action, position) -> np.ndarray:
        """(B,) int64 actions by the rule (see ActionChooser.choose)."""
        q = self.q_values(fov, last_action, position)
        return self.chooser.choose(q, np.asarray(fov).reshape(q.shape[0], *np.shape(fov)[-3:]),
                                   np.asarray(position).reshape(q.shape[0], 2))
