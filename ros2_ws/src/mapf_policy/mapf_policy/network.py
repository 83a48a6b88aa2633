"""QNetwork: the paper's policy network (section III-E, Fig. 2), observation -> 5 Q-values.

fov (B, 6, l, l) -> self-attention (y = x + eta * o) -> four 3x3 stride-1 convs 6-64-128-192-256 (ReLU)
-> CBAM channel attention -> CBAM spatial attention -> flatten;
last_action (B, 5) -> FC; position (B, 2) / position_scale -> FC; concat -> FC -> FC -> Q (B, 5).

How the widths were chosen. The paper fixes the self-attention (f, g, h: 6 -> 6), the four convs and
the layer counts, and reports 1,004,443 parameters in total. The convs without padding take 9x9 to 1x1,
so the trunk gives 256 features and costs 741,376 parameters. The rest is 263,067 parameters and
this one set of widths (found by enumerating plausible choices) matches it exactly:
  f, g, h: 1x1 convs 6 -> 6 without bias               3 x 36 =     108
  channel attention: shared MLP 256 -> 16 -> 256 without bias (CBAM, r = 16)   8,192
  spatial attention: 7x7 conv 2 -> 1 without bias (CBAM)                          98
  last action FC 5 -> 512, position FC 2 -> 64 (with bias)              3,072 + 192
  FC (256 + 512 + 64) -> 300, FC 300 -> 5 (with bias)               249,900 + 1,505
The choice is not unique (the count alone cannot pin it down), but it uses CBAM's own defaults.
With the trunk at 1x1, spatial attention gates the whole 256-vector with one learned scalar map
(only the kernel's centre tap touches the data): we keep it for fidelity and for the Table III ablation.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from mapf_policy.config import STILL_KEYS, NetworkConfig
from mapf_policy.runtime_net import still_onehot as runtime_still_onehot


class SelfAttention(nn.Module):
    """Eqs. (1)-(4): s_ij = f(x_i)^T g(x_j), beta_ji = softmax_i(s_ij), o_j = sum_i beta_ji h(x_i), y = x + eta o.

    x_i is the 6-channel vector of position i of the l*l field of view; f, g, h are 1x1 convolutions.
    """

    def __init__(self, channels: int, eta: float):
        super().__init__()
        self.f = nn.Conv1d(channels, channels, 1, bias=False)
        self.g = nn.Conv1d(channels, channels, 1, bias=False)
        self.h = nn.Conv1d(channels, channels, 1, bias=False)
        self.eta = float(eta)  # fixed to 1 in the paper, so a constant rather than a parameter

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, hgt, wid = x.shape
        flat = x.reshape(b, c, hgt * wid)  # (B, C, N)
        s = torch.bmm(self.f(flat).transpose(1, 2), self.g(flat))  # s[b, i, j] = f(x_i) . g(x_j)
        beta = torch.softmax(s, dim=1)  # normalised over i for each j (eq. 2)
        o = torch.bmm(self.h(flat), beta)  # o[b, :, j] = sum_i h(x_i) beta[b, i, j]
        return x + self.eta * o.reshape(b, c, hgt, wid)


class ChannelAttention(nn.Module):
    """CBAM channel attention: x * sigmoid(MLP(avgpool x) + MLP(maxpool x)), the MLP shared (two FC layers)."""

    def __init__(self, channels: int, reduction: int):
        super().__init__()
        self.fc1 = nn.Linear(channels, channels // reduction, bias=False)
        self.fc2 = nn.Linear(channels // reduction, channels, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        avg = x.mean(dim=(2, 3))
        mx = x.amax(dim=(2, 3))
        gate = torch.sigmoid(self.fc2(F.relu(self.fc1(avg))) + self.fc2(F.relu(self.fc1(mx))))
        return x * gate[:, :, None, None]


class SpatialAttention(nn.Module):
    """CBAM spatial attention: x * sigmoid(conv([mean over channels, max over channels]))."""

    def __init__(self, kernel: int):
        super().__init__()
        self.conv = nn.Conv2d(2, 1, kernel, padding=kernel // 2, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pooled = torch.cat([x.mean(dim=1, keepdim=True), x.amax(dim=1, keepdim=True)], dim=1)
        return x * torch.sigmoid(self.conv(pooled))


class QNetwork(nn.Module):
    """Maps one agent's observation (fov, last_action, position) to Q(s, .) for the 5 actions."""

    def __init__(self, cfg: NetworkConfig | None = None):
        super().__init__()
        cfg = cfg or NetworkConfig()
        cfg.validate()
        self.cfg = cfg
        self.attention = SelfAttention(cfg.fov_channels, cfg.attention_eta) if cfg.self_attention else None
        layers, c_in = [], cfg.fov_channels
        for c_out in cfg.conv_channels:
            layers += [nn.Conv2d(c_in, c_out, 3, stride=1, padding=0), nn.ReLU(inplace=True)]
            c_in = c_out
        self.trunk = nn.Sequential(*layers)
        self.channel_attention = ChannelAttention(c_in, cfg.cbam_reduction) if cfg.channel_attention else None
        self.spatial_attention = SpatialAttention(cfg.spatial_kernel) if cfg.spatial_attention else None
        side = cfg.fov_size - 2 * len(cfg.conv_channels)
        self.action_fc = nn.Linear(cfg.n_actions, cfg.action_features)
        self.position_fc = nn.Linear(2, cfg.position_features)
        # The still input (cfg.still_bins > 0, beyond the paper; NetworkConfig.still_bins says why).
        self.still_fc = nn.Linear(cfg.still_bins, cfg.still_features) if cfg.still_bins else None
        extra = cfg.still_features if cfg.still_bins else 0
        self.hidden_fc = nn.Linear(c_in * side * side + cfg.action_features + cfg.position_features + extra,
                                   cfg.hidden_features)
        # The memory (cfg.recurrent, beyond the paper): h_t = GRU(embedding_t, h_{t-1}), Q_t from h_t.
        self.gru = nn.GRUCell(cfg.hidden_features, cfg.hidden_features) if cfg.recurrent else None
        self.q_fc = nn.Linear(cfg.hidden_features, cfg.n_actions)
        # Dueling split (cfg.dueling): q_fc gives the advantages A, value_fc the state value V.
        self.value_fc = nn.Linear(cfg.hidden_features, 1) if cfg.dueling else None

    def check_inputs(self, fov: torch.Tensor, last_action: torch.Tensor, position: torch.Tensor,
                     still: torch.Tensor | None = None) -> None:
        """ValueError naming the input whose shape does not fit (B, 6, l, l), (B, 5), (B, 2), and (B, still_bins)
        for a network with the still input (None otherwise)."""
        l, c, a = self.cfg.fov_size, self.cfg.fov_channels, self.cfg.n_actions
        if fov.dim() != 4 or tuple(fov.shape[1:]) != (c, l, l):
            raise ValueError(f"fov must have shape (B, {c}, {l}, {l}), got {tuple(fov.shape)}")
        b = fov.shape[0]
        if tuple(last_action.shape) != (b, a):
            raise ValueError(f"last_action must have shape ({b}, {a}) (one-hot), got {tuple(last_action.shape)}")
        if tuple(position.shape) != (b, 2):
            raise ValueError(f"position must have shape ({b}, 2) (row, col), got {tuple(position.shape)}")
        bins = self.cfg.still_bins
        if bins and (still is None or tuple(still.shape) != (b, bins)):
            raise ValueError(f"this network takes a still input of shape ({b}, {bins}) (one-hot, still_onehot), got "
                             f"{None if still is None else tuple(still.shape)}")
        if not bins and still is not None:
            raise ValueError("this network has no still input (NetworkConfig.still_bins is 0), but one was given")

    def forward(self, fov: torch.Tensor, last_action: torch.Tensor, position: torch.Tensor,
                still: torch.Tensor | None = None) -> torch.Tensor:
        return self.q_values(self._feed_forward(self.embed(fov, last_action, position, still)))

    def embed(self, fov: torch.Tensor, last_action: torch.Tensor, position: torch.Tensor,
              still: torch.Tensor | None = None) -> torch.Tensor:
        """The (B, hidden_features) features of one step's observation: everything before the output (and the memory)."""
        self.check_inputs(fov, last_action, position, still)
        x = self.attention(fov) if self.attention is not None else fov
        return self.embed_head(self.trunk(x), last_action, position, still)

    def step(self, fov: torch.Tensor, last_action: torch.Tensor, position: torch.Tensor, still: torch.Tensor | None = None,
             h: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """A recurrent network's Q-values of one step and each agent's new memory: (q (B, 5), h (B, hidden_features)).
        `h` is the memory before the step (None: zeros, an episode's start)."""
        return self.remember(self.embed(fov, last_action, position, still), h)

    def remember(self, embedding: torch.Tensor, h: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(q, new memory) from one step's embedding and the memory before it (None: zeros)."""
        if self.gru is None:
            raise ValueError("this network has no memory (NetworkConfig.recurrent is False); call it directly")
        if h is None:
            h = embedding.new_zeros(embedding.shape[0], self.cfg.hidden_features)
        if tuple(h.shape) != (embedding.shape[0], self.cfg.hidden_features):
            raise ValueError(f"memory h must have shape ({embedding.shape[0]}, {self.cfg.hidden_features}), got "
                             f"{tuple(h.shape)}")
        h = self.gru(embedding, h)
        return self.q_values(h), h

    def _feed_forward(self, embedding: torch.Tensor) -> torch.Tensor:
        if self.gru is not None:
            raise ValueError("this network is recurrent (NetworkConfig.recurrent): its Q-values need each agent's "
                             "memory; use QNetwork.step (or RecurrentActor in training)")
        return embedding

    def q_values(self, hidden: torch.Tensor) -> torch.Tensor:
        """The output layer(s): Q (B, 5) from the (B, hidden_features) features (or memory)."""
        if self.value_fc is None:
            return self.q_fc(hidden)
        value, adv = self.value_fc(hidden), self.q_fc(hidden)
        return value + adv - adv.mean(dim=1, keepdim=True)

    def head(self, x: torch.Tensor, last_action: torch.Tensor, position: torch.Tensor,
             still: torch.Tensor | None = None) -> torch.Tensor:
        """Q-values from the trunk's output x (B, C, s, s): CBAM, then the fully connected layers.

        Shared with the inference path (inference.py), which computes the trunk differently."""
        return self.q_values(self._feed_forward(self.embed_head(x, last_action, position, still)))

    def embed_head(self, x: torch.Tensor, last_action: torch.Tensor, position: torch.Tensor,
                   still: torch.Tensor | None = None) -> torch.Tensor:
        """The (B, hidden_features) features from the trunk's output x (B, C, s, s): CBAM, then the first FC layer."""
        if self.channel_attention is not None:
            x = self.channel_attention(x)
        if self.spatial_attention is not None:
            x = self.spatial_attention(x)
        act = F.relu(self.action_fc(last_action))
        pos = F.relu(self.position_fc(position / self.cfg.position_scale))
        parts = [x.flatten(1), act, pos]
        if self.still_fc is not None:
            parts.append(F.relu(self.still_fc(still)))
        z = torch.cat(parts, dim=1)
        return F.relu(self.hidden_fc(z))


def count_parameters(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


def still_onehot(still, bins: int) -> torch.Tensor:
    """(B,) counts of steps on the same cell -> (B, bins) one-hot; counts of bins - 1 or more share the last bin
    (a saturating feature by design: beyond it, how long the agent has waited makes no difference). The robot
    runtime's numpy function (runtime_net.still_onehot) as a tensor."""
    return torch.from_numpy(runtime_still_onehot(still, bins))


def network_inputs(obs: dict, cfg: NetworkConfig) -> tuple:
    """The network's inputs as float tensors from an observation dict of MapfEnv: (fov, last_action, position),
    and the one-hot still input when the network takes it."""
    inputs = tuple(torch.from_numpy(np.asarray(obs[k], dtype=np.float32)) for k in ("fov", "last_action", "position"))
    if cfg.still_bins:
        inputs += (still_input(obs, cfg),)
    return inputs


def still_input(obs: dict, cfg: NetworkConfig) -> torch.Tensor:
    """The one-hot still input (B, still_bins) from an observation dict of MapfEnv, for a network that takes one."""
    key = STILL_KEYS[cfg.still_count]
    if key not in obs:
        raise ValueError(f"this network takes a still input, but the observation has no {key!r} counts")
    return still_onehot(obs[key], cfg.still_bins)
