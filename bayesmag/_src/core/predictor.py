r"""The one predictive distribution: physics posterior + residual term + optional network + fusion + family.

A :class:`Predictor` holds everything a fitted calibration needs to predict a recording; its
:meth:`~Predictor.predict` is pure (same inputs, same outputs) and returns a
:class:`Prediction`: the predictive distribution all scores come from, its mean and total sd,
and the named standard deviations it is built from. The job, the simulation study, the
hybrid benchmark and ``bayesmag apply`` (through :class:`~bayesmag._src.app.artifact.Calibration`)
all predict through it, so what a run reports and what ``apply`` computes from the saved
calibration cannot drift apart.

Composition (:func:`compose`), per row and axis, with physics aleatoric / epistemic sds
:math:`a_p, e_p` (PS-QMC), residual sd :math:`r` (training scatter beyond the propagated input
noise), network aleatoric / epistemic sds :math:`a, e` (MC DropConnect) and transfer sd
:math:`\tau` (between-session variation, :func:`estimate_transfer`), and conformal scale :math:`c`
(conformal factor on held-out time, :mod:`bayesmag._src.pipeline.conformal`; 1 when absent):

* physics only: :math:`N(\bar y_{phys},\; c^2 (a_p^2 + r^2 + e_p^2) + \tau^2)`;
* network, ``fusion = "moment_match"``: mean :math:`\bar y_{phys} + \mu_{NN}`, variance
  :math:`c^2 (a^2 + e^2 + e_p^2) + \tau^2`, the network's likelihood family moment-matched to it
  (the network learned :math:`a^2` from residuals that already hold :math:`a_p^2` and :math:`r^2`);
* network, ``fusion = "paper"``: Gaussian with :math:`c^2 (a_p^2 + a^2 + e^2 + e_p^2) + \tau^2`
  (Shetty & Marndi 2026, sec. 2.5).

The transfer part enters only rows of a *new session* (``new_session``: a recording that is not
one of the training runs -- every row of a recording given to ``bayesmag apply``); rows of the
training sessions (random or time-block test rows) get :math:`\tau = 0`. It is absent (not
zero-added) when ``transfer_sd`` is None, and :math:`k` when ``scale`` is None.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import numpy as np

from bayesmag._src.core.likelihoods import Gaussian, Likelihood, get_likelihood, moment_match
from bayesmag._src.core.physics import new_session_runs

__all__ = ["FUSIONS", "UQOptions", "Components", "Prediction", "Predictor", "TransferEstimate", "compose",
           "estimate_transfer", "network_inputs",
           "session_variance_bound", "few_runs_warning"]

FUSIONS = ("moment_match", "paper")

#: Confidence of the upper bound on the transfer variance (:func:`estimate_transfer`).
TRANSFER_CONFIDENCE = 0.8

#: Rows per MC-DropConnect call (bounds memory of the passes on large recordings).
NN_CHUNK = 50_000


def network_inputs(data) -> np.ndarray:
    """The residual network's inputs ``(n, 4)``: measured field (3) and temperature, float64."""
    return np.column_stack([data.b_meas, data.temperature]).astype(np.float64)


@dataclasses.dataclass(frozen=True)
class UQOptions:
    """How the physics uncertainty is propagated (:func:`~bayesmag.physics_uncertainty`)."""

    method: str = "auto"               # physics_uq.DEFAULT_METHOD: analytic where exact, else psqmc
    n_params: int = 500
    n_qmc: int = 1000
    seed: int = 0
    chunk_size: int = 256


class Components(NamedTuple):
    """The separately computed pieces of a prediction: physics UQ, (optional) MC network output and
    (optional) row-dependent transfer sd ``(n, 3)`` of a hierarchical session model."""

    physics: Any                 # PhysicsUQ
    nn: Any = None               # MCPrediction or None
    transfer: Any = None         # (n, 3) transfer sd from Predictor.sessions, or None


