"""The robot's Q-network without torch: an exported model file (.npz) and a numpy forward pass.

An exported file (written by `scripts/export_model`, mapf_policy/export.py) is a numpy .npz holding
- every tensor of the model's state_dict under its own name, float32, in torch's layout;
- `__export__`: a JSON string {"format", "version", "network_config", "meta", "source": {"file", "sha256"},
  "weights_sha256"}: the NetworkConfig that built the network, the model file's metadata, the SHA-256 of the
  model file it came from (what ties it to that file), and the fingerprint of the weights in it
  (`weights_fingerprint`), checked on every load so that a damaged or edited file is refused.
It loads with `np.load(allow_pickle=False)`: nothing is unpickled.

`RuntimeNet` computes QNetwork.forward (mapf_policy/network.py) with numpy in float32; Q-values agree with
torch's to about 1e-6 (tests/unit/test_runtime_net.py checks 1e-4 on observations of generated episodes).
It supports what NetworkConfig describes but the memory: the ablations (attention modules off), the dueling head, and
the second design's inputs beyond the paper (the channels after the paper's six, NetworkConfig.extra_channels, and
the one-hot still input, NetworkConfig.still_bins; `still_onehot`).
Why numpy rather than ONNX Runtime: models/README.md, "Robot runtime without torch".

Layouts. The trunk runs channels-last, (B, H, W, C), so that each 3x3 valid convolution is one matrix
product of gathered patches (B*H'*W', 9*C) with the weights reordered once at load to (kh, kw, C_in) x C_out;
the patches are one fancy-index gather with indices computed at load (numpy's strided views cost more than
the arithmetic at one agent). The spatial attention's small convolution is one matrix made at load.
The self-attention uses s_ij = x_i^T (W_f^T W_g) x_j, one 6x6 matrix instead of two products.
This module imports numpy and the typed config (mapf_policy/config.py) only: never torch, never training code.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from mapf_policy.config import NetworkConfig

EXPORT_FORMAT = "mapf_policy.qnetwork.npz"
EXPORT_VERSION = 1
HEADER_KEY = "__export__"


def file_sha256(path) -> str:
    """Hex SHA-256 of a file's bytes (ties an export to the model file it came from)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def weights_fingerprint(arrays: dict) -> str:
    """Hex SHA-256 over the weights: name, dtype, shape and bytes of each array, in name order."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}\n".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def expected_shapes(cfg: NetworkConfig) -> dict:
    """name -> shape of every tensor QNetwork(cfg).state_dict() holds (mirrors network.py)."""
    shapes, c_in = {}, cfg.fov_channels
    if cfg.self_attention:
        for m in ("f", "g", "h"):
            shapes[f"attention.{m}.weight"] = (c_in, c_in, 1)
    for k, c_out in enumerate(cfg.conv_channels):
        shapes[f"trunk.{2 * k}.weight"] = (c_out, c_in, 3, 3)
        shapes[f"trunk.{2 * k}.bias"] = (c_out,)
        c_in = c_out
    if cfg.channel_attention:
        shapes["channel_attention.fc1.weight"] = (c_in // cfg.cbam_reduction, c_in)
        shapes["channel_attention.fc2.weight"] = (c_in, c_in // cfg.cbam_reduction)
    if cfg.spatial_attention:
        shapes["spatial_attention.conv.weight"] = (1, 2, cfg.spatial_kernel, cfg.spatial_kernel)
    side = cfg.fov_size - 2 * len(cfg.conv_channels)
    hidden_in = (c_in * side * side + cfg.action_features + cfg.position_features
                 + (cfg.still_features if cfg.still_bins else 0))
    for name, (n_out, n_in) in (("action_fc", (cfg.action_features, cfg.n_actions)),
                                ("position_fc", (cfg.position_features, 2))) + (
            (("still_fc", (cfg.still_features, cfg.still_bins)),) if cfg.still_bins else ()) + (
                                ("hidden_fc", (cfg.hidden_features, hidden_in)),
                                ("q_fc", (cfg.n_actions, cfg.hidden_features))) + (
            (("value_fc", (1, cfg.hidden_features)),) if cfg.dueling else ()):
        shapes[f"{name}.weight"] = (n_out, n_in)
        shapes[f"{name}.bias"] = (n_out,)
    return shapes


def check_weights(arrays: dict, cfg: NetworkConfig, source: str) -> None:
    """ValueError listing missing and unexpected tensors and wrong shapes or dtypes against `cfg`."""
    expected = expected_shapes(cfg)
    problems = []
    missing, unexpected = sorted(set(expected) - set(arrays)), sorted(set(arrays) - set(expected))
    if missing:
        problems.append(f"missing tensors {missing}")
    if unexpected:
        problems.append(f"unexpected tensors {unexpected}")
    for k in sorted(set(expected) & set(arrays)):
        if tuple(arrays[k].shape) != expected[k]:
            problems.append(f"{k}: file has shape {tuple(arrays[k].shape)}, the network config needs {expected[k]}")
        elif arrays[k].dtype != np.float32:
            problems.append(f"{k}: dtype {arrays[k].dtype}, expected float32")
    if problems:
        raise ValueError(f"{source}: weights do not fit its network config: " + "; ".join(problems))


def read_export(path) -> tuple[dict, dict]:
    """(header dict, weights {name: float32 array}) of an exported file, fully checked; ValueError naming the
    problem (not an export, other version, bad config, weights that do not fit it or do not match the
    fingerprint), FileNotFoundError when there is no file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"exported model file {path} does not exist (make it with scripts/export_model)")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except Exception as exc:  # zipfile, pickle refusal, truncated data: all mean "not an export"
        raise ValueError(f"{path} is not a readable exported model (.npz from scripts/export_model): {exc}") from exc
    if HEADER_KEY not in arrays:
        raise ValueError(f"{path} is not an exported model: no '{HEADER_KEY}' entry (make one with scripts/export_model)")
    try:
        header = json.loads(str(arrays.pop(HEADER_KEY)))
    except ValueError as exc:
        raise ValueError(f"{path}: its '{HEADER_KEY}' entry is not JSON: {exc}") from exc
    if not isinstance(header, dict) or header.get("format") != EXPORT_FORMAT:
        raise ValueError(f"{path} is not an exported model (format tag is not '{EXPORT_FORMAT}')")
    if header.get("version") != EXPORT_VERSION:
        raise ValueError(f"{path} has export version {header.get('version')!r}; this runtime reads {EXPORT_VERSION}")
    for key in ("network_config", "meta", "source", "weights_sha256"):
        if key not in header:
            raise ValueError(f"{path}: its header lacks '{key}'")
    try:
        cfg = NetworkConfig.from_dict(header["network_config"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: bad network_config: {exc}") from exc
    if cfg.recurrent:
        raise ValueError(f"{path}: a recurrent network (NetworkConfig.recurrent); this runtime is feed-forward")
    check_weights(arrays, cfg, str(path))
    if weights_fingerprint(arrays) != header["weights_sha256"]:
        raise ValueError(f"{path}: the weights do not match the fingerprint written at export: the file is damaged "
                         f"or was edited; export it again with scripts/export_model")
    return header, arrays


def still_onehot(counts, bins: int) -> np.ndarray:
    """(B,) counts -> (B, bins) float32 one-hot; counts of bins - 1 or more share the last bin (NetworkConfig.still_bins:
    a saturating feature by design). ValueError for anything but a 1-D array of integer counts >= 0."""
    c = np.asarray(counts)
    if c.ndim != 1 or not (np.issubdtype(c.dtype, np.integer) or (c.size and np.all(c == np.round(c)))) or (c < 0).any():
        raise ValueError(f"still must be a (B,) array of integer counts >= 0, got {c!r}")
    return np.eye(bins, dtype=np.float32)[np.minimum(c.astype(np.int64), bins - 1)]


def _patch_index(side: int, channels: int) -> np.ndarray:
    """(side'^2, 9 * C) flat indices into a channels-last (side, side, C) image: row (i, j) of the result
    gathers the 3x3 patch at output cell (i, j), ordered (kh, kw, C), side' = side - 2."""
    out = side - 2
    i, j, kh, kw, c = np.meshgrid(np.arange(out), np.arange(out), np.arange(3), np.arange(3), np.arange(channels),
                                  indexing="ij")
    return (((i + kh) * side + (j + kw)) * channels + c).reshape(out * out, 9 * channels)


def _conv_matrix(kernel: np.ndarray, side: int) -> np.ndarray:
    """(2 * side^2, side^2) matrix of the zero-padded ('same') correlation of a (2, side, side) map, flattened
    channel-major, with `kernel` (2, k, k), k odd: torch's Conv2d(2, 1, k, padding=k // 2, bias=False)."""
    k = kernel.shape[-1]
    mat = np.zeros((2, side, side, side, side), dtype=np.float32)  # [c, input row, input col, out row, out col]
    for i in range(side):
        for j in range(side):
            for di in range(k):
                for dj in range(k):
                    r, q = i + di - k // 2, j + dj - k // 2
                    if 0 <= r < side and 0 <= q < side:
                        mat[:, r, q, i, j] = kernel[:, di, dj]
    return mat.reshape(2 * side * side, side * side)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


class RuntimeNet:
    """QNetwork's forward pass in numpy: `RuntimeNet.load(path)(fov, last_action, position) -> (B, 5)` float32."""

    def __init__(self, cfg: NetworkConfig, weights: dict, header: dict | None = None):
        if cfg.recurrent:
            raise ValueError("a recurrent network (NetworkConfig.recurrent); this runtime is feed-forward")
        check_weights(weights, cfg, "weights")
        self.cfg, self.header = cfg, dict(header or {})
        w = {k: np.asarray(v, dtype=np.float32) for k, v in weights.items()}
        self.attention = None
        if cfg.self_attention:
            wf, wg, wh = (w[f"attention.{m}.weight"][:, :, 0] for m in ("f", "g", "h"))
            self.attention = (np.ascontiguousarray(wf.T @ wg), wh)  # M of s_ij = x_i^T M x_j, and W_h
        self.convs, side = [], cfg.fov_size
        for k in range(len(cfg.conv_channels)):
            weight = w[f"trunk.{2 * k}.weight"]  # (C_out, C_in, 3, 3) -> rows (kh, kw, C_in)
            self.convs.append((_patch_index(side, weight.shape[1]),
                               np.ascontiguousarray(weight.transpose(2, 3, 1, 0).reshape(-1, weight.shape[0])),
                               w[f"trunk.{2 * k}.bias"]))
            side -= 2
        self.channel_mlp = ((w["channel_attention.fc1.weight"].T.copy(), w["channel_attention.fc2.weight"].T.copy())
                            if cfg.channel_attention else None)
        # The spatial attention's padded k x k convolution over the (2, s, s) pooled maps, as one matrix.
        self.spatial = _conv_matrix(w["spatial_attention.conv.weight"][0], side) if cfg.spatial_attention else None
        self.fc = {name: (w[f"{name}.weight"].T.copy(), w[f"{name}.bias"])
                   for name in ("action_fc", "position_fc", "still_fc", "hidden_fc", "q_fc", "value_fc")
                   if f"{name}.weight" in w}

    @classmethod
    def load(cls, path) -> "RuntimeNet":
        header, arrays = read_export(path)
        return cls(NetworkConfig.from_dict(header["network_config"]), arrays, header)

    def check_inputs(self, fov: np.ndarray, last_action: np.ndarray, position: np.ndarray,
                     still: np.ndarray | None = None) -> None:
        """ValueError naming the input whose shape does not fit (B, C, l, l) (C = NetworkConfig.fov_channels),
        (B, 5), (B, 2), and (B, still_bins) for a network with the still input (None otherwise)."""
        l, c, a = self.cfg.fov_size, self.cfg.fov_channels, self.cfg.n_actions
        if fov.ndim != 4 or fov.shape[1:] != (c, l, l):
            raise ValueError(f"fov must have shape (B, {c}, {l}, {l}), got {fov.shape}")
        b = fov.shape[0]
        if last_action.shape != (b, a):
            raise ValueError(f"last_action must have shape ({b}, {a}) (one-hot), got {last_action.shape}")
        if position.shape != (b, 2):
            raise ValueError(f"position must have shape ({b}, 2) (row, col), got {position.shape}")
        bins = self.cfg.still_bins
        if bins and (still is None or still.shape != (b, bins)):
            raise ValueError(f"this network takes a still input of shape ({b}, {bins}) (one-hot, still_onehot), got "
                             f"{None if still is None else still.shape}")
        if not bins and still is not None:
            raise ValueError("this network has no still input (NetworkConfig.still_bins is 0), but one was given")

    def __call__(self, fov, last_action, position, still=None) -> np.ndarray:
        fov = np.asarray(fov, dtype=np.float32)
        last_action = np.asarray(last_action, dtype=np.float32)
        position = np.asarray(position, dtype=np.float32)
        still = None if still is None else np.asarray(still, dtype=np.float32)
        self.check_inputs(fov, last_action, position, still)
        b, c, hgt, wid = fov.shape
        flat = fov.reshape(b, c, hgt * wid)  # (B, C, N)
        if self.attention is not None:  # eqs. (1)-(4): y = x + eta * o
            m, wh = self.attention
            scores_t = np.matmul((m @ flat).transpose(0, 2, 1), flat)  # [b, j, i] = s_ij: softmax over i, last axis
            scores_t -= scores_t.max(axis=2, keepdims=True)
            beta_t = np.exp(scores_t)
            beta_t /= beta_t.sum(axis=2, keepdims=True)
            o = np.matmul(wh @ flat, beta_t.transpose(0, 2, 1))  # o[:, :, j] = sum_i h(x_i) beta_ji
            flat = flat + np.float32(self.cfg.attention_eta) * o
        x = flat.transpose(0, 2, 1).reshape(b, hgt, wid, c)  # channels-last
        for index, weight, bias in self.convs:
            side = x.shape[1] - 2
            patches = x.reshape(b, -1)[:, index].reshape(b * side * side, -1)
            x = np.maximum(patches @ weight + bias, 0.0).reshape(b, side, side, -1)
        return self._head(x, last_action, position, still)

    def _head(self, x: np.ndarray, last_action: np.ndarray, position: np.ndarray,
              still: np.ndarray | None = None) -> np.ndarray:
        """QNetwork.head on the channels-last trunk output (B, s, s, C): CBAM, then the fully connected layers."""
        b = x.shape[0]
        if self.channel_mlp is not None:
            fc1, fc2 = self.channel_mlp
            pooled = np.concatenate([x.mean(axis=(1, 2)), x.max(axis=(1, 2))])  # (2B, C): avg rows, then max rows
            mlp = np.maximum(pooled @ fc1, 0.0) @ fc2
            x = x * _sigmoid(mlp[:b] + mlp[b:])[:, None, None, :]
        if self.spatial is not None:
            pooled = np.concatenate([x.mean(axis=3).reshape(b, -1), x.max(axis=3).reshape(b, -1)], axis=1)
            gate = pooled @ self.spatial  # (B, s*s)
            x = x * _sigmoid(gate).reshape(b, x.shape[1], x.shape[2], 1)
        feats = x.transpose(0, 3, 1, 2).reshape(b, -1)  # torch's flatten order (C, s, s)
        act = np.maximum(last_action @ self.fc["action_fc"][0] + self.fc["action_fc"][1], 0.0)
        pos = position / np.float32(self.cfg.position_scale)
        pos = np.maximum(pos @ self.fc["position_fc"][0] + self.fc["position_fc"][1], 0.0)
        parts = [feats, act, pos]
        if still is not None:  # torch's order: trunk features, last action, position, still input
            parts.append(np.maximum(still @ self.fc["still_fc"][0] + self.fc["still_fc"][1], 0.0))
        z = np.concatenate(parts, axis=1)
        hidden = np.maximum(z @ self.fc["hidden_fc"][0] + self.fc["hidden_fc"][1], 0.0)
        q = hidden @ self.fc["q_fc"][0] + self.fc["q_fc"][1]
        if "value_fc" not in self.fc:
            return q
        value = hidden @ self.fc["value_fc"][0] + self.fc["value_fc"][1]  # dueling: Q = V + A - mean(A)
        return value + q - q.mean(axis=1, keepdims=True)
