"""Conformal interval calibration: the scores, the quantile, and the cross-conformal time-block folds.

Split conformal (Vovk et al. 2005; Lei et al. 2018): held-out rows' conformity scores
``|y - mean| / half-width`` under the central ``level`` interval (:func:`conformal_ratios`); the
``ceil((n+1) level)``-th smallest of them is the per-axis factor ``k`` on the predictive sd
(:func:`conformal_quantile`, :func:`conformal_scale`). The hybrid stage pools the scores of K
time-block folds, each scored by the network that did not see it (cross-conformal):
:func:`conformal_folds` places the folds and :func:`conformal_plan` sizes them.
"""

from __future__ import annotations

import numpy as np

from bayesmag._src.core.data import split_time_blocks
from bayesmag._src.core.predictor import FUSIONS, Prediction

__all__ = ["FUSIONS", "conformal_folds", "conformal_plan", "conformal_quantile", "conformal_ratios", "conformal_scale"]


def conformal_folds(run: np.ndarray, *, fraction: float, folds: int, seed: int) -> np.ndarray:
    """Cross-conformal folds ``(n,)``: fold ``k`` is one contiguous time block of ``fraction`` of every run,
    placed at a seeded position inside the k-th of ``folds`` equal stretches of the run (rows in time order);
    rows in no fold are -1. Stratified positions: the folds together sample the whole length of every run,
    so the scale does not hang on where one block per run happened to fall.
    """
    sp = split_time_blocks(run, test_fraction=folds * fraction, n_blocks=folds, seed=seed)
    held = np.zeros(run.size, bool)
    held[sp.test] = True
    fold = np.full(run.size, -1)
    for r in np.unique(run):
        rows = np.flatnonzero(run == r)
        slot = np.minimum(np.arange(rows.size) // max(rows.size // folds, 1), folds - 1)   # split_time_blocks' slots
        fold[rows[held[rows]]] = slot[held[rows]]
    return fold


def conformal_plan(split, net_cfg) -> tuple[float, int]:
    """``(fraction, folds)`` of the cross-conformal folds (``split``: its ``kind``, ``test_fraction``,
    ``n_blocks``; ``net_cfg``: its ``validation_fraction`` and ``conformal_folds``, e.g. :class:`NetworkSettings`): each fold one block of ``fraction`` of every
    run's training rows, ``folds`` of them.

    The scores must be as hard as the rows they calibrate: a network predicting the middle of a long
    held-out stretch errs more than one bridging a short gap. So with a ``time_blocks`` split the fold
    blocks are at least as long as the test blocks (``test_fraction / n_blocks`` of a run, i.e.
    ``test_fraction / n_blocks / (1 - test_fraction)`` of its training rows), else
    ``validation_fraction``; and there are at most ``conformal_folds`` of them, fewer where longer
    blocks would not fit in a run together (folds x fraction < 1; at least 2 folds, blocks then < 1/2).

    Example: ``test_fraction = 0.2`` in one block per run: blocks of 0.25 of the training rows, 3 folds.
    """
    fraction = net_cfg.validation_fraction
    if split.kind == "time_blocks":
        fraction = max(fraction, split.test_fraction / split.n_blocks / (1.0 - split.test_fraction))
    folds = net_cfg.conformal_folds
    while folds > 2 and folds * fraction >= 1.0:
        folds -= 1
    return min(fraction, 0.49), folds


def conformal_ratios(y: np.ndarray, pred: Prediction, level: float) -> np.ndarray:
    """Conformity scores ``|y - mean| / half-width`` ``(n, 3)`` of held-out rows ``y`` under the central
    ``level`` intervals of ``pred`` (the factor each row's interval would need to cover it)."""
    lo, hi = pred.interval(level)
    return np.abs(np.asarray(y, np.float64) - pred.mean) / (0.5 * (hi - lo))


def conformal_quantile(ratios: np.ndarray, level: float) -> np.ndarray:
    """Per-axis split-conformal quantile of ``ratios`` ``(n, 3)``: the ``ceil((n+1) level)``-th smallest."""
    ratios = np.asarray(ratios, np.float64)
    n = ratios.shape[0]
    if n < 20:
        raise ValueError(f"conformal_scale needs at least 20 held-out rows, got {n}")
    rank = min(int(np.ceil((n + 1) * level)), n)
    return np.sort(ratios, axis=0)[rank - 1]


def conformal_scale(y: np.ndarray, pred: Prediction, level: float) -> np.ndarray:
    """Per-axis factor ``k`` on the sd so that the central ``level`` intervals of ``pred`` cover
    ``level`` of the held-out rows ``y`` (split conformal: the ``ceil((n+1) level)``-th smallest
    ratio ``|y - mean| / half-width``; Vovk et al. 2005, Lei et al. 2018). Location-scale
    families: multiplying the sd by ``k`` multiplies the interval half-width by ``k``. Cross-conformal
    (scores of several folds, each from the model that did not see it) pools :func:`conformal_ratios`
    and takes :func:`conformal_quantile` of them.
    """
    return conformal_quantile(conformal_ratios(y, pred, level), level)
