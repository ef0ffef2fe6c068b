r"""Many sensors at once: the physics fit, its covariance and the analytic uncertainty, vmapped over sensors.

A fleet is a stack of recordings padded to one length with a row mask (:class:`FleetData`).
Every per-sensor computation is the single-sensor one with the padded rows given weight 0, so
one compiled program serves the whole fleet (``vmap`` over a batch of ``batch_size`` sensors, the
batches run one after another with the same shapes -- rows padded to a multiple of :data:`ROW_BUCKET` --
so memory is bounded by the batch and any number of sensors reuses one compilation):

* the Levenberg-Marquardt fit of :func:`~bayesmag._src.core.fit.levenberg_marquardt` on the residuals
  :math:`w \odot (y - f(\theta; x))` (padded rows :math:`w = 0` change neither the cost nor any step);
* the covariance :math:`s^2 (J^TJ)^{-1}`, :math:`s^2 = \mathrm{RSS}/(n_i - p)` ("white"), or that times
  :math:`(1+\rho_1)/(1-\rho_1)` ("ar1", lag-1 autocorrelation within runs), as
  :func:`~bayesmag._src.core.fit.covariance`; the rank check of :func:`~bayesmag._src.core.fit.unidentifiable`
  (smallest relative singular value of the column-scaled Jacobian);
* the exact ("analytic") physics uncertainty of :func:`~bayesmag._src.core.physics_uq.physics_uncertainty`
  for models linear in their parameters: with Gauss-Hermite input-noise nodes :math:`\epsilon_q`
  (weights :math:`w_q`), :math:`\phi_q = \phi(x+\epsilon_q)`, :math:`m = \sum_q w_q\phi_q`,
  :math:`d_q = \phi_q - m`, :math:`C = \sum_q w_q d_q d_q^T`: mean :math:`m^T\hat\theta`, aleatoric
  :math:`\langle C, \hat\theta\hat\theta^T + \Sigma_\theta\rangle`, epistemic
  :math:`\sqrt{(m^T\Sigma_\theta m + \phi_0^T\Sigma_\theta\phi_0)/2}`.

``tests/test_fleet.py`` checks every sensor against :func:`~bayesmag.fit_physics` and
:func:`~bayesmag.physics_uncertainty` run one sensor at a time.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from bayesmag._src.core.data import CalibrationData
from bayesmag._src.core.fit import RANK_RTOL, RESULTS, levenberg_marquardt
from bayesmag._src.core.physics import Inputs, PhysicsModel, centred

__all__ = ["FleetData", "FleetFit", "FleetUQ", "fit_fleet", "fleet_uncertainty", "fleet_input_noise",
           "fleet_predict", "robust_z"]


@dataclasses.dataclass(frozen=True)
class FleetData:
    """Recordings of ``N`` sensors padded to ``n`` rows: arrays ``(N, n, ...)``, ``mask`` (N, n) true on real rows.

    Example:
      >>> from bayesmag._src.core.simulate import simulate
      >>> f = FleetData.from_recordings([simulate(30, seed=s) for s in range(2)] + [simulate(20, seed=2)])
      >>> f.b_meas.shape, f.n_rows.tolist()
      ((3, 30, 3), [30, 30, 20])
    """

    ids: tuple[str, ...]
    b_meas: np.ndarray
    temperature: np.ndarray
    time: np.ndarray
    run: np.ndarray
    b_ref: np.ndarray
    mask: np.ndarray

    @classmethod
    def from_recordings(cls, recordings: Sequence[CalibrationData], ids: Sequence[str] | None = None,
                        *, pad_to: int | None = None) -> "FleetData":
        """Stack recordings (each with a reference), zero-padded at the end to the longest (or ``pad_to``)."""
        recs = list(recordings)
        if not recs:
            raise ValueError("a fleet needs at least one recording.")
        ids = tuple(str(i) for i in (ids if ids is not None else range(len(recs))))
        if len(ids) != len(recs):
            raise ValueError(f"{len(ids)} ids for {len(recs)} recordings.")
        n = max(r.n for r in recs) if pad_to is None else int(pad_to)
        N = len(recs)
        b, t, tm, ref = np.zeros((N, n, 3)), np.zeros((N, n)), np.zeros((N, n)), np.zeros((N, n, 3))
        run = np.zeros((N, n), np.int64)
        mask = np.zeros((N, n), bool)
        for i, r in enumerate(recs):
            if r.b_ref is None:
                raise ValueError(f"sensor {ids[i]}: the recording has no reference columns (bx_ref, by_ref, bz_ref).")
            k = r.n
            if k > n:
                raise ValueError(f"sensor {ids[i]} has {k} rows, more than pad_to = {n}.")
            b[i, :k], t[i, :k], tm[i, :k], ref[i, :k], run[i, :k] = r.b_meas, r.temperature, r.time, r.b_ref, r.run
            run[i, k:] = r.run[-1] if k else 0
            mask[i, :k] = True
        return cls(ids, b, t, tm, run, ref, mask)

    @property
    def n_sensors(self) -> int:
        return len(self.ids)

    @property
    def n_rows(self) -> np.ndarray:
        return self.mask.sum(axis=1)

    def sensor(self, i: int) -> CalibrationData:
        """Sensor ``i``'s recording without padding."""
        k = int(self.n_rows[i])
        return CalibrationData(self.b_meas[i, :k], self.temperature[i, :k], self.b_ref[i, :k], self.time[i, :k],
                               self.run[i, :k], source=f"fleet sensor {self.ids[i]}")

    def inputs(self) -> Inputs:
        return Inputs(jnp.asarray(self.b_meas), jnp.asarray(self.temperature), jnp.asarray(self.time),
                      jnp.asarray(self.run))


