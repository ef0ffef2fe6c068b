r"""The residual network's own new-session error in the hybrid transfer part (``[uq] transfer_networks``).

The transfer part of :mod:`~bayesmag._src.core.predictor` (``"loro"``) and of the hierarchical session
model (``"hierarchical"``) is estimated from the *physics* model's between-run scatter. The hybrid
prediction adds a residual network trained on every training run; on a session it never saw, its
correction differs from the one it would have made had it seen the session (it absorbs part of every
training session's shift, wrong for a new one), and that difference is in neither transfer term.

With ``transfer_networks = "by_run_folds"`` the training runs are split into :math:`K` =
min(``network.conformal_folds``, runs) groups (:func:`run_folds`); fold network :math:`k` is trained
without the runs of group :math:`k`. On every training row :math:`i` the network's new-session error is
:math:`d_i = \mu_{\text{fold}}(x_i) - \mu_{\text{full}}(x_i)`, the fold network's correction (it never
saw the row's run) less the calibrated predictor's (it did), on the rows inside the value domain of the
other folds' runs (:func:`fold_domain_mask`; rows outside it are extrapolation, flagged by the domain check,
not transfer -- as in :func:`~bayesmag._src.core.predictor.estimate_transfer`). A new session's hybrid error is then
(the error a network that had seen the session would make: the within-session variance and the physics
transfer part cover it) + :math:`d`, taken as independent; :math:`\tau_n` is the sd whose central
``level`` interval covers :math:`d`: :math:`\tau_n^2` = the ``level`` quantile of :math:`(d_i/z)^2` over
the training rows, every run weighted equally (the grouped conformal quantile of
:func:`~bayesmag._src.core.predictor.estimate_transfer`), :func:`network_transfer_sd`. The hybrid predictor
adds :math:`\tau_n` in quadrature to its transfer part (``Predictor.network_transfer_sd``); rows of the
training sessions never get it. No chi-square bound is applied (the physics transfer part carries one).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.stats

from bayesmag._src.core.data import AXES
from bayesmag._src.core.predictor import _weighted_quantile

__all__ = ["TRANSFER_NETWORKS", "NetworkTransfer", "run_folds", "fold_domain_mask", "grouped_excess_quantile", "network_transfer_sd"]

#: Values of ``[uq] transfer_networks``.
TRANSFER_NETWORKS = ("none", "by_run_folds")


@dataclasses.dataclass(frozen=True)
class NetworkTransfer:
    """The network part of the transfer sd ``sd`` (3,), uT, and how it was obtained.

    ``folds``: run groups; ``fold_runs``: the runs of every group; ``rmse_out_of_fold`` /
    ``rmse_in_sample``: per axis, the RMSE of the network's correction against its target (the pooled
    physics fit's residual) from the fold networks and from the calibrated predictor's network, on the rows in
    the other folds' domain (``rows_in_domain`` of them: 0 gives ``sd`` 0, nothing measured); ``rows``:
    the per-row pieces (``nn_oof``, ``nn_full``, ``resid``, ``run``, ``inside``).
    """

    sd: np.ndarray
    folds: int
    fold_runs: tuple
    rmse_out_of_fold: np.ndarray
    rmse_in_sample: np.ndarray
    rows_in_domain: int = 0
    rows: dict | None = dataclasses.field(default=None, repr=False, compare=False)   # per training row, for benchmarks

    def as_dict(self) -> dict:
        ax = lambda v: {a: float(x) for a, x in zip(AXES, v)}  # noqa: E731
        return {"method": "by_run_folds", "sd": ax(self.sd), "folds": self.folds,
                "fold_runs": [list(map(int, r)) for r in self.fold_runs], "rows_in_domain": int(self.rows_in_domain),
                "rmse_out_of_fold": ax(self.rmse_out_of_fold), "rmse_in_sample": ax(self.rmse_in_sample)}


def run_folds(run: np.ndarray, n_folds: int, seed: int) -> tuple[np.ndarray, int]:
    """Grouped K-fold by run: ``(fold of every row (n,), K)``, K = min(``n_folds``, runs), runs shuffled
    by ``seed`` and dealt to the folds in turn (each run in exactly one fold).

    Example: ``run_folds(np.repeat([1, 2, 3], 4), 5, 0)[1] == 3``.
    """
    runs = np.unique(run)
    k = int(min(n_folds, runs.size))
    fold_of_run = np.empty(runs.size, int)
    fold_of_run[np.random.default_rng(seed).permutation(runs.size)] = np.arange(runs.size) % k
    return fold_of_run[np.searchsorted(runs, run)], k


def fold_domain_mask(train, run_fold: np.ndarray) -> np.ndarray:
    """(n,) bool: the row lies inside the value domain of the rows of the other folds (field and temperature,
    :class:`~bayesmag._src.core.domain.Domain` without rates), i.e. its fold network interpolates there."""
    from bayesmag._src.core.domain import Domain

    inside = np.zeros(train.n, bool)
    for k in np.unique(run_fold):
        rows = np.flatnonzero(run_fold == k)
        other = train.subset(np.flatnonzero(run_fold != k))
        inside[rows] = ~Domain.from_data(other, rates=False).outside(train.subset(rows)).any(axis=1)
    return inside


def grouped_excess_quantile(err: np.ndarray, var: np.ndarray, run: np.ndarray, level: float = 0.95) -> np.ndarray:
    r"""(3,) :math:`\sqrt{\max(q, 0)}`, :math:`q` the ``level`` quantile of :math:`(e/z)^2 - v` over the rows, every run
    weighted equally: the sd that, added to variance ``var``, makes central ``level`` intervals cover ``err``.

    ``err``, ``var``: (n, 3); ``run``: (n,). Example: one of five runs off by 2 uT, unit variance: ``(2/1.96)^2 - 1``.
    """
    z = scipy.stats.norm.ppf(0.5 + level / 2)
    need = (np.asarray(err, np.float64) / z) ** 2 - np.broadcast_to(np.asarray(var, np.float64), np.shape(err))
    _, inv, counts = np.unique(run, return_inverse=True, return_counts=True)
    w = 1.0 / counts[inv]
    q = np.array([_weighted_quantile(need[:, a], w, level) for a in range(need.shape[1])])
    return np.sqrt(np.maximum(q, 0.0))


def network_transfer_sd(nn_oof: np.ndarray, nn_full: np.ndarray, run: np.ndarray, level: float = 0.95) -> np.ndarray:
    """(3,) network part of the transfer sd: covers ``nn_oof - nn_full`` (fold network less full network, per
    training row) at ``level``, every run weighted equally (:func:`grouped_excess_quantile` with no variance).

    Example: ``network_transfer_sd(np.ones((4, 3)), np.zeros((4, 3)), np.arange(4))`` is ``1/1.96`` per axis.
    """
    d = np.asarray(nn_oof, np.float64) - np.asarray(nn_full, np.float64)
    return grouped_excess_quantile(d, 0.0, run, level)
