"""Fast CPU forward passes of QNetwork: the same function, only float rounding differs (Q-values within
1e-5 of QNetwork.forward, gradients within a relative 1e-5; tests/unit/test_inference.py).

- `FastForward(net)(fov, last_action, position)`: differentiable; the learner's online network trains
  through it on CPU.
- `InferenceNet(net)(...)`: the same without autograd, with the derived weights cached; `Policy`, the
  training actors and the learner's target network use it.

Why. Batched over many agents, QNetwork.forward spends about 80 % of its time in oneDNN convolutions whose
images (9x9 down to 1x1) are too small for them to run near the CPU's peak, and the convolutions' arithmetic
alone, done directly, would take about 6.5 ms for 64 agents on this machine's core (throwaway profiles and
timings, sixth and seventh sessions). Here:
- The trunk runs channels-last, (B, H, W, C) contiguous, so each layer's output is the next one's input.
- From 8 agents in a batch up, a layer whose input is 7x7 or 5x5 (the second and third with the paper's
  9x9 field of view) is a single-tile Winograd convolution F(m x m, 3 x 3), m = 5 or 3 (winograd.py): the
  whole input is one tile, so no tiling is needed, and it takes n^2 products per channel pair (n = m + 2)
  instead of 9 m^2: 49 instead of 225, and 25 instead of 81. The transforms are small matrix products.
- Any other layer, and every layer of a smaller batch, is im2col and one matrix product: a strided view
  gathers the 3x3 patches, copied into a (B*H'*W', 9*C) matrix times the weights reshaped to (9*C, C_out).
  The last convolution (3x3 in, 1x1 out) is then a plain fully connected layer.
- Self-attention (eqs. 1-4) uses s_ij = f(x_i).g(x_j) = x_i^T (W_f^T W_g) x_j: one 6x6 product instead of
  two. It computes the scores transposed, so that the softmax over i runs along the last, contiguous axis.
- CBAM and the fully connected layers are QNetwork.head itself.
Measured figures: models/README.md, "Inference speed" (scripts/bench_inference --forward fast reference,
scripts/bench_learner).

Winograd's transforms cost some precision: against a float64 reference, the second and third layers of
git f80edd2:models/hscl.pt are off by about 1.5e-5 and 3e-6 (activations of order 2), against 6e-7 and 3e-7 for the
direct product. The points below gave the smallest of those errors among those tried.

Memory. Each call allocates and frees intermediates of about 1-2 MB (the attention's 81x81 scores per
agent, the Winograd products). With glibc's default settings, the freed top of the heap is often handed
back to the system and faulted in again at the next call: at 64 agents one process took 7 ms per call and
the next 10 ms, the same code. `keep_freed_memory` (called once by FastForward) raises glibc's trim and
mmap thresholds for the process, so the heap keeps what it has; the price is a few tens of MB held.

InferenceNet rebuilds its cached weights whenever a parameter of the wrapped QNetwork has changed since
they were made (torch's per-tensor version counter, bumped by load_state_dict and optimizer steps), so an
actor that loads new weights into its QNetwork never runs stale ones.
"""
from __future__ import annotations

import ctypes
import functools
from fractions import Fraction

import numpy as np
import torch

from mapf_policy.network import QNetwork
from mapf_policy.winograd import toom_cook

# Output side m -> the finite interpolation points of F(m, 3); other sides use im2col.
WINOGRAD_POINTS = {5: (0, 1, -1, 2, -2, Fraction(1, 2)), 3: (0, 1, -1, Fraction(1, 2))}
# Smaller batches use im2col everywhere: the transforms' fixed cost does not pay off there
# (models/README.md, "Inference speed": scripts/bench_inference --forward winograd im2col --batches 4 8 16).
WINOGRAD_MIN_BATCH = 8


# glibc mallopt parameters (malloc.h) and the values set: keep up to 256 MB of freed heap top, and serve
# blocks up to 32 MB (glibc's largest mmap threshold on 64-bit) from the heap.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_TRIM_BYTES, _MMAP_BYTES = 256 << 20, 32 << 20