@dataclasses.dataclass(frozen=True)
class FleetFit:
    """Per-sensor physics fits: ``theta`` (N, 3, p), ``cov`` (N, 3, p, p), ``s2``/``rmse``/``rho1``/``sv_ratio``/
    ``result``/``n_steps`` (N, 3), ``n`` (N,). ``result`` indexes :data:`~bayesmag._src.core.fit.RESULTS`."""

    model: PhysicsModel
    theta: np.ndarray
    cov: np.ndarray
    s2: np.ndarray
    rmse: np.ndarray
    rho1: np.ndarray
    sv_ratio: np.ndarray
    result: np.ndarray
    n_steps: np.ndarray
    n: np.ndarray
    covariance_method: str = "white"

    @property
    def converged(self) -> np.ndarray:
        """(N,) true where every axis converged."""
        return (self.result == RESULTS.index("converged")).all(axis=1)

    @property
    def identifiable(self) -> np.ndarray:
        """(N,) true where the data inform every parameter on every axis: no rank deficiency, and a finite,
        positive definite covariance (a near-singular ``J^T J`` inverted in the batch gave a negative eigenvalue,
        a condition number of 5e300 and offsets of 1600 uT at a singular-value ratio of 7.6e-7)."""
        cov = np.asarray(self.cov, np.float64)
        finite = np.isfinite(cov).all(axis=(-2, -1))
        cov = np.where(finite[..., None, None], cov, 0.0)
        dg = np.diagonal(cov, axis1=-2, axis2=-1)
        d = np.sqrt(np.where(dg > 0, dg, 1.0))
        corr = cov / (d[..., :, None] * d[..., None, :])
        k = np.arange(dg.shape[-1])
        corr[..., k, k] = np.where(dg == 0, 1.0, corr[..., k, k])     # s2 = 0 (noise-free rows): no evidence
        pd = finite & (np.linalg.eigvalsh(corr).min(axis=-1) > 0)
        return ((self.sv_ratio >= RANK_RTOL) & pd).all(axis=1)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diagonal(self.cov, axis1=-2, axis2=-1), 0, None))


class FleetUQ:
    """Per-row physics mean and uncertainty parts of every sensor, each (N, n, 3) (padded rows: zeros)."""

    def __init__(self, mean, aleatoric, epistemic):
        self.mean, self.aleatoric, self.epistemic = mean, aleatoric, epistemic


#: Rows are padded to a multiple of this, so fleets of similar lengths share one compiled program.
ROW_BUCKET = 256


