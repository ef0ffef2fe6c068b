r"""The residual network's own new-session error in the hybrid transfer term (``[uq] transfer_networks``).

The transfer term of :mod:`~bayesmag._src.core.predictor` (``"loro"``) and of the hierarchical session
model (``"hierarchical"``) is estimated from the *physics* model's between-run scatter. The hybrid
prediction adds a residual network trained on every training run, so its error on a session it never
saw is not in that spread. With ``transfer_networks = "by_run_folds"`` the training runs are split
into :math:`K` = min(``network.conformal_folds``, runs) groups (:func:`run_folds`); fold network
:math:`k` is trained without the runs of group :math:`k`, and every training row :math:`i` gets an
out-of-session hybrid prediction: the leave-one-run-out physics prediction
(:func:`physics_loro_predictions`) plus the correction of the fold network that did not see its run.
Its error :math:`e_i` is covered by the new-session interval of variance
:math:`\sigma_i^2 + \tau_{p,i}^2 + \tau_n^2` (:math:`\sigma_i^2`: the calibrated hybrid predictor's
variance at the row without transfer; :math:`\tau_{p,i}`: the physics transfer sd there) iff
:math:`\tau_n^2 \ge (e_i/z)^2 - \sigma_i^2 - \tau_{p,i}^2`; :math:`\tau_n^2` is the ``level``
quantile of that bound over the training rows, every run weighted equally (the grouped conformal
quantile of :func:`~bayesmag._src.core.predictor.estimate_transfer`), floored at 0
(:func:`network_transfer_sd`). The hybrid predictor adds :math:`\tau_n` in quadrature to its transfer
part (``Predictor.network_transfer_sd``); rows of the training sessions never get it.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.stats

from bayesmag._src.core.data import AXES
from bayesmag._src.core.predictor import _weighted_quantile

__all__ = ["TRANSFER_NETWORKS", "NetworkTransfer", "run_folds", "physics_loro_predictions", "network_transfer_sd"]

#: Values of ``[uq] transfer_networks``.
TRANSFER_NETWORKS = ("none", "by_run_folds")


@dataclasses.dataclass(frozen=True)
class NetworkTransfer:
    """The network part of the transfer sd ``sd`` (3,), uT, and how it was obtained.

    ``folds``: run groups; ``fold_runs``: the runs of every group; ``rmse_out_of_fold`` /
    ``rmse_in_sample``: per axis, the RMSE of the out-of-session hybrid prediction (fold network +
    leave-one-run-out physics) and of the calibrated predictor on the same training rows; ``rows``: the
    per-row pieces (``err``, ``var``, ``tau_p``, ``nn_oof``, ``nn_full``, ``phys_loro``, ``phys_pooled``, ``run``).
    """

    sd: np.ndarray
    folds: int
    fold_runs: tuple
    rmse_out_of_fold: np.ndarray
    rmse_in_sample: np.ndarray
    rows: dict | None = dataclasses.field(default=None, repr=False, compare=False)   # per training row, for benchmarks

    def as_dict(self) -> dict:
        ax = lambda v: {a: float(x) for a, x in zip(AXES, v)}  # noqa: E731
        return {"method": "by_run_folds", "sd": ax(self.sd), "folds": self.folds,
                "fold_runs": [list(map(int, r)) for r in self.fold_runs],
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


def physics_loro_predictions(train, fit) -> np.ndarray:
    """(n, 3) prediction of every training row by the physics fit without its run (all folds in one
    compiled fit, :func:`~bayesmag._src.core.fit.fit_folds`); a fold that cannot be fitted keeps ``fit``'s."""
    from bayesmag._src.core.fit import fit_folds
    from bayesmag._src.core.physics import inputs_from_data

    runs = np.unique(train.run)
    held = np.stack([train.run == r for r in runs])
    out = np.asarray(fit.predict(inputs_from_data(train)), np.float64).copy()
    if runs.size < 2:
        return out
    thetas, oks = fit_folds(train, fit.model, ~held)
    for k in np.flatnonzero(oks):
        rows = np.flatnonzero(held[k])
        out[rows] = np.asarray(fit.model.predict_all(thetas[k], inputs_from_data(train.subset(rows))))
    return out


def network_transfer_sd(err: np.ndarray, var: np.ndarray, tau_p: np.ndarray, run: np.ndarray,
                        level: float = 0.95) -> np.ndarray:
    r"""(3,) network transfer sd: the grouped ``level`` quantile of :math:`(e/z)^2 - \sigma^2 - \tau_p^2`, floored at 0.

    ``err``: (n, 3) out-of-session errors; ``var``: (n, 3) predictive variance without transfer; ``tau_p``:
    (3,) or (n, 3) physics transfer sd; ``run``: (n,) run of every row (every run weighs the same).

    Example: one run with errors 2 uT, the others 0, unit variance, no physics transfer: ``tau_n^2 = (2/1.96)^2 - 1``.
    """
    z = scipy.stats.norm.ppf(0.5 + level / 2)
    need = (np.asarray(err) / z) ** 2 - np.asarray(var) - np.broadcast_to(np.asarray(tau_p, np.float64) ** 2, err.shape)
    _, inv, counts = np.unique(run, return_inverse=True, return_counts=True)
    w = 1.0 / counts[inv]
    q = np.array([_weighted_quantile(need[:, a], w, level) for a in range(err.shape[1])])
    return np.sqrt(np.maximum(q, 0.0))
