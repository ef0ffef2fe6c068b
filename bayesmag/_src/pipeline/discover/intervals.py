r"""95 % intervals of a finding's located value (a thermal lag's tau, a step's time) by a block bootstrap of its profile.

A step inside a run has its own exact profile over every sample time of the run
(:func:`step_profile`, :func:`step_interval`); a thermal lag's tau uses the grid below.

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

import math

import numpy as np

__all__ = ["profile_interval", "profile_minimiser", "step_profile", "step_candidates", "step_minimiser", "step_interval", "N_BOOT"]

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


def _block_bootstrap(fit: np.ndarray, e: np.ndarray, block_rows: int, n_boot: int, seed: int) -> np.ndarray:
    """``(outputs * n, n_boot)`` series ``fit`` plus residuals ``e`` (outputs, n) resampled in circular
    blocks of ``block_rows`` rows (Politis & Romano 1992), the same blocks for every output."""
    outputs, n = e.shape
    L = int(np.clip(block_rows, 1, n))
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, n, (n_boot, -(-n // L)))
    idx = ((starts[:, :, None] + np.arange(L)[None, None, :]) % n).reshape(n_boot, -1)[:, :n]
    return fit[:, None] + e[:, idx.T].reshape(outputs * n, n_boot)


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
    Y = _block_bootstrap(fit, e, block_rows, n_boot, seed)
    sse = np.stack([_profile(X, Y)[0] for X in designs], axis=1)      # (R, V)
    mins = _argmin(grid, sse)
    a = (1 - level) / 2
    lo, hi = np.quantile(mins, [a, 1 - a])
    edge = float(np.mean((mins <= grid[0]) | (mins >= grid[-1])))
    return float(lo), float(hi), best, edge


def step_profile(Z: np.ndarray, col: np.ndarray, Y: np.ndarray, rows: np.ndarray, cand: np.ndarray,
                 outputs: int = 3) -> np.ndarray:
    r"""(C, R) SSE of the fit of each column of ``Y`` on ``[Z, step]`` with the step switched on
    from row ``rows[j]`` to the end of its run, for every candidate ``j`` in ``cand``; exact.

    By Frisch-Waugh-Lovell, with :math:`\tilde Y = M_Z Y` and the step column :math:`s_j`:

    .. math::  \mathrm{SSE}_j = \|\tilde Y\|^2 - \frac{(s_j^\top \tilde Y)^2}{s_j^\top s_j - (Z^\top s_j)^\top (Z^\top Z)^{-1} Z^\top s_j},

    and :math:`s_j^\top \tilde Y`, :math:`Z^\top s_j`, :math:`s_j^\top s_j` are reverse cumulative
    sums over the run's rows, so every sample time of the run is tried at the cost of one fit.

    Args:
      Z: (outputs*n, k) the other columns; col: (outputs*n,) the step column with every row of its
        run switched on; Y: (outputs*n, R) targets; rows: (c,) the run's rows in time order;
      cand: indices into ``rows`` of the candidate first stepped rows (>= 1).
    """
    Zs = _scaled(np.asarray(Z, dtype=float))
    G = Zs.T @ Zs
    k = G.shape[0]
    G = G + 1e-10 * max(float(np.trace(G)) / max(k, 1), 1e-300) * np.eye(k)
    Y = np.asarray(Y, dtype=float)
    Yt = Y - Zs @ np.linalg.solve(G, Zs.T @ Y)
    n = Y.shape[0] // outputs
    c = np.asarray(col, dtype=float).reshape(outputs, n)[:, rows]                     # (outputs, c)
    h = np.einsum("ac,acr->cr", c, Yt.reshape(outputs, n, -1)[:, rows])
    zc = np.einsum("ac,ack->ck", c, Zs.reshape(outputs, n, k)[:, rows])
    rc = lambda a: np.cumsum(a[::-1], axis=0)[::-1][cand]                             # noqa: E731  rows[j:] summed
    H, ZC, CC = rc(h), rc(zc), rc((c * c).sum(0))
    den = CC - (ZC * np.linalg.solve(G, ZC.T).T).sum(1)
    ok = den > 1e-9 * np.maximum(CC, 1e-300)
    gain = np.where(ok[:, None], H**2 / np.where(ok, den, 1.0)[:, None], 0.0)
    return (Yt * Yt).sum(0)[None, :] - gain


def step_candidates(c: int, margin: float = 0.02) -> np.ndarray:
    """Indices of the candidate first stepped rows of a run of ``c`` rows: at least ``margin`` of
    the rows (and one) before the step and as many stepped."""
    m = max(1, int(math.ceil(margin * c)))
    cand = np.arange(m, c - m + 1)
    if cand.size == 0:
        raise ValueError(f"a step inside a run needs at least 2 rows in the run; this one has {c}.")
    return cand


def step_minimiser(Z, col, y, rows, time, *, outputs: int = 3, margin: float = 0.02) -> float:
    """The least-squares step time (midpoint of the last unstepped and first stepped sample) over
    every sample time of the run (:func:`step_profile`); the estimate of :func:`step_interval`."""
    rows = np.asarray(rows)
    cand = step_candidates(rows.size, margin)
    j = int(np.argmin(step_profile(Z, col, np.asarray(y, dtype=float)[:, None], rows, cand, outputs)[:, 0]))
    return float(0.5 * (time[rows[cand[j] - 1]] + time[rows[cand[j]]]))


def step_interval(Z: np.ndarray, col: np.ndarray, y: np.ndarray, rows: np.ndarray, time: np.ndarray,
                  block_rows: int, *, outputs: int = 3, margin: float = 0.02, n_boot: int = N_BOOT,
                  seed: int = 0, level: float = 0.95) -> dict:
    """A step's time inside a run: the least-squares estimate over every sample time and its
    interval by a moving-block bootstrap of the exact profile (:func:`step_profile`).

    The step is located between two samples: the estimate is the midpoint of the last
    unstepped and the first stepped sample minimising the SSE (the profile is constant between
    samples, so no interpolation); a replicate gives such a sample pair too. The interval runs
    from the last unstepped sample of the ``(1 - level) / 2`` quantile replicate to the first
    stepped sample of the ``(1 + level) / 2`` one (quantiles taken outward), joined with the
    estimate's own pair: the replicates' minimisers are discrete, and a bootstrap set that
    piles up on one side of the estimate must still contain the data's minimiser.
    Candidates leave ``margin`` of the run's rows (at least one) at each end (a step at the
    run's ends is a run offset).

    Returns a dict: ``estimate``, ``lower``, ``upper`` (time units), ``row`` (first stepped row),
    ``edge`` (fraction of replicates at the first or last candidate).

    Example:
      >>> rng = np.random.default_rng(0); t = np.arange(600.0); run = np.zeros(600, int)
      >>> y = 1.0 * (t >= 240.5) + 0.3 * rng.standard_normal(600)
      >>> out = step_interval(np.ones((600, 1)), np.ones(600), y, np.arange(600), t, 20, outputs=1)
      >>> bool(out["lower"] <= 240.5 <= out["upper"]) and out["upper"] - out["lower"] < 10
      True
    """
    rows = np.asarray(rows)
    time = np.asarray(time, dtype=float)
    y = np.asarray(y, dtype=float)
    cand = step_candidates(rows.size, margin)
    j = int(np.argmin(step_profile(Z, col, y[:, None], rows, cand, outputs)[:, 0]))
    n = y.size // outputs
    on = np.zeros(n)
    on[rows[cand[j]:]] = 1.0
    X = np.column_stack([np.asarray(Z, dtype=float), np.asarray(col, dtype=float) * np.tile(on, outputs)])
    Xs = _scaled(X)
    beta = np.linalg.lstsq(Xs, y, rcond=None)[0]
    fit = Xs @ beta
    e = (y - fit).reshape(outputs, -1)
    Yb = _block_bootstrap(fit, e, block_rows, n_boot, seed)
    mins = np.argmin(step_profile(Z, col, Yb, rows, cand, outputs), axis=0)
    a = (1 - level) / 2
    qlo = int(np.quantile(mins, a, method="lower"))
    qhi = int(np.quantile(mins, 1 - a, method="higher"))
    lo, hi = min(qlo, j), max(qhi, j)
    first, prev = time[rows[cand]], time[rows[cand - 1]]
    return {"estimate": float(0.5 * (prev[j] + first[j])), "lower": float(prev[lo]), "upper": float(first[hi]),
            "row": int(rows[cand[j]]), "edge": float(np.mean((mins == 0) | (mins == cand.size - 1)))}
