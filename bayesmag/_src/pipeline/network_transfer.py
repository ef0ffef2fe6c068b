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

**With the hierarchical transfer** (``[uq] transfer = "hierarchical"``) the two parts are not added: the session
model is refitted on the *out-of-fold hybrid residuals* :math:`e_i = y_i - f(x_i, \hat\theta) - \mu_{\text{fold}}(x_i)`
(:func:`hybrid_session_model`), on the training rows inside the other folds' domain. In them the distortion all
sessions share is removed by networks that learned it from the other runs (the physics-residual model read it as
session change), while the session's own shift and the network's error on a session it did not see stay (the
in-sample residuals after the full network lose about half of every training run's shift: the network absorbed
it). That model's row-wise transfer sd then *replaces* physics session model + :math:`\tau_n` for the hybrid's
new-session rows: :math:`d` is already inside those residuals, so adding :math:`\tau_n` again would count the
network's new-session error twice.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.stats

from bayesmag._src.core.data import AXES
from bayesmag._src.core.predictor import _weighted_quantile

__all__ = ["TRANSFER_NETWORKS", "NetworkTransfer", "run_folds", "fold_domain_mask", "grouped_excess_quantile",
           "network_transfer_sd", "hybrid_residual_rows", "hybrid_session_model", "new_session_transfer_rows"]

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
    session_model: object = None    # TransferEstimate of the hybrid session model (hierarchical transfer), or None

    def as_dict(self) -> dict:
        ax = lambda v: {a: float(x) for a, x in zip(AXES, v)}  # noqa: E731
        out = {"method": "by_run_folds", "sd": ax(self.sd), "folds": self.folds,
               "fold_runs": [list(map(int, r)) for r in self.fold_runs], "rows_in_domain": int(self.rows_in_domain),
               "rmse_out_of_fold": ax(self.rmse_out_of_fold), "rmse_in_sample": ax(self.rmse_in_sample)}
        if self.session_model is not None:      # sd is then reported, not added (it is inside the model's residuals)
            out["combined"] = "hierarchical_out_of_fold"
            out["session_model"] = {"residuals": "out-of-fold hybrid (physics residual - fold network)",
                                    **self.session_model.as_dict()}
        return out


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


#: A run enters the hybrid session model with at least this many rows inside the other folds' domain.
MIN_ROWS_PER_RUN = 2


def _kept_rows(train, nt: NetworkTransfer):
    """Indices of the training rows the hybrid session model is fitted on (:func:`hybrid_residual_rows`), or None."""
    keep = np.asarray(nt.rows["inside"], bool).copy()
    runs, counts = np.unique(train.run[keep], return_counts=True)
    keep &= np.isin(train.run, runs[counts >= MIN_ROWS_PER_RUN])
    if np.unique(train.run[keep]).size < max(2, np.unique(train.run).size):
        return None     # a session left out (e.g. the only run that varies temperature): its information would be lost
    return np.flatnonzero(keep)


def hybrid_residual_rows(train, nt: NetworkTransfer):
    r"""The training rows the hybrid session model is fitted on: those inside the other folds' domain, of runs with
    at least :data:`MIN_ROWS_PER_RUN` of them, with reference :math:`B_{ref} - \mu_{\text{fold}}` (so that the
    physics residual at the pooled fit is the out-of-fold hybrid residual); None unless every training run keeps
    :data:`MIN_ROWS_PER_RUN` rows (a run left out takes what only it shows with it: on Belsten ``paper_hybrid`` run 6,
    the only run whose temperature varies, has no row inside the other folds' domain, and the refitted model's
    transfer sd ran to 130-520 uT at the hottest rows; the physics session model and :math:`\tau_n` are used then).

    Rows outside are left out, not given the full network's correction: a fold network extrapolating there is
    not the error a new session inside the domain sees (and the domain check flags such rows of a new session).
    The AR(1) model then takes the kept rows of a run as consecutive (a run's gaps are not modelled).
    """
    return _residual_rows(train, nt, _kept_rows(train, nt))