def _padded_rows(n: int) -> int:
    return -(-int(n) // ROW_BUCKET) * ROW_BUCKET


def _pad_rows(fleet: "FleetData") -> "FleetData":
    n = fleet.mask.shape[1]
    extra = _padded_rows(n) - n
    if not extra:
        return fleet

    def pad(a, edge=False):
        w = [(0, 0), (0, extra)] + [(0, 0)] * (a.ndim - 2)
        return np.pad(a, w, mode="edge") if edge else np.pad(a, w)
    return FleetData(fleet.ids, pad(fleet.b_meas), pad(fleet.temperature), pad(fleet.time), pad(fleet.run, True),
                     pad(fleet.b_ref), pad(fleet.mask))


def _batched(fn, arrays, batch_size: int):
    """``fn`` (jitted, vmapped over its leading axis) on consecutive batches of ``batch_size`` sensors.

    Every call has the same shapes (the last batch is filled with copies of sensor 0, dropped after), so one
    compiled program serves any number of sensors; memory is bounded by the batch.
    """
    n = arrays[0].shape[0]
    b = max(1, min(int(batch_size), n))
    outs = []
    for lo in range(0, n, b):
        chunk = [a[lo:lo + b] for a in arrays]
        k = chunk[0].shape[0]
        if k < b:
            chunk = [np.concatenate([c, np.repeat(c[:1], b - k, axis=0)]) for c in chunk]
        outs.append(jax.tree_util.tree_map(lambda a, k=k: a[:k], fn(*map(jnp.asarray, chunk))))
    return [np.concatenate([np.asarray(o[j]) for o in outs]) for j in range(len(outs[0]))]


def _scaled_inverse(A):
    """Inverse via the correlation-scaled matrix (as fit.covariance)."""
    d = jnp.sqrt(jnp.clip(jnp.diag(A), 1e-300, None))
    As = A / jnp.outer(d, d)
    return jnp.linalg.inv(As) / jnp.outer(d, d)    # singular: the sensor is reported unidentifiable


def _centred(model: PhysicsModel, f: "FleetData") -> tuple[PhysicsModel, np.ndarray]:
    """:func:`~bayesmag._src.core.physics.centred` for the padded fleet: the model at T0 = 0 and T - T0."""
    model_c, inputs = centred(model, Inputs(f.b_meas, f.temperature, f.time, f.run))
    return model_c, np.asarray(inputs.t)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _fit_jit(model: PhysicsModel, method: str, th0, b, t, time, run, y, w):
    p = model.n_params

    def one_sensor(th0_, b_, t_, time_, run_, y_, w_):
        inputs = Inputs(b_, t_, time_, run_)
        n = w_.sum()

        def one_axis(th, yy):
            sol = levenberg_marquardt(lambda q: w_ * (yy - model.predict(q, inputs)), th)
            J = jax.jacfwd(model.predict)(sol.theta, inputs) * w_[:, None]        # (n, p), padded rows 0
            r = w_ * (yy - model.predict(sol.theta, inputs))
            s2 = r @ r / (n - p)
            cov = s2 * _scaled_inverse(J.T @ J)
            rc = w_ * (r - r.sum() / n)
            same = (w_[1:] * w_[:-1]) * (run_[1:] == run_[:-1])
            den = rc @ rc
            rho = jnp.where(den > 0, jnp.sum(rc[1:] * rc[:-1] * same) / jnp.where(den > 0, den, 1.0)
                            * n / jnp.maximum(same.sum(), 1.0), 0.0)
            rho = jnp.where(n < 3, 0.0, rho)
            if method == "ar1":
                rp = jnp.maximum(rho, 0.0)
                cov = cov * (1 + rp) / (1 - jnp.minimum(rp, 0.99))
            norm = jnp.linalg.norm(J, axis=0)
            sv = jnp.linalg.svd(J / jnp.where(norm > 0, norm, 1.0), compute_uv=False)
            ratio = jnp.where(jnp.any(norm <= jnp.finfo(J.dtype).tiny), 0.0, sv.min() / sv.max())
            rmse = jnp.sqrt(r @ r / n)
            return sol.theta, cov, s2, rmse, rho, ratio, sol.result, sol.n_steps

        return jax.vmap(one_axis, in_axes=(0, 1))(th0_, y_)

    return jax.vmap(one_sensor)(th0, b, t, time, run, y, w)


def fit_fleet(fleet: FleetData, model: PhysicsModel | None = None, *, covariance_method: str = "white",
              batch_size: int = 64) -> FleetFit:
    """Fit ``model`` to every sensor of ``fleet`` (each axis separately) in one compiled, batched program.

    Equals :func:`~bayesmag.fit_physics` on each sensor's unpadded recording (``covariance_method``
    ``"white"`` or ``"ar1"``). ``batch_size`` sensors are vmapped at a time (memory ~ batch x rows x p).
    Sensors that did not converge or whose data cannot inform every parameter are reported
    (:attr:`FleetFit.converged`, :attr:`FleetFit.identifiable`), not raised.
    """
    if covariance_method not in ("white", "ar1"):
        raise ValueError(f"fleet covariance method {covariance_method!r} is not supported; use 'white' or 'ar1' "
                         f"(Newey-West needs a per-sensor lag choice: fit that sensor alone with fit_physics).")
    model = model or PhysicsModel.paper()
    n = fleet.n_rows
    if np.any(n <= model.n_params):
        bad = [fleet.ids[i] for i in np.flatnonzero(n <= model.n_params)][:5]
        raise ValueError(f"sensor(s) {bad} have <= {model.n_params} rows, too few to fit {model.n_params} parameters "
                         f"per axis.")
    th0 = np.broadcast_to(model.init_params_all().astype(np.float64), (fleet.n_sensors, 3, model.n_params))
    f = _pad_rows(fleet)
    model_c, t_c = _centred(model, f)
    theta, cov, s2, rmse, rho, ratio, result, steps = _batched(
        functools.partial(_fit_jit, model_c, covariance_method),
        [th0, f.b_meas, t_c, f.time, f.run, f.b_ref, f.mask.astype(np.float64)], batch_size)
    return FleetFit(model, theta, cov, s2, rmse, rho, ratio, result, steps, n, covariance_method)


@functools.partial(jax.jit, static_argnums=0)
def _predict_jit(model: PhysicsModel, theta, b, t, time, run):
    def one_sensor(th, b_, t_, time_, run_):
        inputs = Inputs(b_, t_, time_, run_)
        return (jax.vmap(lambda q: model.predict(q, inputs), out_axes=-1)(th),)
    return jax.vmap(one_sensor)(theta, b, t, time, run)


def fleet_predict(fit: FleetFit, fleet: FleetData, *, batch_size: int = 64) -> np.ndarray:
    """The plug-in physics prediction :math:`f(x; \\hat\\theta_i)` of every row of every sensor, ``(N, n, 3)``
    (padded rows 0): :meth:`~bayesmag.PhysicsFit.predict` of each sensor, one compiled program for the fleet."""
    f = _pad_rows(fleet)
    n = fleet.mask.shape[1]
    model_c, t_c = _centred(fit.model, f)
    (pred,) = _batched(functools.partial(_predict_jit, model_c),
                       [fit.theta, f.b_meas, t_c, f.time, f.run], batch_size)
    return np.where(fleet.mask[..., None], pred[:, :n], 0.0)


def fleet_input_noise(fleet: FleetData) -> np.ndarray:
    """(N, 4, 4) diagonal ``Sigma_in`` per sensor, the estimator of
    :func:`~bayesmag._src.core.physics_uq.estimate_input_noise` (within-run second differences, 1.4826 MAD / sqrt 6)."""
    cols = np.concatenate([fleet.b_meas, fleet.temperature[..., None]], axis=-1)          # (N, n, 4)
    run, m = fleet.run, fleet.mask
    same = (run[:, 2:] == run[:, 1:-1]) & (run[:, 1:-1] == run[:, :-2]) & m[:, 2:] & m[:, 1:-1] & m[:, :-2]
    d2 = cols[:, 2:] - 2 * cols[:, 1:-1] + cols[:, :-2]
    d2 = np.where(same[..., None], d2, np.nan)
    med = np.nanmedian(d2, axis=1, keepdims=True)
    sd = 1.4826 * np.nanmedian(np.abs(d2 - med), axis=1) / np.sqrt(6.0)                  # (N, 4)
    return np.einsum("ni,ij->nij", sd**2, np.eye(4))


def _sqrt_psd_batched(cov: np.ndarray) -> np.ndarray:
    out = np.empty_like(cov)
    for i, c in enumerate(cov):               # 4x4 each: a loop over sensors costs microseconds
        try:
            out[i] = np.linalg.cholesky(c)
        except np.linalg.LinAlgError:
            w, V = np.linalg.eigh(c)
            out[i] = V * np.sqrt(np.clip(w, 0, None))
    return out


@functools.partial(jax.jit, static_argnums=0)
def _uq_jit(model: PhysicsModel, z, wq, theta, cov, L, b, t, time, run):
    def one_sensor(th, cv, L_, b_, t_, time_, run_):
        inputs = Inputs(b_, t_, time_, run_)
        eps = z @ L_.T                                                   # (q, 4)
        pert = Inputs(b_[:, None, :] + eps[None, :, :3], t_[:, None] + eps[None, :, 3],
                      jnp.broadcast_to(time_[:, None], (t_.shape[0], z.shape[0])),
                      jnp.broadcast_to(run_[:, None], (t_.shape[0], z.shape[0])))
        phi = model.features(pert)                                       # (n, q, p)
        m = jnp.einsum("q,nqa->na", wq, phi)
        d = phi - m[:, None, :]
        C = jnp.einsum("nqa,nqb->nab", d * wq[None, :, None], d)         # input-noise covariance of phi, once
        phi0 = model.features(inputs)                                    # (n, p)

        def one_axis(th_a, cv_a):
            alea = jnp.einsum("nab,ab->n", C, jnp.outer(th_a, th_a) + cv_a)
            var_mc = jnp.sum((m @ cv_a) * m, axis=-1)
            var_jac = jnp.sum((phi0 @ cv_a) * phi0, axis=-1)
            return m @ th_a, alea, (var_mc + var_jac) / 2

        return jax.vmap(one_axis, out_axes=-1)(th, cv)                  # each (n, 3)

    return jax.vmap(one_sensor)(theta, cov, L, b, t, time, run)


def fleet_uncertainty(fit: FleetFit, fleet: FleetData, sigma_in: np.ndarray, *, batch_size: int = 8,
                      quad_nodes: int | None = None) -> FleetUQ:
    """Exact physics mean and uncertainty (``method="analytic"`` of :func:`~bayesmag.physics_uncertainty`)
    for every row of every sensor of ``fleet``, under each sensor's fit and ``sigma_in`` (N, 4, 4).

    Needs a model linear in its parameters and polynomial in the inputs; nodes per input:
    ``degree + 1`` for diagonal ``sigma_in`` (exact), ``2 degree + 1`` otherwise.
    """
    model = fit.model
    if not model.is_linear or model.degree is None:
        raise ValueError("the fleet's uncertainty is the analytic method: it needs a model linear in its parameters "
                         "and polynomial in the inputs (no input transforms such as thermal_lag).")
    sigma_in = np.broadcast_to(np.asarray(sigma_in, np.float64), (fleet.n_sensors, 4, 4))
    diagonal = np.allclose(sigma_in, sigma_in * np.eye(4))
    nodes = quad_nodes or (model.degree + 1 if diagonal else 2 * model.degree + 1)
    from bayesmag._src.core.physics_uq import gauss_hermite_normal
    z, wq = gauss_hermite_normal(nodes, np.eye(4))
    f = _pad_rows(fleet)
    n = fleet.mask.shape[1]
    model_c, t_c = _centred(model, f)
    mean, alea, epi = (o[:, :n] for o in _batched(
        functools.partial(_uq_jit, model_c, jnp.asarray(z), jnp.asarray(wq)),
        [fit.theta, fit.cov, _sqrt_psd_batched(np.array(sigma_in)), f.b_meas, t_c, f.time, f.run],
        batch_size))
    m = fleet.mask[..., None]
    return FleetUQ(np.where(m, mean, 0.0), np.where(m, np.sqrt(np.clip(alea, 0, None)), 0.0),
                   np.where(m, np.sqrt(np.clip(epi, 0, None)), 0.0))


def robust_z(x: np.ndarray, axis: int = 0) -> np.ndarray:
    r"""Robust z-scores :math:`(x - \mathrm{median}) / (1.4826\,\mathrm{MAD})` along ``axis`` (0 where MAD = 0
    and x equals the median; +-inf where MAD = 0 and it does not).

    Example:
      >>> robust_z(np.array([1.0, 2.0, 3.0, 4.0, 100.0])).round(2).tolist()
      [-1.35, -0.67, 0.0, 0.67, 65.41]
    """
    x = np.asarray(x, np.float64)
    med = np.median(x, axis=axis, keepdims=True)
    mad = 1.4826 * np.median(np.abs(x - med), axis=axis, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (x - med) / mad
    return np.where(x == med, 0.0, z)