@functools.lru_cache(maxsize=None)
def keep_freed_memory() -> bool:
    """Make glibc's malloc keep freed memory for reuse (see "Memory" above); once per process.

    True if the settings took; False elsewhere (another C library or system), where nothing changes."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_BYTES)) and bool(libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_BYTES))
    except (OSError, AttributeError):
        return False


@functools.lru_cache(maxsize=None)
def _transforms(m: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The 2-D F(m x m, 3 x 3) transforms on a flattened (row, column) axis: kron(B^T, B^T) (n^2, n^2) for
    the input and kron(A^T, A^T) (m^2, n^2) for the output in float32, kron(G, G) (n^2, 9) for the weights
    in float64 (the weights are transformed in float64 and rounded once)."""
    at, g, bt = toom_cook(m, 3, WINOGRAD_POINTS[m])
    with torch.inference_mode(False):  # cached: made inside inference mode, autograd could not use them
        return (torch.from_numpy(np.kron(bt, bt)).float(), torch.from_numpy(np.kron(at, at)).float(),
                torch.from_numpy(np.kron(g, g)))


class _Layer:
    """One 3x3 stride-1 valid convolution + ReLU, channels-last, with weights derived from a Conv2d."""

    def __init__(self, conv: torch.nn.Conv2d, m: int):
        self.m, self.bias = m, conv.bias
        # Rows ordered (kh, kw, C_in), the layout of the patches gathered by im2col.
        self.im2col_weight = conv.weight.permute(2, 3, 1, 0).reshape(-1, conv.out_channels)
        self.transforms = None
        if m in WINOGRAD_POINTS:
            self.transforms = tuple(t.to(conv.weight.device) for t in _transforms(m))
            n = m + 2
            # G w G^T for every channel pair: (n^2, C_in, C_out).
            u = self.transforms[2] @ self.im2col_weight.reshape(9, -1).double()
            self.winograd_weight = u.float().view(n * n, conv.in_channels, conv.out_channels)

    def __call__(self, x: torch.Tensor, winograd: bool) -> torch.Tensor:
        if winograd and self.transforms is not None:
            return self._winograd(x)
        b, hgt, wid, c = x.shape
        x = x.contiguous()
        sb, sh, sw, sc = x.stride()
        patches = x.as_strided((b, hgt - 2, wid - 2, 3, 3, c), (sb, sh, sw, sh, sw, sc))
        out = torch.addmm(self.bias, patches.reshape(-1, 9 * c), self.im2col_weight)
        return torch.relu(out).view(b, hgt - 2, wid - 2, -1)

    def _winograd(self, x: torch.Tensor) -> torch.Tensor:
        b, _, _, c = x.shape
        m, n = self.m, self.m + 2
        to_tile, from_tile, _ = self.transforms
        cols = x.reshape(b, n * n, c).transpose(0, 1).reshape(n * n, b * c)
        v = (to_tile @ cols).view(n * n, b, c)
        prod = torch.bmm(v, self.winograd_weight)  # (n^2, B, C_out): one product per point of the tile
        c_out = prod.shape[2]
        y = (from_tile @ prod.view(n * n, b * c_out)).view(m, m, b, c_out).permute(2, 0, 1, 3)
        return torch.relu(y + self.bias)


