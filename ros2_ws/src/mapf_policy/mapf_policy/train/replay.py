"""Transitions in compact numpy form, an episode recorder and a ring replay buffer.

One transition (s, a, r, s', terminated, a*) of one agent, stored as
  fov uint8 (6, l, l)      (all observation channels are 0/1, checked on recording)
  last_action int8         (index of the one-hot; s' has last_action = action)
  position int16 (2,)      raw (row, col)
  action int8, reward float32, terminated bool
  next_fov uint8 (6, l, l), next_position int16 (2,)
  expert int8              expert action a*, or -1 when the state has no expert label
About 1 kB per transition with l = 9. `to_tensors` rebuilds the network inputs.
"""
from __future__ import annotations

import numpy as np
import torch


def field_specs(fov_size: int) -> dict:
    l = fov_size
    return {
        "fov": (np.uint8, (6, l, l)),
        "last_action": (np.int8, ()),
        "position": (np.int16, (2,)),
        "action": (np.int8, ()),
        "reward": (np.float32, ()),
        "terminated": (np.bool_, ()),
        "next_fov": (np.uint8, (6, l, l)),
        "next_position": (np.int16, (2,)),
        "expert": (np.int8, ()),
    }


def _compact_fov(fov: np.ndarray) -> np.ndarray:
    small = fov.astype(np.uint8)
    if not np.array_equal(small, fov):
        raise ValueError("fov values must be 0/1 to be stored compactly (got other values)")
    return small


class EpisodeRecorder:
    """Collects the transitions of all agents of one episode, step by step."""

    def __init__(self):
        self._steps: list[dict] = []

    def add(self, obs: dict, actions, rewards, next_obs: dict, terminated: bool, expert=None) -> None:
        n = len(actions)
        self._steps.append({
            "fov": _compact_fov(obs["fov"]),
            "last_action": obs["last_action"].argmax(axis=1).astype(np.int8),
            "position": obs["position"].astype(np.int16),
            "action": np.asarray(actions, dtype=np.int8),
            "reward": np.asarray(rewards, dtype=np.float32),
            "terminated": np.full(n, bool(terminated)),
            "next_fov": _compact_fov(next_obs["fov"]),
            "next_position": next_obs["position"].astype(np.int16),
            "expert": np.full(n, -1, dtype=np.int8) if expert is None else np.asarray(expert, dtype=np.int8),
        })

    def __len__(self) -> int:
        return sum(len(s["action"]) for s in self._steps)

    def arrays(self) -> dict:
        if not self._steps:
            raise ValueError("the episode recorded no steps")
        return {k: np.concatenate([s[k] for s in self._steps]) for k in self._steps[0]}


def concat(chunks: list[dict]) -> dict:
    return {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}


class ReplayBuffer:
    """Fixed-capacity ring of transitions; the oldest are overwritten when full."""

    def __init__(self, capacity: int, fov_size: int):
        if capacity < 1:
            raise ValueError(f"replay capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self.specs = field_specs(fov_size)
        self.data = {k: np.zeros((self.capacity,) + shape, dtype=dt) for k, (dt, shape) in self.specs.items()}
        self.size = 0
        self.cursor = 0
        self.added = 0  # transitions ever added (checkpoint metadata; the replay ratio counts Learner.online_received)

    def __len__(self) -> int:
        return self.size

    def add(self, chunk: dict) -> None:
        missing = set(self.specs) - set(chunk)
        if missing:
            raise ValueError(f"transition chunk lacks fields {sorted(missing)}")
        n = len(chunk["action"])
        for k, (_, shape) in self.specs.items():
            if chunk[k].shape != (n,) + shape:
                raise ValueError(f"transition field {k} has shape {chunk[k].shape}, expected {(n,) + shape}")
        self.added += n
        if n > self.capacity:  # keep only the newest
            chunk = {k: v[-self.capacity:] for k, v in chunk.items()}
            n = self.capacity
        idx = (self.cursor + np.arange(n)) % self.capacity
        for k in self.specs:
            self.data[k][idx] = chunk[k]
        self.cursor = int((self.cursor + n) % self.capacity)
        self.size = min(self.capacity, self.size + n)

    def sample(self, n: int, rng: np.random.Generator) -> dict:
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        idx = rng.integers(0, self.size, n)
        return {k: v[idx] for k, v in self.data.items()}


def to_tensors(batch: dict, device: torch.device) -> dict:
    """Network inputs for s and s' plus targets, as float / long / bool tensors on `device`."""
    eye = torch.eye(5)
    t = {
        "fov": torch.from_numpy(batch["fov"]).float(),
        "last_action": eye[torch.from_numpy(batch["last_action"].astype(np.int64))],
        "position": torch.from_numpy(batch["position"]).float(),
        "action": torch.from_numpy(batch["action"].astype(np.int64)),
        "reward": torch.from_numpy(batch["reward"]),
        "terminated": torch.from_numpy(batch["terminated"]),
        "next_fov": torch.from_numpy(batch["next_fov"]).float(),
        "next_last_action": eye[torch.from_numpy(batch["action"].astype(np.int64))],
        "next_position": torch.from_numpy(batch["next_position"]).float(),
        "expert": torch.from_numpy(batch["expert"].astype(np.int64)),
    }
    t = {k: v.to(device) for k, v in t.items()}
    for k in ("fov", "next_fov"):
        t[k] = t[k].contiguous(memory_format=torch.channels_last)
    return t