@dataclasses.dataclass(frozen=True)
class Prediction:
    """A predictive distribution over ``(n, 3)`` field values (uT) and the parts it is made of.

    ``parts``: named sds ``(n, 3)`` -- ``aleatoric_physics``, ``epistemic_physics``, and, where
    they enter the total, ``residual_physics``, ``aleatoric_nn``, ``epistemic_nn``, ``transfer``.
    ``in_domain`` / ``domain_reason``: ``(n,)``, set by :meth:`Predictor.predict` when the
    predictor knows its training domain, else None. ``level``: the calibration's interval level (its
    ``[uq] level``, :attr:`Predictor.level`), what :meth:`interval` gives without an argument.
    """

    mean: np.ndarray
    dist: Likelihood
    total: np.ndarray
    parts: dict
    fusion: str | None = None
    family: str = "gaussian"
    in_domain: np.ndarray | None = None
    domain_reason: np.ndarray | None = None
    level: float = 0.95

    def __post_init__(self):
        check_level(self.level, "Prediction.level")

    def interval(self, level: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Central interval of :attr:`dist` of probability ``level`` (default: :attr:`level`, the calibration's),
        float64 ``(lower, upper)``; a level outside (0, 1), such as 95, is a ``ValueError`` naming it."""
        level = self.level if level is None else check_level(level, "Prediction.interval(level)")
        lo, hi = self.dist.interval(level)
        return np.asarray(lo, np.float64), np.asarray(hi, np.float64)

    def _part(self, name):
        return self.parts.get(name)

    aleatoric_physics = property(lambda self: self._part("aleatoric_physics"))
    epistemic_physics = property(lambda self: self._part("epistemic_physics"))
    residual_physics = property(lambda self: self._part("residual_physics"))
    aleatoric_nn = property(lambda self: self._part("aleatoric_nn"))
    epistemic_nn = property(lambda self: self._part("epistemic_nn"))
    transfer = property(lambda self: self._part("transfer"))


def check_level(level, what: str = "level") -> float:
    """``level`` as a float if it is a number in (0, 1); else a ``ValueError`` naming it (95 for 0.95 among them)."""
    if isinstance(level, bool) or not isinstance(level, (int, float, np.integer, np.floating)) or not 0 < level < 1:
        hint = f" (a percentage? use {level / 100:g})" if (isinstance(level, (int, float)) and not isinstance(
            level, bool) and 1 < level < 100) else ""
        raise ValueError(f"{what} = {level!r} must be a number in (0, 1), e.g. 0.95 for a 95 % interval{hint}.")
    return float(level)


def compose(physics, nn=None, *, residual_sd=None, fusion: str = "moment_match", family: str = "gaussian",
            fixed_shape=None, transfer_sd=None, scale=None, new_session=True, level: float = 0.95) -> Prediction:
    """The predictive distribution from its computed parts (rules in the module docstring).

    ``physics``: a :class:`~bayesmag.PhysicsUQ`; ``nn``: an MC-DropConnect
    :class:`~bayesmag._src.core.network.MCPrediction` or None; ``residual_sd``, ``transfer_sd``:
    ``(3,)`` or ``(n, 3)`` sds or None; ``fixed_shape``: the family's shape fields held fixed
    (:attr:`NetworkSpec.fixed_shape`, e.g. Student-t ``df``); the others come from the network's
    learned per-row values; ``scale``: ``(3,)`` interval factor or None; ``new_session``:
    bool or ``(n,)`` mask of the rows the transfer part enters; ``level``: the prediction's interval level
    (:attr:`Prediction.level`).
    """
    if fusion not in FUSIONS:
        raise ValueError(f"fusion {fusion!r} is not known; it must be one of {list(FUSIONS)}")
    p_mean = np.asarray(physics.mean, np.float64)
    parts = {"aleatoric_physics": np.asarray(physics.aleatoric), "epistemic_physics": np.asarray(physics.epistemic)}
    tau = None
    if transfer_sd is not None:
        new = np.broadcast_to(np.asarray(new_session, bool).reshape(-1, 1) if np.ndim(new_session) else
                              np.asarray(bool(new_session)), (p_mean.shape[0], 1))
        tau = np.where(new, np.broadcast_to(np.asarray(transfer_sd, np.float64), p_mean.shape), 0.0)
    k2 = None if scale is None else np.asarray(scale, np.float64) ** 2
    if nn is None:
        resid = np.broadcast_to(np.zeros(3) if residual_sd is None else np.asarray(residual_sd, np.float64),
                                p_mean.shape)
        parts["residual_physics"] = resid
        var = physics.aleatoric**2 + resid**2 + physics.epistemic**2
        if k2 is not None:
            var = k2 * var
        if tau is not None:
            var = var + tau**2
        mean, dist_fam = p_mean, "gaussian"
        dist = Gaussian(mean, np.sqrt(var))
        fusion = None
    else:
        mean = p_mean + nn.mean
        parts["aleatoric_nn"], parts["epistemic_nn"] = nn.aleatoric, nn.epistemic
        var = nn.aleatoric**2 + nn.epistemic**2 + physics.epistemic**2
        if fusion == "paper":
            var = var + physics.aleatoric**2
        if k2 is not None:
            var = k2 * var
        if tau is not None:
            var = var + tau**2
        if fusion == "paper":
            dist_fam, dist = "gaussian", Gaussian(mean, np.sqrt(var))
        else:
            fixed = dict(fixed_shape or {})
            shape = {f: fixed[f] if f in fixed else nn.shape[f] for f in get_likelihood(family).shape_names()}
            dist_fam, dist = family, moment_match(family, mean, var, **shape)
    if tau is not None:
        parts["transfer"] = tau
    return Prediction(mean, dist, np.sqrt(var), parts, fusion, dist_fam, level=level)


@dataclasses.dataclass(frozen=True)
class Predictor:
    """Everything needed to predict a recording: a frozen value, :meth:`predict` is pure.

    ``fit``: the physics posterior (a :class:`~bayesmag.PhysicsFit` or the view a saved
    calibration gives); ``sigma_in``: (4, 4) input-noise covariance; ``residual_sd``: (3,)
    residual term; ``network``: trained :class:`~bayesmag._src.core.network.ResidualNetwork`, a
    :class:`~bayesmag._src.core.network.NetworkEnsemble` of them (``passes`` split over the members, moments
    pooled over all passes) or None, predicted with ``passes`` MC passes from ``network_seed``; ``fusion``: one of
    :data:`FUSIONS`; ``transfer_sd``: (3,) between-session sd or None; ``scale``: (3,) interval
    factor (:func:`~bayesmag._src.pipeline.conformal.conformal_scale`) or None; ``domain``: the
    training :class:`~bayesmag._src.core.domain.Domain` or None; ``uq``: physics UQ settings;
    ``sessions``: a hierarchical session posterior (``transfer_sd(fit, data) -> (n, 3)``, e.g.
    :class:`~bayesmag._src.pipeline.sessions.SessionPosterior`) whose row-dependent transfer sd
    replaces ``transfer_sd``, or None; ``network_transfer_sd``: (3,) sd of the network's own error on a new
    session (:mod:`~bayesmag._src.pipeline.network_transfer`), added in quadrature to the transfer part, or None;
    ``level``: the calibration's central interval level (``[uq] level``), which every :class:`Prediction` it makes
    carries (:meth:`Prediction.interval` without an argument).
    """

    fit: Any
    sigma_in: np.ndarray
    residual_sd: np.ndarray
    network: Any = None
    passes: int = 100
    network_seed: int = 0
    fusion: str = "moment_match"
    transfer_sd: np.ndarray | None = None
    scale: np.ndarray | None = None
    domain: Any = None
    uq: UQOptions = UQOptions()
    sessions: Any = None
    network_transfer_sd: np.ndarray | None = None    # (3,) the network's own new-session sd ([uq] transfer_networks)
    level: float = 0.95

    def __post_init__(self):
        if self.fusion not in FUSIONS:
            raise ValueError(f"fusion {self.fusion!r} is not known; it must be one of {list(FUSIONS)}")
        check_level(self.level, "Predictor.level")

    def __repr__(self) -> str:
        theta = np.shape(getattr(self.fit, "theta", ()))
        members = getattr(self.network, "members", None)
        net = "none" if self.network is None else (f"ensemble of {len(members)}" if members else "one")
        opt = lambda v: "none" if v is None else "[" + ", ".join(f"{x:.3g}" for x in np.asarray(v, float).reshape(-1)) + "]"  # noqa: E731
        return (f"Predictor(physics {theta[-1] if theta else '?'} parameters per axis, network={net}, "
                f"fusion={self.fusion!r}, transfer_sd={opt(self.transfer_sd)}, scale={opt(self.scale)}, "
                f"uq={self.uq.method!r}, level={self.level:g})")

    @property
    def family(self) -> str:
        """Likelihood family of the predictive distribution's network part ('gaussian' without one)."""
        return "gaussian" if self.network is None else self.network.spec.likelihood

    def physics_part(self, data, *, progress: bool = False, history: tuple | None = None):
        """Physics prediction and its PS-QMC (or analytic) uncertainty for every row of ``data`` (``history``: see
        :func:`~bayesmag._src.core.physics_uq.physics_uncertainty`)."""
        from bayesmag._src.core.physics import inputs_from_data
        from bayesmag._src.core.physics_uq import physics_uncertainty

        o = self.uq
        return physics_uncertainty(self.fit, inputs_from_data(data), sigma_in=self.sigma_in, method=o.method,
                                   n_params=o.n_params, n_qmc=o.n_qmc, seed=o.seed, chunk_size=o.chunk_size,
                                   progress=progress, history=history)

    def network_part(self, data):
        """MC-DropConnect residual prediction for every row of ``data`` (None without a network)."""
        from bayesmag._src.core.network import mc_predict

        if self.network is None:
            return None
        x = network_inputs(data)
        if x.shape[0] <= NN_CHUNK:
            return mc_predict(self.network, x, passes=self.passes, seed=self.network_seed)
        pieces = [mc_predict(self.network, x[lo:lo + NN_CHUNK], passes=self.passes, seed=self.network_seed)
                  for lo in range(0, x.shape[0], NN_CHUNK)]
        cat = {f: np.concatenate([getattr(p, f) for p in pieces]) for f in ("mean", "aleatoric", "epistemic")}
        return type(pieces[0])(**cat, shape={k: np.concatenate([p.shape[k] for p in pieces])
                                             for k in pieces[0].shape})

    def components(self, data, *, progress: bool = False, history: tuple | None = None) -> Components:
        """Physics UQ, the MC network output and the row-dependent transfer sd for every row of ``data``."""
        return Components(self.physics_part(data, progress=progress, history=history), self.network_part(data),
                          self.transfer_part(data))

    def transfer_part(self, data):
        """Row-dependent transfer sd ``(n, 3)`` of the hierarchical session model (None without one)."""
        return None if self.sessions is None else self.sessions.transfer_sd_for(self.fit, data)

    def compose(self, c: Components, *, fusion: str | None = None, new_session=True) -> Prediction:
        """The prediction from already computed components (``fusion`` overrides the predictor's;
        ``new_session``: bool or (n,) mask of rows from sessions the calibration was not fitted on)."""
        spec = None if self.network is None else self.network.spec
        transfer = self.transfer_sd
        if self.sessions is not None:
            if c.transfer is None and np.any(new_session):
                raise ValueError("this predictor's transfer sd depends on the rows (hierarchical session model): "
                                 "build the components with Predictor.components(data) or Components(..., "
                                 "transfer=Predictor.transfer_part(data)).")
            transfer = c.transfer
        if self.network_transfer_sd is not None and self.network is not None:
            nts = np.asarray(self.network_transfer_sd, np.float64)
            transfer = nts if transfer is None else np.sqrt(np.asarray(transfer, np.float64) ** 2 + nts**2)
        return compose(c.physics, c.nn, residual_sd=self.residual_sd, fusion=fusion or self.fusion,
                       family=self.family, fixed_shape=None if spec is None else spec.fixed_shape, transfer_sd=transfer,
                       scale=self.scale, new_session=new_session, level=self.level)

    def predict(self, data, *, new_session=True, progress: bool = False, history: tuple | None = None) -> Prediction:
        """The predictive distribution for every row of ``data`` (no reference needed).

        ``new_session`` (default True: a recording given to a saved calibration is a new session)
        adds the transfer part; False predicts rows of the training sessions.
        """
        if np.any(new_session) and self.fit.model.bound_runs:
            # a run offset or step fitted to a training run is no part of a new session's model (new_session_runs)
            data = dataclasses.replace(data, run=new_session_runs(self.fit.model, data.run, new_session))
        pred = self.compose(self.components(data, progress=progress, history=history), new_session=new_session)
        if self.domain is None:
            return pred
        out = self.domain.outside(data, pred.mean)
        return dataclasses.replace(pred, in_domain=~out.any(axis=1), domain_reason=self.domain.reasons(out))


@dataclasses.dataclass(frozen=True)
class TransferEstimate:
    """Between-session sd per axis and how it was obtained.

    ``method``: ``"leave_one_run_out"``, ``"largest_offset_change"`` (fewer than 3 usable runs)
    or ``"off"``; ``per_run``: for every left-out run, its in-domain rows and RMSE per axis;
    ``warning``: text for the user, or None.
    """

    sd: np.ndarray
    method: str
    per_run: dict
    warning: str | None = None

    def as_dict(self) -> dict:
        return {"sd": {ax: float(v) for ax, v in zip("xyz", self.sd)}, "method": self.method,
                "per_run": self.per_run, "warning": self.warning}


def _weighted_quantile(v: np.ndarray, w: np.ndarray, q: float) -> float:
    order = np.argsort(v)
    cum = np.cumsum(w[order]) / np.sum(w)
    return float(v[order][min(np.searchsorted(cum, q - 1e-12), v.size - 1)])


def session_variance_bound(need, weight, within, n_runs: int, level: float = 0.95, exact=0.0) -> np.ndarray:
    r"""Between-session sd from leave-one-run-out rows: the grouped conformal quantile, bounded over the runs.

    ``need`` (n,) or (n, k): each left-out row's :math:`(e_i / z)^2 - s_i^2`, the smallest extra variance that
    covers it (:math:`z = \Phi^{-1}((1+\mathrm{level})/2)`, :math:`s_i^2` its within-session variance);
    ``weight`` (n,): ``1 / n_r`` for a row of run ``r`` (every run counts once); ``within``: the within-session
    variance :math:`s^2` the bound is on (scalar or (k,)); ``n_runs`` = R, the runs the rows come from. The
    ``level`` quantile :math:`q` of ``need`` makes the new-session variance :math:`s^2 + q`; from R runs it is
    replaced by its one-sided :data:`TRANSFER_CONFIDENCE` = c upper bound :math:`(s^2 + q)(R-1)/\chi^2_{R-1}(1-c)`,
    and the sd returned is :math:`\sqrt{\max(\text{that} - s^2, 0)}`: (k,), or a float for a 1-D ``need``.
    ``exact``: a part :math:`w^2 \le s^2` of the within variance known from far more than R samples (white
    reading noise), held out of the bound: :math:`(s^2 - w^2 + q)(R-1)/\chi^2_{R-1}(1-c) + w^2 - s^2`.

    Example:
      >>> import scipy.stats    # three runs, median row need 1.0: x 2 / chi2_2(0.2) = 4.48
      >>> round(session_variance_bound(np.array([0.0, 1.0, 2.0]), np.ones(3), 0.0, 3, level=0.5) ** 2, 3)
      4.481
    """
    import scipy.stats
    need = np.asarray(need, np.float64)
    v = need.reshape(need.shape[0], -1)
    q = np.array([_weighted_quantile(v[:, a], np.asarray(weight, np.float64), level) for a in range(v.shape[1])])
    within = np.broadcast_to(np.asarray(within, np.float64), q.shape)
    exact = np.minimum(np.broadcast_to(np.asarray(exact, np.float64), q.shape), within)
    inflate = (n_runs - 1) / scipy.stats.chi2.ppf(1 - TRANSFER_CONFIDENCE, n_runs - 1)
    tau = np.sqrt(np.maximum((q + within - exact) * inflate + exact - within, 0.0))
    return float(tau[0]) if need.ndim == 1 else tau


def estimate_transfer(train, fit, fit_fn=None, *, level: float = 0.95, min_runs: int = 3,
                      series=None) -> TransferEstimate:
    r"""Between-session (transfer) sd from the training runs: leave-one-run-out, conformal over runs.

    For every training run ``r``: refit without ``r`` and predict run ``r``'s
    rows that lie inside the other runs' value domain (rows outside it are extrapolation, flagged
    by the domain check, not transfer). Row ``i`` of a left-out run is covered by a central
    ``level`` Gaussian interval of variance :math:`s^2 + \tau^2` (:math:`s^2`: the pooled fit's
    residual variance, the within-session part) iff
    :math:`\tau^2 \ge (e_i / z)^2 - s^2`, :math:`z = \Phi^{-1}((1+\mathrm{level})/2)`. The
    ``level`` quantile :math:`q` of that bound over the left-out rows, every run weighted equally
    (grouped, Mondrian-style conformal calibration with runs as groups), makes the new-session
    variance :math:`s^2 + q`. That variance is estimated from :math:`R` usable runs (the runs, not
    the rows, are the sample), so it is replaced by its one-sided :data:`TRANSFER_CONFIDENCE` = c
    upper bound, :math:`(s^2 + q)(R-1)/\chi^2_{R-1}(1 - c)` (x 1.29 at R = 30, x 2.1 at R = 6),
    and :math:`\tau^2 = (s^2 + q)(R-1)/\chi^2_{R-1}(1 - c) - s^2`. The bound is on the whole
    new-session variance: the pooled :math:`s^2` holds part of the between-run scatter too, and
    bounding :math:`q` alone took that part as exact (``benchmarks/bench_transfer.py``). With fewer
    than ``min_runs`` usable runs it cannot be estimated: the sd is widened to the largest change of
    the per-run mean residual of the pooled ``fit`` between two runs (0 for one run), with a warning.
    ``series``: ``(recording, train_index)`` for a model whose rows depend on their neighbours (input
    transforms, history terms): the folds are fitted and predicted within the recording (held-out rows stay in
    the series, weight 0), as the job's fit was.
    """
    import scipy.stats

    from bayesmag._src.core.domain import Domain
    from bayesmag._src.core.physics import inputs_from_data

    runs = [int(r) for r in np.unique(train.run)]
    if fit_fn is None and fit.model.bound_runs:
        # a run offset (or step) of the left-out run has no value in its fold: each fold refits the model without
        # it (physics.restricted) and predicts the run as a new session, with no offset of its own
        from bayesmag._src.core.fit import fit_physics
        from bayesmag._src.core.physics import restricted

        def fit_fn(other):
            return fit_physics(other, restricted(fit.model, np.unique(other.run)))    # a fold it refuses: skipped
    per_run, need, weight = {}, [], []
    s2 = np.asarray(fit.s2, np.float64)
    z = scipy.stats.norm.ppf(0.5 + level / 2)
    if len(runs) >= min_runs:
        held_all = np.stack([train.run == r for r in runs])
        whole = series is not None and fit_fn is None and fit.model.needs_series
        if whole:                   # the folds within the recording: its other rows stay in the series
            from bayesmag._src.core.fit import fit_folds
            recording, index = series
            keep = np.zeros((len(runs), recording.n), bool)
            keep[:, index] = ~held_all
            thetas, oks = fit_folds(recording, fit.model, keep)
            rec_inputs = inputs_from_data(recording)
        elif fit_fn is None:        # every fold in one compiled, vmapped fit (fit.fit_folds)
            from bayesmag._src.core.fit import fit_folds
            thetas, oks = fit_folds(train, fit.model, ~held_all)
        for k, r in enumerate(runs):
            held, rest = held_all[k], ~held_all[k]
            other, left = train.subset(np.flatnonzero(rest)), train.subset(np.flatnonzero(held))
            inside = ~Domain.from_data(other, rates=False).outside(left).any(axis=1)
            per_run[str(r)] = {"n_in_domain": int(inside.sum()), "rmse": None}
            if inside.sum() < 2:
                continue
            rows = left.subset(np.flatnonzero(inside))
            if fit_fn is None:
                if not oks[k]:      # an unidentifiable fold (e.g. no temperature variation) is skipped
                    continue
                pred = (np.asarray(fit.model.predict_all(thetas[k], rec_inputs))[index[held][inside]] if whole
                        else fit.model.predict_all(thetas[k], inputs_from_data(rows)))
            else:
                try:
                    f = fit_fn(other)
                    ok = bool(getattr(f, "converged", True))
                except Exception:    # an unidentifiable fold (e.g. no temperature variation) is skipped
                    ok = False
                if not ok:
                    continue
                pred = f.predict(inputs_from_data(rows))
            e = rows.b_ref - np.asarray(pred)
            need.append((e / z) ** 2 - s2)
            weight.append(np.full(rows.n, 1.0 / rows.n))
            per_run[str(r)]["rmse"] = {ax: float(v) for ax, v in zip("xyz", np.sqrt(np.mean(e**2, axis=0)))}
            per_run[str(r)]["temperature"] = [float(rows.temperature.min()), float(rows.temperature.max())]
    if len(need) >= min_runs:
        # few runs estimate the new-session variance poorly: a one-sided upper confidence bound (chi-square,
        # R - 1 dof) on all of it, s^2 + tau^2, not on the excess tau^2 alone (the pooled s^2 already holds
        # part of the between-run scatter, and its share was taken as exact)
        tau = session_variance_bound(np.concatenate(need), np.concatenate(weight), s2, len(need), level)
        return TransferEstimate(tau, "leave_one_run_out", per_run)
    usable = len(need)
    # residuals as a new session would see them: without the terms bound to training runs (a run offset would
    # otherwise take the run-to-run change out of the residual means)
    view = dataclasses.replace(train, run=new_session_runs(fit.model, train.run))
    rec = None if series is None else (dataclasses.replace(series[0], run=new_session_runs(fit.model, series[0].run)),
                                       series[1])
    resid = fit.residuals(view, rec)            # within the recording where the model needs it
    means = np.array([resid[train.run == r].mean(axis=0) for r in runs])
    tau = means.max(axis=0) - means.min(axis=0)
    bound = ", ".join(t.name for t in fit.model.terms if t.bound_runs())
    warning = few_runs_warning(len(runs), usable, min_runs, f"{' / '.join(f'{v:.3g}' for v in tau)} uT (x / y / z)",
                               f", taken without the model's {bound} (a new session is calibrated without them)"
                               if bound else "")
    return TransferEstimate(tau, "largest_offset_change", per_run, warning)


def few_runs_warning(n_runs: int, usable: int, min_runs: int, change: str, detail: str = "") -> str:
    """The warning when fewer than ``min_runs`` training runs are usable for leave-one-run-out: the intervals for
    new sessions are widened by the largest run-to-run change of the mean residual (``change``, formatted)."""
    return (f"The training data hold {n_runs} run(s) ({usable} usable for leave-one-run-out; at least {min_runs} are "
            f"needed), so the transfer (between-session) uncertainty cannot be estimated. The intervals for new "
            f"sessions are widened by the largest run-to-run change of the mean residual, {change}"
            + (" -- zero with one run: they hold no between-session term at all" if n_runs < 2 else "")
            + detail + ". Record at least 3 sessions to estimate it.")