class FastForward:
    """Q-values of a QNetwork, computed faster on CPU; differentiable: `FastForward(net)(fov, last, position)`."""

    def __init__(self, net: QNetwork, winograd_min_batch: int | None = WINOGRAD_MIN_BATCH):
        """`winograd_min_batch`: batches from this size up use the Winograd layers; None: im2col only."""
        if not isinstance(net, QNetwork):
            raise ValueError(f"{type(self).__name__} wraps a QNetwork, got {type(net).__name__}")
        if winograd_min_batch is not None and (isinstance(winograd_min_batch, bool)
                                               or not isinstance(winograd_min_batch, int) or winograd_min_batch < 1):
            raise ValueError(f"winograd_min_batch must be an integer >= 1 or None, got {winograd_min_batch!r}")
        self.net, self.winograd_min_batch = net, winograd_min_batch
        keep_freed_memory()

    @property
    def cfg(self):
        return self.net.cfg

    def derived_weights(self) -> tuple:
        """(attention matrices or None, layers), as functions of the network's parameters."""
        at, attention = self.net.attention, None
        if at is not None:
            wf, wg, wh = (m.weight[:, :, 0] for m in (at.f, at.g, at.h))
            attention = (wf.t() @ wg, wh)  # M in s_ij = x_i^T M x_j, and W_h
        side, layers = self.cfg.fov_size, []
        for conv in (c for c in self.net.trunk if isinstance(c, torch.nn.Conv2d)):
            side -= 2
            layers.append(_Layer(conv, side))
        return attention, layers

    def _attention(self, fov: torch.Tensor, scores: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        """Eqs. (1)-(4) on (B, C, l, l); returns y = x + eta * o channels-last, (B, l, l, C)."""
        b, c, hgt, wid = fov.shape
        flat = fov.reshape(b, c, hgt * wid)  # (B, C, N)
        # scores_t[b, j, i] = (M x_j) . x_i = s_ij; the softmax over i (eq. 2) is over the last axis.
        scores_t = torch.bmm(torch.matmul(scores, flat).transpose(1, 2), flat)
        beta_t = torch.softmax(scores_t, dim=2)
        o = torch.bmm(torch.matmul(values, flat), beta_t.transpose(1, 2))  # o[:, j] = sum_i beta_ji h(x_i)
        return (flat + self.net.attention.eta * o).transpose(1, 2).reshape(b, hgt, wid, c)

    def _q(self, weights: tuple, fov: torch.Tensor, last_action: torch.Tensor, position: torch.Tensor,
           still: torch.Tensor | None = None) -> torch.Tensor:
        return self.net.q_values(self.net._feed_forward(self._embed(weights, fov, last_action, position, still)))

    def _embed(self, weights: tuple, fov: torch.Tensor, last_action: torch.Tensor, position: torch.Tensor,
               still: torch.Tensor | None = None) -> torch.Tensor:
        self.net.check_inputs(fov, last_action, position, still)
        attention, layers = weights
        x = self._attention(fov, *attention) if attention is not None else fov.permute(0, 2, 3, 1)
        winograd = self.winograd_min_batch is not None and fov.shape[0] >= self.winograd_min_batch
        for layer in layers:
            x = layer(x, winograd)
        return self.net.embed_head(x.permute(0, 3, 1, 2), last_action, position, still)  # NCHW view for CBAM

    def __call__(self, fov: torch.Tensor, last_action: torch.Tensor, position: torch.Tensor,
                 still: torch.Tensor | None = None) -> torch.Tensor:
        """(B, 5) Q-values; the inputs' shapes are checked as by QNetwork.forward."""
        return self._q(self.derived_weights(), fov, last_action, position, still)

    def embed(self, fov: torch.Tensor, last_action: torch.Tensor, position: torch.Tensor,
              still: torch.Tensor | None = None) -> torch.Tensor:
        """QNetwork.embed, faster: the (B, hidden_features) features before the output (and the memory)."""
        return self._embed(self.derived_weights(), fov, last_action, position, still)


class InferenceNet(FastForward):
    """FastForward without autograd, its derived weights cached until the network's parameters change."""

    def __init__(self, net: QNetwork, winograd_min_batch: int | None = WINOGRAD_MIN_BATCH):
        super().__init__(net, winograd_min_batch)
        self._versions, self._weights = None, None

    def __call__(self, fov: torch.Tensor, last_action: torch.Tensor, position: torch.Tensor,
                 still: torch.Tensor | None = None) -> torch.Tensor:
        with torch.inference_mode():
            return self._q(self._cached(), fov, last_action, position, still)

    def embed(self, fov: torch.Tensor, last_action: torch.Tensor, position: torch.Tensor,
              still: torch.Tensor | None = None) -> torch.Tensor:
        with torch.inference_mode():
            return self._embed(self._cached(), fov, last_action, position, still)

    def _cached(self) -> tuple:
        versions = tuple((id(p), p._version) for p in self.net.parameters())
        if versions != self._versions:
            self._weights, self._versions = self.derived_weights(), versions
        return self._weights
