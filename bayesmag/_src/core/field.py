r"""Field calibration: the thermo-affine sensor model fitted against a measurement model, with honest uncertainty.

Model (the same one as the vector calibration), reading u (uT), :math:`T_c = T - T_0`:

.. math::  B = M(T)\,u + o(T),\quad M = S + K_s T_c,\quad o = O + K_o T_c .

The residual comes from a :class:`~bayesmag._src.core.measurement.MeasurementModel` (vector,
scalar, constant). For a magnitude model the gauge is M(T) upper-triangular (S and Ks
upper-triangular: 18 parameters with temperature terms, 9 without), plus ``trace(S) = 3`` when the
field magnitude is itself fitted.

Estimate: the posterior mode under weak Gaussian priors (:class:`FieldPrior`; they only matter
where the motion leaves a direction unconstrained) by Levenberg-Marquardt, then the Laplace
posterior :math:`\Sigma = (J^T J / (s^2 c) + \mathrm{diag}(\tau^{-2}))^{-1}` with :math:`s^2` the
residual variance and :math:`c = (1+\rho_1)/(1-\rho_1)` for AR(1) residuals (``covariance="ar1"``). A scalar
reference with its own noise (``Scalar(ref_sd)``) adds a refit weighted by each row's whole sd and the sandwich
covariance (:func:`fit_field`, :func:`_sandwich`).

Gauge-free quantities compared between any two fits (:func:`invariants`): :math:`Q = S^T S`,
:math:`dQ/dT = K_s^T S + S^T K_s`, :math:`d = S^{-1} O`, :math:`dd/dT = S^{-1}(K_o - K_s S^{-1} O)`
at :math:`T_0`. An invariant is *identified* by a recording when the data shrink its prior standard
deviation by at least a factor of 2 (:data:`IDENTIFIED_RATIO`); otherwise its answer is the prior's.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

from bayesmag._src.core.fit import lag1_autocorrelation, levenberg_marquardt
from bayesmag._src.core.measurement import Constant, MeasurementModel, Scalar, Vector

__all__ = ["FieldModel", "FieldPrior", "FieldFit", "fit_field", "invariants", "INVARIANT_NAMES",
           "IDENTIFIED_RATIO", "wrap_deg", "direction_coverage", "gauge_form", "heading", "heading_with_uncertainty",
           "gaussian_scores", "field_target", "heading_flagged", "field_scale_check", "supported_field", "gain_check",
           "log_gain_sd", "judge_gains"]

AXES = ("x", "y", "z")
#: posterior sd / prior sd above which an invariant counts as not identified by the recording
IDENTIFIED_RATIO = 0.5
INVARIANT_NAMES = tuple(
    [f"Q_{AXES[i]}{AXES[j]}" for i in range(3) for j in range(i, 3)]
    + [f"dQ/dT_{AXES[i]}{AXES[j]}" for i in range(3) for j in range(i, 3)]
    + [f"d_{a}" for a in AXES] + [f"dd/dT_{a}" for a in AXES])
_IU = np.triu_indices(3)


@dataclasses.dataclass(frozen=True)
class FieldPrior:
    """Standard deviations of the weak Gaussian priors (means: S = I, everything else 0; F: mean |u|).

    Defaults are wide for a magnetometer on a vehicle: gains +-25 %, cross terms 0.1, hard iron
    100 uT, thermal gain 1 %/C, thermal offset 1 uT/C.
    """

    s_diag: float = 0.25
    s_off: float = 0.1
    ks: float = 0.01
    o: float = 100.0
    ko: float = 1.0
    f_rel: float = 0.5


@dataclasses.dataclass(frozen=True)
class FieldModel:
    """Parameter layout of the thermo-affine model under a measurement model's gauge.

    Example:
      >>> m = FieldModel(Scalar(), t0=20.0)
      >>> m.n_params, m.param_names[:4]
      (18, ('S_xx', 'S_xy', 'S_xz', 'S_yy'))
    """

    measurement: MeasurementModel
    t0: float = 0.0
    temperature: bool = True

    @property
    def mask(self) -> np.ndarray:
        return np.triu(np.ones((3, 3), bool)) if self.measurement.gauge == "upper" else np.ones((3, 3), bool)

    def _s_idx(self):
        idx = [(i, j) for i in range(3) for j in range(3) if self.mask[i, j]]
        if self.measurement.scale_gauge:
            idx.remove((2, 2))          # S_zz = 3 - S_xx - S_yy
        return idx

    def _k_idx(self):
        return [(i, j) for i in range(3) for j in range(3) if self.mask[i, j]]

    @property
    def param_names(self) -> tuple[str, ...]:
        n = [f"S_{AXES[i]}{AXES[j]}" for i, j in self._s_idx()]
        if self.temperature:
            n += [f"Ks_{AXES[i]}{AXES[j]}" for i, j in self._k_idx()]
        n += [f"O_{a}" for a in AXES]
        if self.temperature:
            n += [f"Ko_{a}" for a in AXES]
        return tuple(n) + self.measurement.extra_names()

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def unpack(self, theta):
        """``(S, Ks, O, Ko, extra)`` from the flat parameter vector."""
        si, ki = self._s_idx(), self._k_idx()
        k = 0
        S = jnp.zeros((3, 3), theta.dtype)
        for (i, j) in si:
            S = S.at[i, j].set(theta[k]); k += 1
        if self.measurement.scale_gauge:
            S = S.at[2, 2].set(3.0 - S[0, 0] - S[1, 1])
        Ks = jnp.zeros((3, 3), theta.dtype)
        if self.temperature:
            for (i, j) in ki:
                Ks = Ks.at[i, j].set(theta[k]); k += 1
        O = theta[k:k + 3]; k += 3
        Ko = jnp.zeros(3, theta.dtype)
        if self.temperature:
            Ko = theta[k:k + 3]; k += 3
        return S, Ks, O, Ko, theta[k:]

    def pack(self, S, Ks, O, Ko, extra=()) -> np.ndarray:
        S, Ks = np.asarray(S), np.asarray(Ks)
        v = [S[i, j] for i, j in self._s_idx()]
        if self.temperature:
            v += [Ks[i, j] for i, j in self._k_idx()]
        v += list(np.asarray(O))
        if self.temperature:
            v += list(np.asarray(Ko))
        return np.asarray(v + list(extra), dtype=np.float64)

    def calibrate(self, theta, u, t):
        """Calibrated field (n, 3) in the gauge frame."""
        S, Ks, O, Ko, _ = self.unpack(theta)
        tc = (t - self.t0)[:, None]
        return u @ S.T + tc * (u @ Ks.T) + O + tc * Ko

    def residual(self, theta, u, t, target, kappa2=0.0):
        r"""Residuals in reading units: a magnitude residual is divided by :math:`\sqrt{g^2 + \kappa^2}`, g its
        noise gain (:meth:`gain`) and :math:`\kappa = \sigma_{ref}/\sigma` the reference's own noise in units of
        the reading noise (0 for an exact reference): the residual's whole sd in reading units."""
        _, _, _, _, extra = self.unpack(theta)
        r = self.measurement.residual(self.calibrate(theta, u, t), target, extra)
        return r if self.measurement.per_row > 1 else r / jnp.sqrt(self.gain(theta, u, t) ** 2 + kappa2)

    def gain(self, theta, u, t):
        r"""How reading noise reaches the magnitude, :math:`g = \lVert M(T)^T \hat B\rVert` (n,).

        Least squares on raw magnitude residuals would shrink M where the motion leaves a direction
        weak (smaller M, smaller noise, smaller cost: the errors-in-variables pull); dividing by g
        removes that pull. For a vector model g = 1.
        """
        if self.measurement.per_row > 1:
            return jnp.ones(u.shape[:1])
        S, Ks, _, _, _ = self.unpack(theta)
        B = self.calibrate(theta, u, t)
        nb = B / jnp.linalg.norm(B, axis=1, keepdims=True)
        tc = (t - self.t0)[:, None]
        g = nb @ S + tc * (nb @ Ks)
        return jnp.linalg.norm(g, axis=1)

    def prior(self, p: FieldPrior, u) -> tuple[np.ndarray, np.ndarray]:
        """Prior means and standard deviations (p,)."""
        mu, sd = [], []
        for name in self.param_names[:self.n_params - self.measurement.n_extra]:
            kind, ax = name.split("_")
            if kind == "S":
                mu.append(1.0 if ax[0] == ax[1] else 0.0); sd.append(p.s_diag if ax[0] == ax[1] else p.s_off)
            elif kind == "Ks":
                mu.append(0.0); sd.append(p.ks)
            elif kind == "O":
                mu.append(0.0); sd.append(p.o)
            elif kind == "Ko":
                mu.append(0.0); sd.append(p.ko)
        if self.measurement.n_extra:
            f = float(np.mean(np.linalg.norm(u, axis=1)))
            mu.append(f); sd.append(p.f_rel * f)
        return np.asarray(mu), np.asarray(sd)


