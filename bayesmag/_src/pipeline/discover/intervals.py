r"""95 % intervals of a finding's located value (a thermal lag's tau, a step's time) by a block bootstrap of its profile.

For each value ``v`` on a grid the model with the finding at ``v`` (the other findings as
they are) is fitted by least squares; its residual sum of squares is the profile
``SSE(v)``. A bootstrap replicate keeps the designs and adds to the fitted values at the best
``v`` the residuals resampled in blocks of ``block_rows`` consecutive rows (a moving-block
bootstrap: blocks longer than the residual's correlation keep its autocorrelation; the three
outputs of a row move together), then takes the value minimising its profile (parabolic
between grid points). The 2.5 and 97.5 percentiles of the replicates' minimisers are the
interval. Per value one factorisation serves every replicate:

.. math::  \mathrm{SSE}_r(v) = y_r^\top y_r - (X_v^\top y_r)^\top (X_v^\top X_v)^{-1} X_v^\top y_r .

(Resampling whole blocks of *rows* instead drops the rows around a step in a third of the
replicates, and its interval then spans the dropped blocks.)

Example:
  >>> rng = np.random.default_rng(0); x = np.linspace(0, 1, 600)
  >>> y = np.where(x >= 0.4, 1.0, 0.0) + 0.3 * rng.standard_normal(600)
  >>> grid = np.linspace(0.3, 0.5, 41)
  >>> lo, hi, best, _ = profile_interval(lambda v: np.stack([np.ones(600), (x >= v) * 1.0], 1), y, grid, 20)
  >>> bool(lo <= 0.4 <= hi) and hi - lo < 0.02
  True
"""

from __future__ import annotations

import numpy as np

__all__ = ["profile_interval", "profile_minimiser", "N_BOOT"]

#: Bootstrap replicates of an interval.
N_BOOT = 400


def _scaled(X):
    s = np.sqrt((X * X).sum(0))
    return X / np.where(s > 0, s, 1.0)


def _profile(X, Y):
    """SSE of the least-squares fit of each column of Y (m, R) on X (m, k), and the fitted values of column 0."""
    Xs = _scaled(X)
    G = Xs.T @ Xs
    k = G.shape[0]
    G = G + 1e-10 * max(float(np.trace(G)) / k, 1e-300) * np.eye(k)
    C = Xs.T @ Y
    B = np.linalg.solve(G, C)
    return (Y * Y).sum(0) - (B * C).sum(0), Xs @ B[:, 0]


def _argmin(grid: np.ndarray, sse: np.ndarray) -> np.ndarray:
    """Minimiser over ``grid`` of each row of ``sse`` (R, V), parabolic between the neighbours."""
    j = np.argmin(sse, axis=1)
    jj = np.clip(j, 1, grid.size - 2)
    r = np.arange(sse.shape[0])
    y0, y1, y2 = sse[r, jj - 1], sse[r, jj], sse[r, jj + 1]
    den = y0 - 2 * y1 + y2
    h = grid[1] - grid[0] if grid.size > 1 else 0.0
    shift = np.where(den > 0, 0.5 * (y0 - y2) / np.where(den > 0, den, 1.0), 0.0)
    inner = (j >= 1) & (j <= grid.size - 2)
    return np.where(inner, grid[jj] + np.clip(shift, -1, 1) * h, grid[j])


def profile_minimiser(design, y: np.ndarray, grid: np.ndarray) -> float:
    """The value on ``grid`` (parabolic between points) minimising the least-squares profile on all rows."""
    grid = np.asarray(grid, dtype=float)
    full = np.array([_profile(np.asarray(design(v)), np.asarray(y, dtype=float)[:, None])[0][0] for v in grid])
    return float(_argmin(grid, full[None])[0])


def profile_interval(design, y: np.ndarray, grid: np.ndarray, block_rows: int, *, outputs: int = 1,
                     n_boot: int = N_BOOT, seed: int = 0, level: float = 0.95):
    """(lower, upper, minimiser on the data, fraction of replicates at a grid edge).

    Args:
      design: value -> (m, k) design matrix with the finding at that value (rows of ``y``).
      y: (m,) target; with ``outputs`` > 1 it is ``outputs`` stacked series of m / outputs rows
        (output-major) whose rows are resampled together.
      grid: (V,) equally spaced values (e.g. log tau, or a step time).
      block_rows: length of a resampled block (rows of one series; longer than the residual correlation).
      n_boot: bootstrap replicates; seed: their seed; level: the interval's coverage.
    """
    grid = np.asarray(grid, dtype=float)
    y = np.asarray(y, dtype=float)
    designs = [np.asarray(design(v)) for v in grid]
    full = np.array([_profile(X, y[:, None])[0][0] for X in designs])
    best_j = int(np.argmin(full))
    best = float(_argmin(grid, full[None])[0])
    _, fit = _profile(designs[best_j], y[:, None])
    e = (y - fit).reshape(outputs, -1)
    n = e.shape[1]
    L = int(np.clip(block_rows, 1, n))
    rng = np.random.default_rng(seed)
    nblk = -(-n // L)
    starts = rng.integers(0, n, (n_boot, nblk))
    idx = ((starts[:, :, None] + np.arange(L)[None, None, :]) % n).reshape(n_boot, -1)[:, :n]    # circular blocks
    Y = fit[:, None] + e[:, idx.T].reshape(outputs * n, n_boot)
    sse = np.stack([_profile(X, Y)[0] for X in designs], axis=1)      # (R, V)
    mins = _argmin(grid, sse)
    a = (1 - level) / 2
    lo, hi = np.quantile(mins, [a, 1 - a])
    edge = float(np.mean((mins <= grid[0]) | (mins >= grid[-1])))
    return float(lo), float(hi), best, edge