def _residual_rows(train, nt: NetworkTransfer, kept):
    """``train``'s rows ``kept`` with reference B_ref - mu_fold (None for None)."""
    if kept is None:
        return None
    sub = train.subset(kept)
    return dataclasses.replace(sub, b_ref=np.asarray(sub.b_ref, np.float64) - nt.rows["nn_oof"][kept])


def hybrid_session_model(train, fit, nt: NetworkTransfer, uq, series=None):
    r"""``(TransferEstimate, SessionPosterior)`` of the hierarchical session model fitted on the out-of-fold hybrid
    residuals (:func:`hybrid_residual_rows`) with the physics stage's options (``uq``: a
    :class:`~bayesmag._src.pipeline.settings.UQSettings`, ``transfer`` hierarchical), around the pooled LM ``fit``;
    None when a training run has too few rows inside the other folds' domain (:func:`hybrid_residual_rows`; then the
    physics session model and :math:`\tau_n` are used, as without this model).

    ``series = (recording, train_index)``: a model whose rows depend on their neighbours (a thermal lag) is
    linearised and its folds refitted within the recording, whose reference at the kept rows is the same
    :math:`B_{ref} - \mu_{\text{fold}}` (its other rows have weight 0).

    The check against leave-one-run-out (``[uq] transfer_check``) only warns here, whatever its setting: its
    fallback is for the physics session model's known misreadings, while the excess width of this model is the fold
    networks' error on runs they did not see, which a new session meets too. On ``bench_hybrid_shift``
    (``--transfer-networks by_run_folds``, seeds 0-8, 72 left-out sessions) the fallback left 6 session-axes under
    95 % covered or flagged (the worst 38.7 %) against 1 without it (90.3 %), for 61 instead of 77 of 195 over 1.5x
    leave-one-run-out's width (docs/sessions.md, "The check on the hybrid's session model").
    """
    from bayesmag._src.pipeline.sessions import hierarchical_transfer

    kept = _kept_rows(train, nt)
    if kept is None:
        return None
    rows = _residual_rows(train, nt, kept)
    within = None
    if series is not None and fit.model.needs_series:
        recording, index = series[0], np.asarray(series[1])[kept]
        b_ref = np.array(recording.b_ref, np.float64)
        b_ref[index] = rows.b_ref
        within = (dataclasses.replace(recording, b_ref=b_ref), index)
    tr, post = hierarchical_transfer(rows, fit, method="nuts" if uq.transfer.endswith("nuts") else "laplace",
                                     level=uq.level, seed=uq.seed, likelihood=uq.transfer_likelihood,
                                     df=uq.transfer_df, uninformed=uq.transfer_uninformed, series=within,
                                     check="warn")
    return (tr, post) if post is not None else None


def new_session_transfer_rows(pr, data, series=None) -> np.ndarray:
    """(n, 3) transfer sd a :class:`~bayesmag._src.core.predictor.Predictor` adds to a new session's rows of ``data``
    (its row-wise session model or constant, with the network part in quadrature, as ``Predictor.compose``).
    ``series = (recording, index)``: ``data``'s rows taken within the recording (a model that needs its series)."""
    n = data.n
    if series is not None and pr.sessions is not None and pr.fit.model.needs_series:
        t = np.asarray(pr.transfer_part(series[0]), np.float64)[np.asarray(series[1])]
    else:
        t = pr.transfer_part(data) if pr.sessions is not None else \
            np.broadcast_to(np.zeros(3) if pr.transfer_sd is None else np.asarray(pr.transfer_sd, np.float64), (n, 3))
    if pr.network_transfer_sd is not None and pr.network is not None:
        t = np.sqrt(np.asarray(t, np.float64) ** 2 + np.asarray(pr.network_transfer_sd, np.float64) ** 2)
    return np.asarray(t, np.float64)