def gauge_form(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, U)`` with ``M = R U``, R a rotation and U upper-triangular with a positive diagonal (QR).

    Example:
      >>> R, U = gauge_form(np.diag([2.0, 1.0, 1.0]))
      >>> np.allclose(R, np.eye(3)), np.allclose(U, np.diag([2, 1, 1]))
      (True, True)
    """
    Q, U = np.linalg.qr(np.asarray(M, dtype=np.float64))
    s = np.sign(np.diag(U))
    s[s == 0] = 1
    return Q * s, U * s[:, None]


def invariants(S, Ks, O, Ko):
    """The 18 gauge-free numbers (:data:`INVARIANT_NAMES`): Q, dQ/dT (upper entries), d, dd/dT at T0."""
    Q = S.T @ S
    dQ = Ks.T @ S + S.T @ Ks
    Si = jnp.linalg.inv(S)
    d = Si @ O
    dd = Si @ (Ko - Ks @ d)
    return jnp.concatenate([Q[_IU], dQ[_IU], d, dd])


def field_target(measurement: MeasurementModel, b_ref=None, f_ref=None, n: int | None = None) -> np.ndarray:
    """What the measurement model compares with: the vector (n, 3), a magnitude (n,), or the field F (n,).

    A vector reference given to a magnitude model is withheld down to its magnitude.
    """
    if isinstance(measurement, Vector):
        if b_ref is None:
            raise ValueError("the vector measurement model needs the reference field columns bx_ref, by_ref, bz_ref.")
        return np.asarray(b_ref, np.float64)
    if isinstance(measurement, Scalar):
        if f_ref is not None:
            return np.asarray(f_ref, np.float64).reshape(-1)
        if b_ref is None:
            raise ValueError("the scalar measurement model needs a reference magnitude column f_ref "
                             "(or reference field columns, whose magnitude is used).")
        return np.linalg.norm(np.asarray(b_ref, np.float64), axis=1)
    m = n if n is not None else len(b_ref if b_ref is not None else f_ref)
    f = measurement.field if measurement.field is not None else 1.0
    return np.full(m, float(f))


# --------------------------------------------------------------------------- the fit


def _static(model: FieldModel) -> FieldModel:
    """The model with T0 = 0, for the jitted functions (called with T - T0): the model is a static argument,
    so a T0 inside it would compile them again for every recording."""
    return dataclasses.replace(model, t0=0.0)


@functools.partial(jax.jit, static_argnums=(0,))
def _solve(model: FieldModel, theta0, u, t, target, mu, w, keep, kappa2):
    def r(th):
        return jnp.concatenate([model.residual(th, u, t, target, kappa2) * keep, w * (th - mu)])
    return levenberg_marquardt(r, theta0, max_steps=2000)


@functools.partial(jax.jit, static_argnums=(0,))
def _jac_resid(model: FieldModel, theta, u, t, target, keep, kappa2):
    f = lambda th: model.residual(th, u, t, target, kappa2) * keep
    return f(theta), jax.jacfwd(f)(theta)


@functools.partial(jax.jit, static_argnums=(0,))
def _hess(model: FieldModel, theta, u, t, target, keep, kappa2):
    return jax.hessian(lambda th: 0.5 * jnp.sum((model.residual(th, u, t, target, kappa2) * keep) ** 2))(theta)


def _sandwich(H, J, r, sig2, infl, sd, fallback):
    r"""Covariance of the estimate from the total-sd weight: :math:`P^{-1}(B + \Lambda)P^{-1}`, P = H / sig2 + Lambda.

    That cost is an estimating equation, not a likelihood: along a direction the motion left weak its expected
    curvature is zero (the flat expected cost that removes the pull), but its score still varies from row to row
    (which noise source dominates a row changes along that direction), so the Laplace P^-1 (curvature only)
    is far too narrow there. B = infl * sum_i s_i s_i^T, s_i = rho_i grad rho_i / sig2, is the score's variance
    (infl: AR(1)); Lambda the prior precision. Where curvature and score variance agree (a likelihood,
    e.g. every direction visited) it equals P^-1. ``fallback`` (the Gauss-Newton Laplace) if P is not positive.
    """
    Lam = np.diag(1.0 / np.asarray(sd) ** 2)
    P = np.asarray(H) / sig2 + Lam
    P = 0.5 * (P + P.T)
    if not (np.all(np.isfinite(P)) and np.linalg.eigvalsh(P)[0] > 0):
        return fallback
    Pi = np.linalg.inv(P)
    sc = np.asarray(J) * np.asarray(r)[:, None] / sig2
    return Pi @ (infl * sc.T @ sc + Lam) @ Pi


def _init(model: FieldModel, u, t, target) -> np.ndarray:
    """Algebraic start: |M u + o|^2 = F^2 solved linearly for (Q, M^T o, |o|^2) at constant temperature."""
    meas = model.measurement
    p = model.n_params
    if isinstance(meas, Vector):
        X = np.column_stack([u, np.ones(len(u))])
        coef, *_ = np.linalg.lstsq(X, target, rcond=None)
        S, O = coef[:3].T, coef[3]
        return model.pack(S, np.zeros((3, 3)), O, np.zeros(3))
    f = target if meas.n_extra == 0 else np.ones(len(u))
    x, y, z = u.T
    D = np.column_stack([x * x, 2 * x * y, 2 * x * z, y * y, 2 * y * z, z * z, 2 * x, 2 * y, 2 * z, np.ones(len(u))])
    try:                                                 # a weak ridge (towards a sphere) for degenerate motions
        cn = np.linalg.norm(D, axis=0)
        lam = np.concatenate([1e-3 * cn[:6], 1e-6 * cn[6:]])
        v_prior = np.array([1, 0, 0, 1, 0, 1, 0, 0, 0, 0], float) * np.mean(f**2) / np.mean(np.sum(u * u, axis=1))
        v, *_ = np.linalg.lstsq(np.vstack([D, np.diag(lam)]), np.concatenate([f**2, lam * v_prior]), rcond=None)
        Q = np.array([[v[0], v[1], v[2]], [v[1], v[3], v[4]], [v[2], v[4], v[5]]])
        U = np.linalg.cholesky(Q).T                      # Q = U^T U, U upper
        O = np.linalg.solve(U.T, v[6:9])
        if meas.n_extra:                                 # scale gauge: trace(S) = 3, F in those units
            k = 3.0 / np.trace(U)
            U, O = U * k, O * k
        ok = np.all(np.isfinite(U)) and np.all(np.isfinite(O))
    except np.linalg.LinAlgError:
        ok = False
    if not ok:
        U, O = np.eye(3), -np.mean(u, axis=0)
    extra = []
    if meas.n_extra:
        extra = [float(np.mean(np.linalg.norm(u @ U.T + O, axis=1)))]
    th = model.pack(U, np.zeros((3, 3)), O, np.zeros(3), extra)
    assert th.shape == (p,)
    return th


#: passes of (LM solve, noise level) at most, and the relative change of the noise level that ends them
_MAX_PASSES, _SIG_RTOL = 8, 1e-3
#: a refit from ``start`` (cross-validation folds: it only predicts) ends after one pass when its noise level is
#: within 1 % of the start's: the prior weights then differ by < 2 %, which moves the mode by a negligible amount
#: wherever the data dominate the prior (posterior sd <= 0.05 prior sd on the simulated campaigns)
_REFIT_SIG_RTOL = 1e-2
#: the reference-noise refit (``Scalar(ref_sd > 0)``) is kept only if every gain S_ii lies within this many prior sds
#: of 1 (the prior's 99.9 % range): beyond it the refit has reached the degenerate solution M -> 0
_GAIN_Z = 3.29


@dataclasses.dataclass(frozen=True)
class FieldFit:
    """A fitted field calibration: posterior mode, Laplace covariance and diagnostics."""

    model: FieldModel
    theta: np.ndarray
    cov: np.ndarray
    prior_mean: np.ndarray
    prior_sd: np.ndarray
    s2: float
    rho1: float
    inflation: float
    n: int
    converged: bool
    n_steps: int
    covariance_method: str
    coverage: dict
    notes: tuple[str, ...]
    kappa2: float = 0.0       # (reference noise sd / reading noise sd)^2 in the magnitude residual's weight
    weighting: str = "gain"   # "gain" (1/g) or "total" (1/sqrt(g^2 + kappa^2), the reference-noise refit); see fit_field

    @property
    def param_names(self):
        return self.model.param_names

    def __repr__(self) -> str:
        m = self.model
        return (f"FieldFit({m.measurement!r}, n={self.n}, {len(self.theta)} parameters, t0={m.t0:.4g} C, "
                f"temperature_terms={m.temperature}, noise sd={float(np.sqrt(self.s2)):.3g} uT, "
                f"converged={self.converged}, {len(self.notes)} note(s))")

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0, None))

    @property
    def corr(self) -> np.ndarray:
        s = self.std
        return self.cov / np.outer(s, s)

    def matrices(self, theta=None):
        """``(S, Ks, O, Ko, extra)`` as NumPy arrays (gauge frame)."""
        th = jnp.asarray(self.theta if theta is None else theta)
        return tuple(np.asarray(a) for a in self.model.unpack(th))

    def calibrate(self, u, t) -> np.ndarray:
        return np.asarray(self.model.calibrate(jnp.asarray(self.theta), jnp.asarray(u, jnp.float64),
                                               jnp.asarray(t, jnp.float64)))

    def invariants(self) -> dict:
        """Gauge-free quantities with posterior and prior standard deviations and an identified flag."""
        val, G = (np.asarray(x) for x in _invariants_jac(_static(self.model), jnp.asarray(self.theta)))
        cov = G @ self.cov @ G.T
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        prior_sd = np.sqrt(np.clip(np.diag(G @ np.diag(self.prior_sd**2) @ G.T), 0, None))
        ident = sd < IDENTIFIED_RATIO * np.maximum(prior_sd, 1e-300)
        why = np.where(ident, "", "posterior sd > %g x prior sd" % IDENTIFIED_RATIO).astype(object)
        thermal = np.array([n.startswith(("dQ/dT", "dd/dT")) for n in INVARIANT_NAMES])
        if not self.model.temperature:
            ident, why = ident & ~thermal, np.where(thermal, "no temperature terms fitted", why)
        elif self.coverage and self.coverage.get("bands_spread", 2) < 2:
            ident = ident & ~thermal
            why = np.where(thermal, "directions spread at fewer than two temperatures", why)
        if self.coverage and self.coverage.get("missing_directions"):
            # a planar (or narrower) set of field directions is a conic, not a quadric: Q and d are not determined
            ident = np.zeros_like(ident)
            why = np.where(why == "", "field directions did not span 3-D (see direction coverage)", why)
        return {"names": INVARIANT_NAMES, "value": val, "sd": sd, "cov": cov, "prior_sd": prior_sd,
                "identified": ident, "why": why}

    def magnitude(self, u, t) -> tuple[np.ndarray, np.ndarray]:
        """Predicted magnitude (n,) and its parameter (epistemic) standard deviation (n,)."""
        return _magnitude(_static(self.model), jnp.asarray(self.theta), jnp.asarray(self.cov),
                          jnp.asarray(u, jnp.float64), jnp.asarray(t, jnp.float64) - self.model.t0)

    def predict_magnitude(self, u, t) -> dict:
        """Predictive distribution of the reference magnitude: mean, epistemic, noise and total sd."""
        mean, epi = (np.asarray(a) for a in self.magnitude(u, t))
        g = np.asarray(self.model.gain(jnp.asarray(self.theta), jnp.asarray(u, jnp.float64), jnp.asarray(t, jnp.float64)))
        noise = math.sqrt(self.s2) * np.sqrt(g**2 + self.kappa2)
        return {"mean": mean, "epistemic": epi, "noise": noise, "total": np.sqrt(epi**2 + noise**2)}

    def to_json(self) -> dict:
        inv = self.invariants()
        return {
            "measurement": self.model.measurement.describe(), "t0": self.model.t0,
            "temperature_terms": self.model.temperature,
            "gauge": gauge_text(self.model.measurement),
            "param_names": list(self.param_names), "theta": self.theta.tolist(), "std": self.std.tolist(),
            "prior_sd": self.prior_sd.tolist(), "prior_mean": self.prior_mean.tolist(),
            "cov": np.asarray(self.cov).tolist(),
            "s2": self.s2, "rho1": self.rho1, "inflation": self.inflation, "n": self.n,
            "converged": self.converged, "n_steps": self.n_steps, "covariance": self.covariance_method,
            "reference_sd": self.model.measurement.reference_sd, "weighting": self.weighting, "kappa2": self.kappa2,
            "invariants": {n: {"value": float(v), "sd": float(s), "prior_sd": float(p), "identified": bool(i),
                               "why_not": str(w)}
                           for n, v, s, p, i, w in zip(inv["names"], inv["value"], inv["sd"], inv["prior_sd"],
                                                       inv["identified"], inv["why"])},
            "direction_coverage": self.coverage, "notes": list(self.notes),
        }

    @classmethod
    def from_json(cls, doc: dict) -> "FieldFit":
        """The fit :meth:`to_json` wrote (``field_params.json``), every array's shape checked against the model.

        Raises ``ValueError`` naming the key (a file written before ``cov`` was saved says to re-run).

        Example:
          >>> from bayesmag.simulate import simulate_field
          >>> c = simulate_field("dance", n=400, seed=0)
          >>> fit = fit_field(c.data.b_meas, c.data.temperature, c.f_ref, Scalar())
          >>> bool(np.allclose(FieldFit.from_json(fit.to_json()).calibrate(c.data.b_meas[:3], c.data.temperature[:3]),
          ...                  fit.calibrate(c.data.b_meas[:3], c.data.temperature[:3])))
          True
        """
        from bayesmag._src.core.measurement import measurement_from_spec
        if not isinstance(doc, dict):
            raise ValueError("a field calibration must be a JSON object (field_params.json)")
        missing = [k for k in ("measurement", "t0", "temperature_terms", "theta", "cov", "s2") if k not in doc]
        if missing:
            hint = (" (saved before bayesmag stored the covariance: re-run `bayesmag run` on the field config)"
                    if missing == ["cov"] else "")
            raise ValueError(f"field_params.json lacks {missing}{hint}")
        m = doc["measurement"]
        try:
            meas = measurement_from_spec(m["name"], m.get("field"), m.get("reference_sd", 0.0) or 0.0)
            model = FieldModel(meas, t0=float(doc["t0"]), temperature=bool(doc["temperature_terms"]))
            theta = np.asarray(doc["theta"], np.float64)
            cov = np.asarray(doc["cov"], np.float64)
            p = model.n_params
            prior_mean = np.asarray(doc.get("prior_mean", np.zeros(p)), np.float64)
            prior_sd = np.asarray(doc.get("prior_sd", np.ones(p)), np.float64)
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"field_params.json: measurement/t0/theta/cov are not readable ({e})") from None
        for key, a, shape in (("theta", theta, (p,)), ("cov", cov, (p, p)), ("prior_mean", prior_mean, (p,)),
                              ("prior_sd", prior_sd, (p,))):
            if a.shape != shape:
                raise ValueError(f"field_params.json: '{key}' must have shape {shape} for the {m['name']} model's "
                                 f"{p} parameters, got shape {a.shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"field_params.json: '{key}' holds NaN or inf at index "
                                 f"{np.argwhere(~np.isfinite(a))[0].tolist()}; the file is damaged")
        if not math.isfinite(model.t0):
            raise ValueError(f"field_params.json: 't0' = {doc['t0']!r} must be a finite temperature (C)")
        # what a fit can write: a symmetric positive semi-definite covariance, a positive noise variance, gains
        # of a sensor (the fit's prior is 1 +- 0.25) and offsets of a vehicle's field (prior sd 100 uT)
        scale = max(float(np.max(np.abs(cov))), 1e-300)
        if np.max(np.abs(cov - cov.T)) > 1e-8 * scale or np.linalg.eigvalsh(0.5 * (cov + cov.T))[0] < -1e-8 * scale:
            raise ValueError("field_params.json: 'cov' is not a symmetric positive semi-definite covariance; the "
                             "file was edited or is damaged")
        s2 = float(doc["s2"])
        if not (math.isfinite(s2) and s2 > 0):
            raise ValueError(f"field_params.json: 's2' = {doc['s2']!r} must be a positive noise variance (uT^2)")
        S, _, O, _, _ = (np.asarray(x) for x in model.unpack(jnp.asarray(theta)))
        if not (np.all(np.abs(np.diag(S)) < 100) and np.all(np.abs(np.diag(S)) > 1e-3) and np.all(np.abs(O) < 1e5)):
            raise ValueError(f"field_params.json: gains diag(S) = {np.round(np.diag(S), 4).tolist()} or offsets "
                             f"O = {np.round(O, 2).tolist()} uT are not a sensor's (|gain| in (0.001, 100), |O| < 1e5 "
                             f"uT); the file was edited or is damaged")
        return cls(model, theta, cov, prior_mean, prior_sd, s2, float(doc.get("rho1", 0.0)),
                   float(doc.get("inflation", 1.0)), int(doc.get("n", 0)), bool(doc.get("converged", True)),
                   int(doc.get("n_steps", 0)), str(doc.get("covariance", "white")),
                   dict(doc.get("direction_coverage") or {}), tuple(doc.get("notes", ())),
                   float(doc.get("kappa2", 0.0)), str(doc.get("weighting", "gain")))


@functools.partial(jax.jit, static_argnums=(0,))
def _invariants_jac(model: FieldModel, theta):
    g = lambda th: invariants(*model.unpack(th)[:4])
    return g(theta), jax.jacfwd(g)(theta)


@functools.partial(jax.jit, static_argnums=(0,))
def _magnitude(model: FieldModel, theta, cov, u, t):
    def mag(th):
        return jnp.linalg.norm(model.calibrate(th, u, t), axis=1)
    m = mag(theta)
    G = jax.jacfwd(mag)(theta)
    var = jnp.sum((G @ cov) * G, axis=1)
    return m, jnp.sqrt(jnp.maximum(var, 0.0))


def gauge_text(meas: MeasurementModel) -> str:
    if meas.gauge == "none":
        return "none: a vector reference observes every entry of S and Ks"
    txt = ("S and Ks upper-triangular (M(T) = R U(T): the rotation R, 3 degrees of freedom, is invisible to a "
           "magnitude; the calibrated field is in the sensor's gauge frame, whose x axis is the sensor's x axis "
           "and whose y axis lies in the sensor's x-y plane)")
    if meas.scale_gauge:
        txt += "; trace(S) = 3 because the field magnitude was fitted too (magnitudes are relative, directions absolute)"
    return txt


def _check_fit_inputs(u, t, target, keep) -> None:
    """Shapes that agree and finite values in every row (rows outside ``keep`` too: they are carried with weight 0,
    and 0 x NaN is NaN). Raises :class:`~bayesmag._src.core.data.DataError` naming the input and the rows."""
    from bayesmag._src.core.data import DataError, _bad_rows
    n = len(u)
    if u.ndim != 2 or u.shape[1] != 3:
        raise DataError(f"fit_field: u must have shape (n, 3); got {u.shape}.")
    for name, a in (("t", t), ("target", target), ("keep", keep)):
        if a.shape[0] != n:
            raise DataError(f"fit_field: {name} has {a.shape[0]} rows but u has {n}.")
    for name, a in (("u", u), ("t", t), ("target", target)):
        bad = ~np.isfinite(a.reshape(n, -1)).all(axis=1)
        if bad.any():
            raise DataError(f"fit_field: {name} has {int(bad.sum())} row(s) with non-finite values (NaN or inf) at "
                            f"{_bad_rows(bad).replace('data row', 'row')} (counting from 1); remove or repair those "
                            f"rows before fitting.")


def _check_fit_units(u, t, target, measurement: MeasurementModel, field_unit: str | None) -> None:
    """The command line's unit checks (:func:`~bayesmag._src.core.data.check_units`) on ``fit_field``'s arrays:
    readings (and a scalar or vector reference) in uT, temperature in C."""
    from bayesmag._src.core.data import CalibrationData, DataError, check_units
    if field_unit not in (None, "uT"):
        raise DataError(f"fit_field: field_unit = {field_unit!r}; the arrays must be in uT (convert them), and "
                        f"field_unit = 'uT' declares a genuine low-field recording.")
    if field_unit is None and isinstance(measurement, Constant) and measurement.field is not None:
        from bayesmag._src.core.measurement import measurement_from_spec
        try:                            # the command line's check of [measurement] field (nT or gauss for uT)
            measurement_from_spec("constant", measurement.field)
        except ValueError as e:
            raise DataError(f"fit_field: {e}") from None
    extra = ([("reference (target)", np.asarray(target).reshape(len(u), -1))]
             if isinstance(measurement, (Scalar, Vector)) else [])
    check_units(CalibrationData(u, t, None, field_unit=field_unit), origin="the arrays given to fit_field",
                fix="Convert u (and the reference) to uT", declare="field_unit='uT'",
                temperature_fix="Subtract 273.15", extra_fields=extra)


#: a magnitude recording whose readings' spread along their thinnest direction (temperature-driven change removed)
#: is under this many times the reading noise spans a plane: level turns without tilt (ratio 1.0) fitted gains of
#: 0.03 / 0.03 / 0.001 with a 24 deg heading error and 100 % "coverage"; 0.25 deg of tilt gives 1.8 and fits well
PLANAR_RATIO = 1.3


#: ... and the plane is at least this many times wider than that spread (sd along the widest direction / thinnest
#: raw sd): a recording that barely moves, or a few scattered rows, is no plane (flat turns: 360x; Belsten: 1.8x)
PLANAR_ASPECT = 100.0


def planar_spread(u, t, run=None) -> tuple[float, float, float, float]:
    """``(ratio, sd, noise, aspect)`` of the readings ``u`` along their thinnest direction (smallest eigenvector of their
    covariance): the sd after removing a per-run level, a linear temperature trend and the gains' temperature drift
    (temperature, centred within each run, times each reading), the noise as the sd of
    first differences within runs over sqrt(2), their ratio (1 when that direction holds noise only), and the
    aspect: the widest direction's sd over the thinnest one's."""
    u = np.asarray(u, np.float64)
    run = np.zeros(len(u), int) if run is None else np.asarray(run).reshape(-1)
    w, V = np.linalg.eigh(np.cov(u.T))
    p = u @ V[:, 0]
    runs = np.unique(run)
    t = np.asarray(t, np.float64)
    tc = t.copy()
    for r in runs:                   # within each run: a run held at one temperature has none of this change
        tc[run == r] -= t[run == r].mean()
    # temperature-driven change: a level trend and the gains' drift (tc times each reading), not a field direction
    X = np.column_stack([(run == r).astype(float) for r in runs] + [tc] + [tc * (u[:, j] - u[:, j].mean())
                                                                         for j in range(3)])
    resid = p - X @ np.linalg.lstsq(X, p, rcond=None)[0]
    d = np.diff(p)[run[1:] == run[:-1]]
    noise = float(np.std(d) / np.sqrt(2)) if d.size > 1 else 0.0
    sd = float(np.std(resid))
    aspect = float(np.sqrt(max(w[-1], 0.0) / max(w[0], 1e-300)))
    return (sd / noise if noise > 0 else np.inf), sd, noise, aspect


#: The declared field against what the readings support. A magnitude fit (constant F, or a scalar column) takes its
#: scale from the declared field: F given c times too small fits every gain c times too small, and the magnitude
#: residuals stay as small as before (H = 25 uT typed for F = 48.8 uT: gains 0.52 / 0.49 / 0.50, held-out "RMSE"
#: 0.026 uT, half the reading noise). So the fitted gain matrix S (readings in uT -> field) is checked against what
#: a magnetometer is: its singular values (the gains along its principal directions; gauge-free, as magnitudes
#: determine S only up to a rotation) and their geometric mean k = |det S|^(1/3), the overall scale that the
#: declared field sets (F over the readings' |B| after the fitted hard-iron offset, which the offset does not enter).
#: A sensor's factory sensitivity tolerance (a few to about 10 %) and a vehicle's soft iron (a few %, tens of % near
#: steel), with a site field off its IGRF/WMM value by a few % (crustal anomalies, a building's steel), keep k
#: within [0.8, 1.25]: outside that the calibration is kept with a warning naming the declared field
#: (FIELD_SCALE_WARN). Outside [2/3, 3/2] (ArduPilot's CompassCalibrator refuses the same scale correction against
#: the WMM field beyond COMPASS_MAX_SCALE_FACTOR = 1.5) it is not a sensor but a wrong field: H given for F at an
#: inclination above 48 deg (H/F = cos I), a digit missing or extra, another unit; refused (FIELD_SCALE_REFUSE). A
#: single gain outside [0.5, 2] (one direction reading half or twice what a sensor's does) is refused too
#: (GAIN_REFUSE). These limits are judged on what the data show: a limit counts as crossed only when the estimate lies
#: beyond it by more than GAIN_Z posterior sds (of the log gain). Where every direction was visited the sds are
#: ~1e-3 and the limits act as they read; on level turns the vertical gain, and so k, is the prior's answer (sd of
#: log k 0.05-0.6) and a fit whose vertical drifted (level turns, seed 103: gains 0.52 / 0.51 / 0.24, heading still
#: covered) is no evidence of a wrong field. Whatever the sds: a non-positive diagonal of S (the fit passed through a
#: singular M; an exported axis would be mirrored), a gain under GAIN_DEGENERATE (a 20-fold error: F = 500 uT fitted
#: S_yy 0.0004 and O_y 498 uT) or non-finite values are a degenerate fit, refused. The hard-iron offset (tens of uT on
#: drones) never enters: the raw |B| is not compared with F.
FIELD_SCALE_WARN = (0.8, 1.25)
FIELD_SCALE_REFUSE = (2.0 / 3.0, 1.5)
GAIN_REFUSE = (0.5, 2.0)
GAIN_DEGENERATE = 0.05
GAIN_Z = 3.0


def supported_field(u) -> float:
    """The field magnitude (uT) the readings ``u`` (n, 3) support if their gains average 1: an algebraic ellipsoid fit
    ``|U u + c| = 1`` (the fit's start, hard-iron offset removed, no temperature terms) and its geometric-mean radius
    ``det(U)^(-1/3)``. Independent of any declared field; used to name the likely field in messages.

    Example:
      >>> rng = np.random.default_rng(0); d = rng.normal(size=(400, 3)); d /= np.linalg.norm(d, axis=1)[:, None]
      >>> round(supported_field(48.0 * d + [30.0, -20.0, 25.0]), 3)
      48.0
    """
    u = np.asarray(u, np.float64)
    model = FieldModel(Constant(None), t0=0.0, temperature=False)
    th = _init(model, u, np.zeros(len(u)), np.ones(len(u)))
    S, _, O, _, extra = (np.asarray(a) for a in model.unpack(jnp.asarray(th)))
    det = abs(float(np.linalg.det(S)))
    if not (det > 0 and np.isfinite(det)):
        return float(np.median(np.linalg.norm(u - np.mean(u, axis=0), axis=1)))
    return float(np.median(np.linalg.norm(u @ S.T + O, axis=1)) / det ** (1.0 / 3.0))


def gain_check(S, measurement: MeasurementModel, sd_log=None) -> dict:
    """The gain matrix S (T0) of a magnitude fit against a magnetometer's, without the readings.

    ``sd_log``: posterior sds of the log singular values and of log k (4,), :func:`log_gain_sd`; None: 0 (the point
    estimate judged as it is). Returns ``verdict`` (``"ok"``, ``"warn"``, ``"refuse"``), ``gains`` (singular values
    of S), ``overall`` (k, their geometric mean), ``degenerate`` (non-finite, a non-positive diagonal, a gain under
    :data:`GAIN_DEGENERATE`, or a gain beyond :data:`GAIN_REFUSE` by more than :data:`GAIN_Z` sds), ``scale_bad``
    (k beyond :data:`FIELD_SCALE_REFUSE` by more than :data:`GAIN_Z` sds; never for a fitted field, whose scale is a
    gauge), ``scale_warn`` (the same for :data:`FIELD_SCALE_WARN`). A vector measurement is always ``"ok"``.

    Example:
      >>> gain_check(0.5 * np.eye(3), Constant(25.0))["verdict"], gain_check(np.eye(3), Constant(50.0))["verdict"]
      ('refuse', 'ok')
      >>> S = 0.75 * np.eye(3)        # F = 37 uT at a 49 uT site; then the same gains, each known to 10 % only
      >>> gain_check(S, Constant(37.0))["verdict"], gain_check(S, Constant(37.0), [0.1] * 4)["verdict"]
      ('warn', 'ok')
    """
    S = np.asarray(S, np.float64)
    finite = bool(np.all(np.isfinite(S)))
    sv = np.linalg.svd(S, compute_uv=False) if finite else np.full(3, np.nan)
    k = abs(float(np.linalg.det(S))) ** (1.0 / 3.0) if finite else float("nan")
    z = np.zeros(4) if sd_log is None else GAIN_Z * np.nan_to_num(np.asarray(sd_log, np.float64), nan=np.inf)
    out = {"S": S, "gains": sv, "overall": k, "finite": finite, "degenerate": False, "scale_bad": False,
           "scale_warn": False, "verdict": "ok"}
    if measurement.per_row > 1:
        return out

    def beyond(v, lim, zz):                 # log v beyond [log lo, log hi] by more than zz
        with np.errstate(divide="ignore", invalid="ignore"):
            lv = np.log(np.asarray(v, np.float64))
        return bool(np.any((lv + zz < math.log(lim[0])) | (lv - zz > math.log(lim[1]))))

    free = isinstance(measurement, Constant) and measurement.field is None
    degenerate = not finite or bool(np.any(np.diag(S) <= 0) or sv.min() < GAIN_DEGENERATE
                                    or beyond(sv, GAIN_REFUSE, z[:3]))
    scale_bad = finite and not free and beyond(k, FIELD_SCALE_REFUSE, z[3])
    scale_warn = finite and not free and beyond(k, FIELD_SCALE_WARN, z[3])
    out.update(degenerate=degenerate, scale_bad=scale_bad, scale_warn=scale_warn,
               verdict="refuse" if degenerate or scale_bad else "warn" if scale_warn else "ok")
    return out


@functools.partial(jax.jit, static_argnums=(0,))
def _log_gains_jac(model: FieldModel, theta):
    def g(th):
        S = model.unpack(th)[0]
        ls = jnp.log(jnp.abs(jnp.linalg.svd(S, compute_uv=False)))
        return jnp.concatenate([ls, jnp.mean(ls)[None]])         # log k = mean of the log singular values
    return jax.jacfwd(g)(theta)


def log_gain_sd(fit: "FieldFit") -> np.ndarray:
    """Posterior sds (delta method, the fit's covariance) of the log singular values of S and of log k (4,); inf
    where they cannot be computed (a degenerate S)."""
    try:
        G = np.asarray(_log_gains_jac(_static(fit.model), jnp.asarray(fit.theta)))
        sd = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", G, np.asarray(fit.cov), G), 0, None))
    except (ValueError, np.linalg.LinAlgError):
        return np.full(4, np.inf)
    return np.where(np.isfinite(sd), sd, np.inf)


def judge_gains(fit: "FieldFit") -> dict:
    """:func:`gain_check` of a fit's S (T0) as the data show it: the point estimate first ("ok" there is "ok" at any
    sd), else again with the posterior sds (:func:`log_gain_sd`), which can only soften the verdict."""
    S, meas = fit.matrices()[0], fit.model.measurement
    g = gain_check(S, meas)
    return g if g["verdict"] == "ok" else gain_check(S, meas, log_gain_sd(fit))


def field_scale_check(fit: "FieldFit", u, target=None) -> tuple[str, str]:
    """``(verdict, message)`` of a magnitude fit's gains against a magnetometer's (:data:`FIELD_SCALE_WARN`,
    :data:`FIELD_SCALE_REFUSE`, :data:`GAIN_REFUSE`): ``"ok"`` (message ''), ``"warn"`` or ``"refuse"``, the message
    naming the declared field (a scalar ``target``: its median level), the gains found, the field the readings ``u``
    support (:func:`supported_field`), the likely cause and the fix. A vector fit is ``"ok"`` (its reference fixes
    every gain); with a fitted field (``Constant(None)``, trace(S) = 3) only a degenerate fit is refused.
    """
    meas = fit.model.measurement
    g = judge_gains(fit)
    if g["verdict"] == "ok":
        return "ok", ""
    S, sv, k, finite = g["S"], g["gains"], g["overall"], g["finite"]
    degenerate, scale_bad = g["degenerate"], g["scale_bad"]
    free = isinstance(meas, Constant) and meas.field is None
    gains = (f"{', '.join(f'{v:.3g}' for v in sv)} (overall {k:.3g}; diagonal "
             f"{' / '.join(f'{v:.3g}' for v in np.diag(S))})") if finite else "not finite"
    conv = "" if fit.converged else " (and the fit did not converge)"
    sensor = ("an uncalibrated magnetometer's are within tens of percent of 1 (overall "
              f"{FIELD_SCALE_WARN[0]:g}-{FIELD_SCALE_WARN[1]:g}, each {GAIN_REFUSE[0]:g}-{GAIN_REFUSE[1]:g}, "
              "diagonal positive)")

    def degenerate_fit(why: str = "") -> tuple[str, str]:
        return "refuse", (f"The field fit is degenerate{conv}: its gains (singular values of S) are {gains}, where "
                          f"{sensor}.{why} Check the data for outliers and the motion (tilt or tumble so the field "
                          f"sweeps every direction); docs/field.md.")
    if free:
        return degenerate_fit()
    f_sup = supported_field(u)
    f_val = (float(meas.field) if isinstance(meas, Constant) else
             float(np.median(np.asarray(target, np.float64))) if target is not None else float("nan"))
    r = f_val / f_sup if f_sup > 0 else float("nan")
    if isinstance(meas, Constant):
        what = f"The declared field F = {f_val:.4g} uT"
        if r < 1:
            cause = ("the horizontal intensity H given for the total intensity F (H = F cos(inclination): 0.5 F at 60 "
                     "deg) or the vertical component Z" + (", or a typo (a missing digit is /10)" if r < 0.3 else ""))
        else:
            cause = ("a typo (an extra digit is x10) or a field in another unit" if r > 3
                     else "a typo or another site's field")
        fix = (f"Set [measurement] field (fit_field: Constant(F)) to the site's total intensity F in uT (IGRF/WMM "
               f"'F'; these readings support about {f_sup:.3g} uT if their gains average 1), or field = \"free\" for "
               f"a relative calibration")
    else:
        what = f"The scalar reference (median {f_val:.4g} uT)"
        cause = ("a reference column in another unit or scaled (a unit or gain factor in the scalar magnetometer's "
                 "output), or a column that is not the total field (a component, H)")
        fix = (f"Convert or correct the reference column (these readings support about {f_sup:.3g} uT if their "
               f"gains average 1)")
    ratio = f"{r:.3g}x" if np.isfinite(r) else "not"
    head = f"{what} is {ratio} the field the readings support ({f_sup:.3g} uT after the fitted hard-iron offset)"
    field_off = not FIELD_SCALE_REFUSE[0] <= r <= FIELD_SCALE_REFUSE[1]
    if scale_bad or (degenerate and field_off):
        kind = "" if scale_bad else " degenerate"
        return "refuse", (f"{head}: the{kind} calibration it implies has gains (singular values of S) {gains}{conv}, "
                          f"where {sensor}; that is not a sensor but a wrong field. Likely cause: {cause}. {fix}. "
                          f"Refused: no calibration is kept (docs/field.md, the declared field).")
    if degenerate:
        return degenerate_fit(f" {head}, so the field is not the likely cause.")
    return "warn", (f"{head}: the calibration it implies has gains (singular values of S) {gains}, the overall "
                    f"gain outside the {FIELD_SCALE_WARN[0]:g}-{FIELD_SCALE_WARN[1]:g} a magnetometer's sensitivity "
                    f"tolerance and a vehicle's soft iron usually give. Check the declared field: likely cause {cause}; "
                    f"a local anomaly or a building's steel can also move the site's field. Kept; if the field is wrong "
                    f"every gain, offset and export is wrong by the same factor. {fix}.")


def fit_field(u, t, target, measurement: MeasurementModel, *, t0: float | str = "mean",
              temperature_terms: bool | str = "auto", covariance: str = "white", run=None,
              prior: FieldPrior = FieldPrior(), keep=None, start: "FieldFit | None" = None,
              diagnostics: bool = True, field_unit: str | None = None) -> FieldFit:
    """Fit the thermo-affine model to what ``measurement`` knows per row.

    Args:
      u: (n, 3) raw readings, uT. t: (n,) temperature, C.
      target: the measurement model's data (:func:`field_target`).
      t0: reference temperature, or ``"mean"``.
      temperature_terms: True/False, or ``"auto"`` (on when the temperature spans >= 1 C).
      covariance: ``"white"`` or ``"ar1"`` (the white precision deflated by :math:`(1-\rho_1)/(1+\rho_1)`).
      run: (n,) run ids (AR(1) lags stay inside runs).
      keep: optional (n,) bool, the rows the fit uses (the others are carried with weight 0, so refits on
        different subsets of the same rows share one compiled solver: cross-validation folds).
      start: a fit of the same model to start from (its estimate and noise level), e.g. a refit without a fold;
        such a refit ends after one pass when its noise level moved < 1 % (``_REFIT_SIG_RTOL``).
      diagnostics: False skips the direction coverage and identifiability notes and the unit check (refits that
        only predict).
      field_unit: ``None``: ``u`` (and a scalar or vector ``target``) are checked to be in uT (nT, mT and gauss
        refused, as the command line does) and ``t`` in C (kelvin refused); ``"uT"`` declares a genuine low-field
        recording in uT (the check is skipped).
      With ``Scalar(ref_sd > 0)``: the 1/g fit is a pilot, then one solve weighted by 1/sqrt(g^2 + kappa^2) with the
      pilot's noise level, the sandwich covariance, kept unless a gain S_ii leaves 1 +- 3.29 prior sd
      (``FieldFit.weighting`` says which; docs/field.md).
      With ``diagnostics``, the fitted gains are checked against a magnetometer's (:func:`field_scale_check`): a
      declared field (``Constant(F)``) or scalar reference that implies an overall gain outside
      :data:`FIELD_SCALE_REFUSE`, a gain outside :data:`GAIN_REFUSE` or a non-positive diagonal raises ``DataError``
      naming the declared field and the likely cause (H for F, a unit); outside :data:`FIELD_SCALE_WARN` the fit is
      returned with a :class:`~bayesmag.CalibrationWarning` (and the same text in ``notes``). ``Constant(F)`` with F
      outside 1-2000 uT is refused before fitting, as the command line does (unless ``field_unit="uT"``).
    Returns:
      :class:`FieldFit`.

    Example:
      >>> rng = np.random.default_rng(0); d = rng.normal(size=(400, 3)); d /= np.linalg.norm(d, axis=1)[:, None]
      >>> u = 50 * d @ np.diag([1.1, 0.9, 1.0]) + [3.0, -2.0, 1.0]
      >>> f = fit_field(u, np.full(400, 20.0), np.full(400, 50.0), Constant(50.0))
      >>> bool(np.allclose(f.invariants()["value"][:6], [1 / 1.1**2, 0, 0, 1 / 0.9**2, 0, 1], atol=1e-6))
      True
    """
    if covariance not in ("white", "ar1"):
        raise ValueError(f"field covariance {covariance!r} is not known; it must be 'white' or 'ar1'.")
    u = np.asarray(u, np.float64)
    t = np.asarray(t, np.float64).reshape(-1)
    target = np.asarray(target, np.float64)
    kp = np.ones(len(u), bool) if keep is None else np.asarray(keep, bool).reshape(-1)
    _check_fit_inputs(u, t, target, kp)
    if diagnostics:
        from bayesmag._src.core.precision import warn_if_float32
        warn_if_float32("field.fit_field")
        _check_fit_units(u, t, target, measurement, field_unit)
    if temperature_terms == "auto":
        temperature_terms = bool(np.ptp(t[kp]) >= 1.0)
    t0v = float(np.mean(t[kp])) if t0 == "mean" else float(t0)
    model = FieldModel(measurement, t0=t0v, temperature=bool(temperature_terms))
    n_kept = int(kp.sum())
    if n_kept * measurement.per_row <= model.n_params:
        from bayesmag._src.core.data import DataError
        res = f" ({n_kept * measurement.per_row} residuals)" if measurement.per_row > 1 else ""
        raise DataError(f"fit_field: {n_kept} rows{res} but the field model has {model.n_params} parameters: a fit "
                        f"needs more rows than parameters (many more for a useful calibration).")
    if diagnostics and measurement.per_row == 1 and kp.sum() > 3:
        ratio, sd, noise, aspect = planar_spread(u[kp], t[kp], None if run is None else np.asarray(run).reshape(-1)[kp])
        if ratio < PLANAR_RATIO and aspect > PLANAR_ASPECT:
            from bayesmag._src.core.data import DataError
            raise DataError(f"The readings span a plane: along their thinnest direction they vary by {sd:.3g} uT (sd), "
                            f"{ratio:.2f}x the reading noise ({noise:.3g} uT). A magnitude (or scalar) reference then "
                            f"cannot fix the gain and offset across that plane: the fit can shrink the field to a "
                            f"constant and still match |B| (level turns without any tilt). Record with some tilt "
                            f"(0.5 deg is enough in simulation) or a 3-D dance, or calibrate against a vector "
                            f"reference; docs/field.md.")
    theta0 = _init(model, u[kp], t[kp], target[kp]) if start is None else np.asarray(start.theta, np.float64)
    mu, sd = model.prior(prior, u[kp])
    ms, uj, tj, yj = _static(model), jnp.asarray(u), jnp.asarray(t - t0v), jnp.asarray(target)
    kj = jnp.asarray(np.repeat(kp, measurement.per_row).astype(np.float64))
    n_res = int(kp.sum()) * measurement.per_row
    r0, _ = _jac_resid(ms, jnp.asarray(theta0), uj, tj, yj, kj, 0.0)
    sig = max(float(np.sqrt(np.sum(np.asarray(r0) ** 2) / n_res)), 1e-6)
    kappa2, weighting = 0.0, "gain"
    if start is not None:
        sig = math.sqrt(start.s2 * start.inflation)
        kappa2, weighting = start.kappa2, start.weighting
    infl, rho, steps, ok = 1.0, 0.0, 0, True
    theta = theta0
    # The prior enters the LM cost as w (theta - mu) with w = sig / sd, so the mode is the posterior mode only
    # when sig is the noise level the fit itself implies: iterate to that fixed point. (Two passes were not
    # enough: from a poor algebraic start the second pass ran with sig 25x too large, i.e. a prior 600x too
    # strong, which moved the mode by up to 0.6 posterior sd; NUTS showed it, tests/test_field.py.)

    def one_pass(theta, sig, kappa2):
        sol = _solve(ms, jnp.asarray(theta), uj, tj, yj, jnp.asarray(mu), jnp.asarray(sig / sd), kj, kappa2)
        theta = np.asarray(sol.theta)
        r, J = (np.asarray(a) for a in _jac_resid(ms, jnp.asarray(theta), uj, tj, yj, kj, kappa2))
        s2 = float(r @ r / max(n_res - model.n_params, 1))
        # the residuals' lag-1 autocorrelation is measured whatever the covariance (the certificate states it; with
        # "white" it was written as 0.0, a placeholder read as a measurement); only "ar1" inflates by it
        rr = r.reshape(len(u), -1)[kp]
        rk = None if run is None else np.asarray(run)[kp]
        rho = float(np.mean([lag1_autocorrelation(rr[:, k], rk) for k in range(rr.shape[1])]))
        infl = (1 + max(rho, 0.0)) / (1 - min(max(rho, 0.0), 0.99)) if covariance == "ar1" else 1.0
        return theta, J, s2, rho, infl, int(sol.n_steps), int(sol.result) == 0, r

    for k in range(_MAX_PASSES):
        theta, J, s2, rho, infl, n_st, ok, r = one_pass(theta, sig, kappa2)
        steps += n_st
        sig_new = math.sqrt(s2 * infl)
        done = ((k > 0 and abs(sig_new / sig - 1.0) < _SIG_RTOL)
                or (start is not None and abs(sig_new / sig - 1.0) < _REFIT_SIG_RTOL))
        sig = sig_new
        if done:
            break
    ref2 = measurement.reference_sd ** 2 if measurement.per_row == 1 else 0.0
    if ref2 > 0 and start is None:
        # The reference's own noise: divided by g like the reading noise, its cost sum(ref_sd^2 / g^2) falls as M
        # grows along a direction the motion left weak (level turns: the vertical), a pull of its own. The
        # residual's whole sd, sqrt(g^2 + kappa^2) in reading units, removes it (expected cost flat along such a
        # direction), but it is also flat along the degenerate solution M -> 0 (a dead sensor whose offset alone
        # explains a constant magnitude), where the noise level is not identified. So the 1/g fit above is the
        # pilot: it fixes the noise level (identified there), the refit starts from it with sig and kappa held,
        # and the refit is kept only if every gain S_ii stays inside the prior's 99.9 % range (else the pilot,
        # with a note). docs/field.md (Heading) has the measurements.
        k2 = ref2 / s2
        th_c, J_c, s2_c, rho_c, infl_c, n_st, ok_c, r_c = one_pass(theta, sig, k2)
        steps += n_st
        S_c = np.diag(np.asarray(model.unpack(jnp.asarray(th_c))[0]))
        if np.all(np.abs(S_c - 1.0) <= _GAIN_Z * prior.s_diag):
            theta, J, s2, rho, infl, ok, kappa2, weighting, r = th_c, J_c, s2_c, rho_c, infl_c, ok_c, k2, "total", r_c
        else:
            weighting = "gain (the reference-noise refit left the prior's gain range: rejected)"
    P = J.T @ J / (s2 * infl) + np.diag(1.0 / sd**2)
    cov = np.linalg.inv(P)
    if weighting == "total":
        cov = _sandwich(_hess(ms, jnp.asarray(theta), uj, tj, yj, kj, kappa2), J, r, s2 * infl, infl, sd, cov)
    cov = 0.5 * (cov + cov.T)
    fit0 = FieldFit(model, theta, cov, mu, sd, s2, rho, infl, int(kp.sum()), ok, steps, covariance, {}, (),
                    kappa2, weighting)
    if not diagnostics:
        return fit0
    # the declared field (or the scalar column's level) against what the readings support: FIELD_SCALE_REFUSE
    verdict, why = field_scale_check(fit0, u[kp], target[kp])
    if verdict == "refuse":
        from bayesmag._src.core.data import DataError
        raise DataError(why)
    cov_diag = direction_coverage(fit0.calibrate(u[kp], t[kp]), t[kp])
    fit1 = dataclasses.replace(fit0, coverage=cov_diag)
    notes = identifiability_notes(fit1, cov_diag)
    if verdict == "warn":
        import warnings

        from bayesmag._src.core.data import CalibrationWarning, user_stacklevel
        warnings.warn(why, CalibrationWarning, stacklevel=user_stacklevel())
        notes = [why] + notes
    return dataclasses.replace(fit1, notes=tuple(notes))


# --------------------------------------------------------------------------- diagnostics

#: covariance eigenvalue of the unit field direction below which a direction counts as not visited (sd < 0.1)
DIRECTION_MIN = 0.01


def _dir_eigs(B):
    n = B / np.linalg.norm(B, axis=1, keepdims=True)
    C = np.cov(n.T) if len(n) > 1 else np.zeros((3, 3))
    w, V = np.linalg.eigh(C)
    return w, V


def direction_coverage(B: np.ndarray, t: np.ndarray, *, band_width: float = 5.0) -> dict:
    """Which field directions the recording visited, overall and per temperature band.

    The eigenvalues of the covariance of the unit field direction B/|B| (gauge frame): a full
    tumble gives about 1/3 each; an eigenvalue < :data:`DIRECTION_MIN` means the direction barely
    changed along that eigenvector (e.g. the vertical during level turns). Bands are ``band_width`` C wide.
    """
    B, t = np.asarray(B), np.asarray(t)
    w, V = _dir_eigs(B)
    lo, hi = float(np.min(t)), float(np.max(t))
    nb = max(1, int(math.ceil((hi - lo) / band_width - 1e-9)))
    edges = np.linspace(lo, hi, nb + 1)
    bands = []
    for k in range(nb):
        m = (t >= edges[k]) & ((t <= edges[k + 1]) if k == nb - 1 else (t < edges[k + 1]))
        if m.sum() < 10:
            continue
        wb, _ = _dir_eigs(B[m])
        bands.append({"t_lo": float(edges[k]), "t_hi": float(edges[k + 1]), "rows": int(m.sum()),
                      "eigenvalues": wb.tolist(), "spread": bool(wb[0] >= DIRECTION_MIN)})
    missing = [V[:, k].round(3).tolist() for k in range(3) if w[k] < DIRECTION_MIN]
    return {"eigenvalues": w.tolist(), "eigenvectors": V.T.round(4).tolist(), "missing_directions": missing,
            "temperature_range": [lo, hi], "bands": bands,
            "bands_spread": int(sum(b["spread"] for b in bands))}


def _axis_name(v) -> str:
    v = np.abs(np.asarray(v))
    k = int(np.argmax(v))
    return AXES[k] if v[k] > 0.9 else "(" + ", ".join(f"{x:.2f}" for x in np.asarray(v)) + ")"


def identifiability_notes(fit: FieldFit, cov_diag: dict) -> list[str]:
    """Plain-language notes: unvisited directions, thermal terms without spread, invariants not identified."""
    notes = []
    for v in cov_diag["missing_directions"]:
        ax = _axis_name(v)
        notes.append(f"the field direction barely changed along sensor axis {ax}: the scale along {ax} is not "
                     f"separated from the offset along {ax}, nor the cross terms with {ax}; tilt or tumble the "
                     f"sensor so the field sweeps along {ax} (e.g. pitch and roll by +-60 degrees, or a full dance)")
    if fit.model.temperature and cov_diag["bands_spread"] < 2:
        notes.append("the field directions were spread at fewer than two temperatures (5 C bands): the thermal gain "
                     "Ks is not separated from the thermal offset Ko; repeat the motion at a second temperature")
    if heading_flagged(fit):
        notes.append("the reference-noise refit reached the degenerate solution (a gain S_ii left the prior's 99.9 % "
                     "range: M -> 0, the offset alone explaining a constant magnitude); the 1/g fit is kept, which the "
                     "reference's noise pulls along weakly visited directions: its intervals there, heading included, "
                     "are too narrow (heading flagged); tilt the vehicle so every direction is visited, or use "
                     "kind = \"constant\" with the site's field")
    if fit.model.measurement.scale_gauge:
        notes.append("the field magnitude was fitted (constant, free): the overall scale is a gauge (trace(S) = 3)")
    inv = fit.invariants()
    bad = {}
    for n, i, w in zip(inv["names"], inv["identified"], inv["why"]):
        if not i:
            bad.setdefault(w, []).append(n)
    for w, names_ in bad.items():
        notes.append(f"not identified by this recording ({w}): " + ", ".join(names_))
    C = fit.corr
    names = fit.param_names
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            if abs(C[i, j]) > 0.99:
                notes.append(f"{names[i]} and {names[j]} are correlated {C[i, j]:+.3f}: this motion hardly separates them")
    return notes


# --------------------------------------------------------------------------- scores and heading


def gaussian_scores(y, mean, sd, level: float = 0.95) -> dict:
    """Coverage, mean NLL and mean CRPS of Gaussian predictions (closed forms; Gneiting & Raftery 2007)."""
    y, mean, sd = (np.asarray(a, np.float64) for a in (y, mean, sd))
    z = (y - mean) / sd
    k = scipy.stats.norm.ppf(0.5 + level / 2)
    nll = 0.5 * np.log(2 * np.pi * sd**2) + 0.5 * z**2
    crps = sd * (z * (2 * scipy.stats.norm.cdf(z) - 1) + 2 * scipy.stats.norm.pdf(z) - 1 / np.sqrt(np.pi))
    return {"coverage": float(np.mean(np.abs(z) <= k)), "nll": float(np.mean(nll)), "crps": float(np.mean(crps)),
            "rmse": float(np.sqrt(np.mean((y - mean) ** 2))), "mean_width": float(np.mean(2 * k * sd)),
            "level": level, "n": int(y.size)}


def heading_flagged(fit: FieldFit) -> bool:
    """True when heading intervals are not to be trusted: the reference-noise refit was rejected (a gain left the
    prior's range), so the 1/g fit was kept, which a noisy reference pulls along unvisited directions (docs/field.md,
    Heading: its intervals cover 0.39-0.90 there)."""
    return fit.weighting.startswith("gain (")


def heading(B) -> np.ndarray:
    """Magnetic heading in degrees of a level sensor, body frame x forward, y right, z down:
    ``atan2(-B_y, B_x)`` (0 = north, 90 = east)."""
    B = np.asarray(B)
    return np.degrees(np.arctan2(-B[..., 1], B[..., 0]))


def wrap_deg(a):
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


@functools.partial(jax.jit, static_argnums=(0,))
def _heading_jac(model: FieldModel, theta, u, t, R):
    def h(th, uu):
        B = jnp.einsum("nij,nj->ni", R, model.calibrate(th, uu, t))
        return jnp.arctan2(-B[:, 1], B[:, 0])
    val = h(theta, u)
    Gt = jax.jacfwd(h, argnums=0)(theta, u)                        # (n, p)
    return val, Gt


@functools.partial(jax.jit, static_argnums=(0,))
def _heading_row_grad(model: FieldModel, theta, u, t, R):
    def one(uk, tk, Rk):
        B = Rk @ model.calibrate(theta, uk[None], tk[None])[0]
        return jnp.arctan2(-B[1], B[0])
    return jax.vmap(jax.grad(one))(u, t, R)


def heading_with_uncertainty(fit: FieldFit, u, t, R=None, *, noise_sd: float | None = None) -> dict:
    """Heading (degrees) of the calibrated field rotated into the body frame by ``R``, with standard deviations.

    ``R`` (3, 3) or (n, 3, 3) maps the gauge frame to the body frame. A magnitude calibration cannot
    know it (the gauge): it needs a second vector (known attitudes, gravity, or a heading reference),
    so the intervals are conditional on ``R``; ``R=None`` takes the gauge frame as the body frame.
    Returns ``heading``, ``sd_params`` (from the parameter posterior), ``sd_noise`` (the reading's noise,
    ``noise_sd`` per axis, default the fit's residual sd), ``sd`` (both) and ``flagged`` (:func:`heading_flagged`).
    """
    u = jnp.asarray(u, jnp.float64)
    t = jnp.asarray(t, jnp.float64)
    n = u.shape[0]
    R = jnp.broadcast_to(jnp.eye(3) if R is None else jnp.asarray(R, jnp.float64), (n, 3, 3))
    ms, tc = _static(fit.model), t - fit.model.t0
    val, Gt = _heading_jac(ms, jnp.asarray(fit.theta), u, tc, R)
    Gt = np.asarray(Gt)
    var_p = np.sum((Gt @ fit.cov) * Gt, axis=1)
    gu = np.asarray(_heading_row_grad(ms, jnp.asarray(fit.theta), u, tc, R))
    ns = math.sqrt(fit.s2) if noise_sd is None else float(noise_sd)
    var_n = ns**2 * np.sum(gu**2, axis=1)
    deg = 180.0 / np.pi
    return {"heading": np.degrees(np.asarray(val)), "sd_params": deg * np.sqrt(var_p), "sd_noise": deg * np.sqrt(var_n),
            "sd": deg * np.sqrt(var_p + var_n), "flagged": heading_flagged(fit)}
