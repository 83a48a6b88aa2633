"""Toom-Cook (Winograd) matrices for the 1-D correlation y_i = sum_k g_k d_{i+k}: m outputs, r taps.

With n = m + r - 1 evaluation points (n - 1 finite ones and infinity), y = A^T [(G g) * (B^T d)] for every
filter g (r,) and input d (n,), using n multiplications instead of m * r. In 2-D (F(m x m, r x r)),
Y = A^T [(G g G^T) * (B^T d B)] A. A and G follow from Lagrange interpolation at the points; B^T is then
the unique matrix that makes the identity hold, solved for and checked here (no table copied from anywhere).
"""
from __future__ import annotations

from fractions import Fraction

import numpy as np


def toom_cook(m: int, r: int, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A^T (m, n), G (n, r), B^T (n, n)) in float64 for F(m, r) at the n - 1 distinct finite `points`."""
    n = m + r - 1
    pts = [Fraction(p) for p in points]
    if m < 1 or r < 1 or len(pts) != n - 1 or len(set(pts)) != len(pts):
        raise ValueError(f"F({m}, {r}) needs {n - 1} distinct finite points, got {list(points)}")
    at = np.zeros((m, n), dtype=object)
    g = np.zeros((n, r), dtype=object)
    for j, aj in enumerate(pts):
        f = Fraction(1)
        for k, ak in enumerate(pts):
            if k != j:
                f *= aj - ak
        for i in range(m):
            at[i, j] = aj ** i
        for k in range(r):
            g[j, k] = aj ** k / f
    for i in range(m):  # the point at infinity: the leading coefficients
        at[i, n - 1] = Fraction(int(i == m - 1))
    for k in range(r):
        g[n - 1, k] = Fraction(int(k == r - 1))
    at, g = at.astype(np.float64), g.astype(np.float64)
    # sum_j A^T[i, j] G[j, k] B^T[j, l] = [l == i + k] for all i, k, l: linear in the n * n entries of B^T.
    rows = np.zeros((m, r, n, n, n))
    for l in range(n):
        rows[:, :, l, :, l] = at[:, None, :] * g.T[None, :, :]
    rhs = np.zeros((m, r, n))
    for i in range(m):
        for k in range(r):
            rhs[i, k, i + k] = 1.0
    sol = np.linalg.lstsq(rows.reshape(m * r * n, n * n), rhs.reshape(-1), rcond=None)[0]
    bt = sol.reshape(n, n)
    residual = np.abs(np.einsum("ij,jk,jl->ikl", at, g, bt) - rhs).max()
    if residual > 1e-9:
        raise ValueError(f"no exact F({m}, {r}) transform for points {list(points)} (residual {residual:.1e})")
    return at, g, bt
