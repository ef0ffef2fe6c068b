r"""Levenberg-Marquardt least squares, parameter covariance and identifiability diagnostics.

The solver is a compact, jit-compiled Levenberg-Marquardt (Marquardt 1963; scaling by
the running maximum of ``diag(J^T J)`` and the damping update of Nielsen 1999, as in
Moré 1977 / MINPACK's ``lmder`` that ``scipy.optimize.least_squares(method='lm')`` wraps).
It works on any residual function ``r(theta) -> (n,)``, so the same fit serves models that
are nonlinear in their parameters (thermal time constants, timing delays). Failures are
returned as data (:class:`LMSolution.result`), never raised inside ``jit``.

Covariance of the estimate (Seber & Wild 2003, sec. 2.1):

* ``"white"``: :math:`s^2 (J^T J)^{-1}`, :math:`s^2 = \mathrm{RSS}/(n-p)` -- right for
  independent residuals.
* ``"ar1"``: the white covariance inflated by :math:`(1+\rho_1)/(1-\rho_1)`, the
  effective-sample-size correction for AR(1) residuals with lag-1 autocorrelation
  :math:`\rho_1` (exact when regressors vary slowly compared with the noise).
* ``"newey_west"``: the heteroscedasticity-and-autocorrelation-consistent sandwich
  :math:`A^{-1} \hat S A^{-1}` with Bartlett weights (Newey & West 1987), lags chosen by
  Andrews' (1991) AR(1) plug-in rule, sums restricted to lags inside each run.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bayesmag._src.core.frames import frame_io
from bayesmag._src.core.physics import AXES, Inputs, PhysicsModel, centred, median_step

__all__ = ["LMSolution", "RESULTS", "levenberg_marquardt", "PhysicsFit", "fit_physics", "covariance",
           "identifiability", "lag1_autocorrelation", "unidentifiable", "RANK_RTOL"]

RESULTS = ("converged", "max_steps_reached", "nonfinite")


class LMState(NamedTuple):
    theta: jax.Array
    cost: jax.Array
    lam: jax.Array
    nu: jax.Array
    diag: jax.Array
    step: jax.Array
    done: jax.Array
    result: jax.Array


class LMSolution(NamedTuple):
    """Outcome of :func:`levenberg_marquardt`: ``result`` indexes :data:`RESULTS` (0 = converged)."""

    theta: jax.Array
    cost: jax.Array
    result: jax.Array
    n_steps: jax.Array
    grad_norm: jax.Array


def levenberg_marquardt(residual_fn: Callable[[jax.Array], jax.Array], theta0: jax.Array, *,
                        max_steps: int = 200, ftol: float = 1e-12, xtol: float = 1e-12,
                        gtol: float = 1e-12, lam0: float = 1e-3) -> LMSolution:
    r"""Minimise :math:`\tfrac12\|r(\theta)\|^2` by Levenberg-Marquardt.

    Each step solves :math:`(J^T J + \lambda D)\,\delta = -J^T r` with ``D`` the running
    maximum of ``diag(J^T J)``; a step is accepted if the actual reduction is positive,
    and :math:`\lambda` shrinks by :math:`\max(1/3, 1-(2\rho-1)^3)` (Nielsen 1999) or
    grows by a doubling factor. Stops when the relative cost reduction < ``ftol`` and the
    relative step < ``xtol``, or the scaled gradient < ``gtol``.

    Args:
      residual_fn: ``theta (p,) -> r (n,)``, traceable by JAX.
      theta0: starting point (p,).
    Returns:
      :class:`LMSolution`; vmap over problems of equal shape (e.g. the three axes).

    Example:
      >>> sol = levenberg_marquardt(lambda th: jnp.array([th[0] - 2.0, 3 * (th[1] + 1)]), jnp.zeros(2))
      >>> np.round(np.asarray(sol.theta), 6).tolist(), int(sol.result)
      ([2.0, -1.0], 0)
    """
    theta0 = jnp.asarray(theta0)
    jac_fn = jax.jacfwd(residual_fn)

    def cost_of(th):
        r = residual_fn(th)
        return 0.5 * jnp.sum(r * r)

    c0 = cost_of(theta0)
    state = LMState(theta0, c0, jnp.asarray(lam0, theta0.dtype), jnp.asarray(2.0, theta0.dtype),
                    jnp.zeros_like(theta0), jnp.asarray(0), ~jnp.isfinite(c0), jnp.where(jnp.isfinite(c0), 0, 2))

    def cond(s):
        return ~s.done

    def body(s):
        r = residual_fn(s.theta)
        J = jac_fn(s.theta)
        A = J.T @ J
        g = J.T @ r
        diag = jnp.maximum(s.diag, jnp.diag(A))
        dsafe = jnp.where(diag > 0, diag, 1.0)
        delta = jnp.linalg.solve(A + s.lam * jnp.diag(dsafe), -g)
        th_new = s.theta + delta
        c_new = cost_of(th_new)
        pred = -(g @ delta) - 0.5 * delta @ (A @ delta)
        actual = s.cost - c_new
        rho = actual / jnp.where(pred > 0, pred, jnp.inf)
        ok = jnp.isfinite(c_new) & (actual > 0)
        lam = jnp.where(ok, s.lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), s.lam * s.nu)
        nu = jnp.where(ok, 2.0, 2.0 * s.nu)
        theta = jnp.where(ok, th_new, s.theta)
        cost = jnp.where(ok, c_new, s.cost)
        small_f = jnp.abs(actual) <= ftol * jnp.maximum(s.cost, 1e-300)
        small_x = jnp.linalg.norm(delta * jnp.sqrt(dsafe)) <= xtol * (jnp.linalg.norm(s.theta * jnp.sqrt(dsafe)) + xtol)
        small_g = jnp.max(jnp.abs(g) / jnp.sqrt(dsafe)) <= gtol * jnp.maximum(jnp.sqrt(2 * s.cost), 1e-300)
        converged = (ok & small_f & small_x) | small_g | (~ok & small_x) | (s.cost == 0)
        step = s.step + 1
        bad = ~jnp.isfinite(lam) | (lam > 1e30)
        maxed = step >= max_steps
        done = converged | maxed | bad
        result = jnp.where(converged, 0, jnp.where(bad, 2, jnp.where(maxed, 1, 0)))
        return LMState(theta, cost, jnp.minimum(lam, 1e32), nu, diag, step, done, result)

    s = jax.lax.while_loop(cond, body, state)
    r = residual_fn(s.theta)
    g = jac_fn(s.theta).T @ r
    return LMSolution(s.theta, s.cost, s.result, s.step, jnp.linalg.norm(g))


# --------------------------------------------------------------------------- covariance


def lag1_autocorrelation(r: np.ndarray, run: np.ndarray | None = None) -> float:
    """Lag-1 autocorrelation of residuals ``r`` (pairs across run boundaries excluded)."""
    r = np.asarray(r, dtype=np.float64)
    r = r - r.mean()
    same = np.ones(r.size - 1, dtype=bool) if run is None else (np.asarray(run)[1:] == np.asarray(run)[:-1])
    den = np.sum(r * r)
    if den == 0 or r.size < 3:
        return 0.0
    return float(np.sum((r[1:] * r[:-1])[same]) / den * r.size / max(same.sum(), 1))


def _andrews_bandwidth(rho: float, n: int) -> int:
    """Andrews (1991) AR(1) plug-in lag count for the Bartlett kernel."""
    rho = float(np.clip(rho, -0.97, 0.97))
    alpha = 4 * rho**2 / ((1 - rho) ** 2 * (1 + rho) ** 2)
    return int(np.clip(np.ceil(1.1447 * (alpha * n) ** (1 / 3)), 1, max(1, n // 4)))


def _safe_inverse(A: np.ndarray) -> np.ndarray:
    """Inverse via the correlation-scaled matrix (better conditioned); pinv if singular."""
    d = np.sqrt(np.clip(np.diag(A), 1e-300, None))
    As = A / np.outer(d, d)
    try:
        inv = np.linalg.inv(As)
    except np.linalg.LinAlgError:
        inv = np.linalg.pinv(As, rcond=1e-15)
    return inv / np.outer(d, d)


def covariance(J: np.ndarray, r: np.ndarray, *, method: str = "white", run: np.ndarray | None = None,
               lags: int | None = None) -> tuple[np.ndarray, dict]:
    """Parameter covariance for residuals ``r`` (n,) with Jacobian ``J`` (n, p) of the *model*.

    Returns ``(cov, info)`` with ``info`` holding ``s2``, ``dof``, ``rho1`` and, for
    Newey-West, ``lags``. See the module docstring for the methods.
    """
    valid = ("white", "ar1", "newey_west")
    if method not in valid:
        raise ValueError(f"covariance method {method!r} is not known; it must be one of {list(valid)}.")
    J = np.asarray(J, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    n, p = J.shape
    dof = n - p
    s2 = float(r @ r / dof)
    A = J.T @ J
    Ainv = _safe_inverse(A)
    rho = lag1_autocorrelation(r, run)
    info = {"s2": s2, "dof": int(dof), "rho1": rho, "method": method}
    if method == "white":
        return s2 * Ainv, info
    if method == "ar1":
        infl = (1 + max(rho, 0.0)) / (1 - min(max(rho, 0.0), 0.99))
        info["inflation"] = float(infl)
        return infl * s2 * Ainv, info
    L = _andrews_bandwidth(rho, n) if lags is None else int(lags)
    info["lags"] = L
    run = np.zeros(n, dtype=np.int64) if run is None else np.asarray(run)
    S = bartlett_scores(J * r[:, None], run, L)
    S *= n / dof                                            # small-sample dof correction
    return Ainv @ S @ Ainv, info


def bartlett_scores(u: np.ndarray, run: np.ndarray, lags: int) -> np.ndarray:
    r"""Bartlett-weighted long-run sum of scores ``u`` (n, p): :math:`\sum_{|t-s| \le L,\ run_t = run_s}
    (1 - |t-s|/(L+1))\, u_t u_s^\top` (the Newey-West middle; pairs within a run only).

    The Bartlett weights are the overlap of two boxes of length :math:`L+1`, so the sum is
    :math:`C^\top C / (L+1)`, ``C`` the sums of ``u`` over every window of :math:`L+1` consecutive rows clipped to
    its run (cumulative sums): one product of :math:`O(n p^2)` instead of one per lag, :math:`O(L n p^2)` (strongly
    autocorrelated residuals give :math:`L \approx 270` at 12 600 rows). Runs must be contiguous blocks of rows
    for that; otherwise (a run's label back after another's) the lag loop is used, which also pairs rows of a run
    across the other run.
    """
    u = np.asarray(u, dtype=np.float64)
    run = np.asarray(run)
    n, p = u.shape
    L = int(lags)
    starts = np.flatnonzero(np.r_[True, run[1:] != run[:-1]]) if n else np.zeros(0, int)
    if np.unique(run[starts]).size < starts.size:           # a run in more than one block: the lag loop
        S = u.T @ u
        for l in range(1, L + 1):
            same = run[l:] == run[:-l]
            G = (u[l:][same]).T @ (u[:-l][same])
            S += (1 - l / (L + 1)) * (G + G.T)
        return S
    S = np.zeros((p, p))
    for a, b in zip(starts, np.r_[starts[1:], n]):          # one block per run (few)
        cs = np.concatenate([np.zeros((1, p)), np.cumsum(u[a:b], axis=0)])
        m = np.arange(-L, b - a)                           # window starts; [m, m + L] clipped to the run
        C = cs[np.clip(m + L + 1, 0, b - a)] - cs[np.clip(m, 0, b - a)]
        S += C.T @ C
    return S / (L + 1)


# --------------------------------------------------------------------------- identifiability


def identifiability(cov: np.ndarray, names: tuple[str, ...], *, corr_threshold: float = 0.99,
                    ratio_threshold: float = 1e-6) -> dict:
    """Near-collinear parameter groups from a covariance matrix.

    Returns the correlation matrix, the condition number of the correlation-scaled
    information matrix, the pairs with ``|corr| > corr_threshold`` and, for each
    eigenvector of the correlation matrix with a tiny eigenvalue, the poorly identified
    combination (the well-identified combinations are orthogonal to it).
    """
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    corr = cov / np.outer(np.where(sd > 0, sd, 1), np.where(sd > 0, sd, 1))
    w, V = np.linalg.eigh(corr)
    cond = float(w.max() / max(w.min(), 1e-300))
    pairs = [
        {"a": names[i], "b": names[j], "corr": float(corr[i, j])}
        for i in range(len(names)) for j in range(i + 1, len(names)) if abs(corr[i, j]) > corr_threshold
    ]
    weak = []
    for k in np.flatnonzero(w < ratio_threshold * w.max()):
        v = V[:, k]
        big = np.argsort(-np.abs(v))[:4]
        big = [i for i in big if abs(v[i]) > 0.1]
        weak.append({"eigenvalue_ratio": float(w[k] / w.max()),
                     "combination": {names[i]: float(v[i]) for i in big}})
    return {"corr": corr, "condition_number": cond, "high_corr_pairs": pairs, "weak_directions": weak}


# --------------------------------------------------------------------------- rank check

#: Relative singular-value threshold of the column-scaled Jacobian below which it is rank-deficient:
#: sqrt(float64 eps) = 1.5e-8. The covariance inverts J^T J, whose eigenvalues are the squared singular
#: values, so a ratio below sqrt(eps) makes J^T J singular to working precision and its inverse noise.
#: The Belsten recordings, nearly collinear in S/Ks, sit at 1.1e-3 (t0 = 0) -- five orders above.
RANK_RTOL = float(np.sqrt(np.finfo(np.float64).eps))


def unidentifiable(J: np.ndarray, names: tuple[str, ...], *, rtol: float = RANK_RTOL) -> tuple[list[str], float]:
    """Parameters the data cannot inform: those in the numerical null space of ``J`` (n, p).

    Columns are scaled to unit norm first (units do not matter); a column of zeros is
    unidentifiable on its own. Returns ``(names, ratio)``: the parameters with weight > 0.1 in
    a singular vector whose singular value is below ``rtol`` times the largest, and the smallest
    relative singular value (0 for a zero column).
    """
    J = np.asarray(J, dtype=np.float64)
    norm = np.linalg.norm(J, axis=0)
    zero = norm <= np.finfo(np.float64).tiny
    if zero.any():
        return [names[i] for i in np.flatnonzero(zero)], 0.0
    _, sv, Vt = np.linalg.svd(J / norm, full_matrices=False)
    ratio = float(sv.min() / sv.max())
    bad = set()
    for k in np.flatnonzero(sv < rtol * sv.max()):
        v = Vt[k]
        bad.update(int(i) for i in np.flatnonzero(np.abs(v) > 0.1))
    return [names[i] for i in sorted(bad)], ratio


# --------------------------------------------------------------------------- physics fit


@dataclasses.dataclass(frozen=True)
class PhysicsFit:
    """A fitted physics model: per-axis parameters (3, p), covariances (3, p, p) and diagnostics."""

    model: PhysicsModel
    theta: np.ndarray
    cov: np.ndarray
    s2: np.ndarray
    n: int
    rmse_in_sample: np.ndarray
    result: tuple[str, str, str]
    n_steps: np.ndarray
    covariance_method: str
    cov_info: tuple[dict, dict, dict]
    diagnostics: tuple[dict, dict, dict]
    design_notes: tuple[str, ...] = ()
    design_warnings: tuple[str, ...] = ()

    @property
    def param_names(self):
        return self.model.param_names

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diagonal(self.cov, axis1=1, axis2=2), 0, None))

    @property
    def converged(self) -> bool:
        return all(r == "converged" for r in self.result)

    @frame_io(physics_inputs=True)   # also a CalibrationData, or a DataFrame (then a DataFrame out)
    def predict(self, inputs: Inputs) -> np.ndarray:
        return np.asarray(self.model.predict_all(jnp.asarray(self.theta), inputs))

    def residuals(self, rows, series=None) -> np.ndarray:
        """(n, 3) ``b_ref - prediction`` of the rows ``rows``. ``series``: ``(recording, index)`` with ``rows`` =
        ``recording``'s rows ``index``: a model whose rows depend on their neighbours (input transforms,
        history terms) then predicts them within the recording, as :func:`fit_physics` with ``keep`` fitted."""
        from bayesmag._src.core.physics import inputs_from_data
        if series is not None and self.model.needs_series:
            recording, index = series
            return np.asarray(rows.b_ref) - self.predict(inputs_from_data(recording))[index]
        return np.asarray(rows.b_ref) - self.predict(inputs_from_data(rows))

    def to_json(self) -> dict:
        out = {"model": self.model.describe(), "n_rows": self.n, "covariance_method": self.covariance_method,
               "axes": {}, "design_notes": list(self.design_notes), "design_warnings": list(self.design_warnings)}
        for a, ax in enumerate(AXES):
            d = self.diagnostics[a]
            out["axes"][ax] = {
                "values": dict(zip(self.param_names, map(float, self.theta[a]))),
                "std": dict(zip(self.param_names, map(float, self.std[a]))),
                "correlation": np.round(d["corr"], 6).tolist(),
                "condition_number": d["condition_number"],
                "high_corr_pairs": d["high_corr_pairs"],
                "weak_directions": d["weak_directions"],
                "residual_std": float(np.sqrt(self.s2[a])),
                "rmse_in_sample": float(self.rmse_in_sample[a]),
                "lag1_autocorrelation": self.cov_info[a]["rho1"],
                "solver": {"result": self.result[a], "steps": int(self.n_steps[a])},
                "covariance_info": {k: v for k, v in self.cov_info[a].items()},
            }
        return out


#: Fewest rows per parameter (per axis) before a fit is warned about: below it the noise level and every
#: uncertainty rest on few residuals (5 x 8 = 40 rows: 32 residual dof, the noise sd known to about 13 %).
MIN_ROWS_PER_PARAM = 5
#: Smallest training temperature span (C) for thermal terms before a fit is warned about (the field
#: calibration's ``temperature_terms = "auto"`` switches them off below the same span).
MIN_TEMPERATURE_SPAN_C = 1.0


#: A residual this many robust sds (1.4826 MAD) from the axis's median marks a gross outlier (a glitch sample in the
#: reference or the readings). The largest on the real Belsten fit is 8.4, on the quickstart campaign 5.1.
OUTLIER_Z = 15.0


def gross_outliers(resid: np.ndarray, *, z: float = OUTLIER_Z) -> np.ndarray:
    """(n, 3) bool: residuals more than ``z`` robust sds (1.4826 MAD about the median) from their axis's median.

    Example:
      >>> r = np.random.default_rng(0).normal(size=(500, 3)) * 0.05; r[31, 1] = 450.0
      >>> np.argwhere(gross_outliers(r)).tolist()
      [[31, 1]]
    """
    r = np.asarray(resid, np.float64)
    med = np.median(r, axis=0)
    sd = 1.4826 * np.median(np.abs(r - med), axis=0)
    return np.abs(r - med) > z * np.where(sd > 0, sd, np.inf)


def _outlier_warning(data, resid: np.ndarray, what: str = "reference or reading") -> list[str]:
    """A warning naming the rows (run, time) and axes of gross outliers in the residuals, or none."""
    bad = gross_outliers(resid)
    rows = np.flatnonzero(bad.any(axis=1))
    if not rows.size:
        return []
    shown = "; ".join(f"run {int(data.run[i])} time {data.time[i]:.6g} s ({', '.join(a for a, b in zip(AXES, bad[i]) if b)}"
                      f": residual {float(np.max(np.abs(resid[i][bad[i]]))):.3g} uT)" for i in rows[:5])
    more = f" and {rows.size - 5} more" if rows.size > 5 else ""
    return [f"{rows.size} row(s) fit more than {OUTLIER_Z:g} robust sds off ({shown}{more}): a glitch in the "
            f"{what} pulls every parameter of a least-squares fit. Check those rows in the file and remove them if "
            f"they are glitches; many such rows together are more likely physics the model lacks (`bayesmag "
            f"discover`)."]


def _design_warnings(data, model: PhysicsModel, cov: np.ndarray, resid: np.ndarray | None = None) -> tuple[str, ...]:
    """What makes a converged fit untrustworthy as a calibration: too few rows for its parameters, thermal terms
    fitted on a temperature span too small to inform them (they are then extrapolations), or gross outliers."""
    out, p = [], model.n_params
    if resid is not None and data.n >= MIN_ROWS_PER_PARAM * p:
        out += _outlier_warning(data, resid)
    if data.n < MIN_ROWS_PER_PARAM * p:
        out.append(f"The fit used {data.n} rows for {p} parameters per axis ({data.n - p} residual degrees of "
                   f"freedom): its noise level and every uncertainty rest on so few residuals that they are "
                   f"themselves uncertain. Record at least {MIN_ROWS_PER_PARAM * p} rows (many more for a useful "
                   f"calibration).")
    if any(getattr(t, "temperature", False) for t in model.terms):
        span = float(np.ptp(data.temperature))
        if span < MIN_TEMPERATURE_SPAN_C:
            names = list(model.param_names)
            thermal = [i for i, n in enumerate(names) if n.startswith(("Ks", "Ko"))]
            sd = np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0, None))
            ko = [i for i in thermal if names[i].startswith("Ko")]
            worst = (f" (Ko sd up to {float(sd[:, ko].max()):.3g} uT/C)" if ko else "")
            out.append(f"The training temperature spans only {span:.3g} C: the thermal terms Ks and Ko are "
                       f"extrapolated from it{worst}, and every calibrated value at another temperature rests on "
                       f"that extrapolation. Record over a wider temperature range, or fit without them ([physics] "
                       f"temperature_terms = false).")
    return tuple(out)


def _design_notes(data, model: PhysicsModel) -> tuple[str, ...]:
    """Plain-language facts about the design that limit what the data can identify."""
    notes = []
    temp_terms = any(getattr(t, "temperature", False) for t in model.terms)
    if not temp_terms:
        return ()
    runs = np.unique(data.run)
    t_std = np.array([data.temperature[data.run == r].std() for r in runs])
    varying = runs[t_std > max(0.5, 0.2 * t_std.max())] if t_std.max() > 0 else runs[:0]
    if 0 < varying.size < runs.size:
        sel = np.isin(data.run, varying)
        b = data.b_meas[sel]
        held = b.std(axis=0) < 0.02 * (np.abs(data.b_meas).max(axis=0) + 1e-12) + 0.5
        if held.all():
            mean = b.mean(axis=0)
            tm = float(data.temperature.mean())
            centred = abs(float(getattr(model, "t0", 0.0)) - tm) < 0.05 * max(float(np.ptp(data.temperature)), 1e-9)
            separate = "eparating Ks_j needs temperature varied while field axis j is swept."
            advice = (f" S{separate}" if centred else      # t0 is already the mean: no advice to set it
                      f" Set [physics] t0 = \"mean\" (the training mean temperature, {tm:.1f} C here): it removes the "
                      f"S-Ks and O-Ko correlations; s{separate}")
            notes.append(
                f"Temperature varies only in run(s) {varying.tolist()}, and there the measured field is held near "
                f"({mean[0]:.1f}, {mean[1]:.1f}, {mean[2]:.1f}) uT. The data then identify only the total thermal "
                f"slope Ks_x*{mean[0]:.1f} + Ks_y*{mean[1]:.1f} + Ks_z*{mean[2]:.1f} + Ko per axis; the individual "
                f"Ks and Ko, and S with O at the reference temperature, are near-collinear.{advice}"
            )
        elif held.any():
            ax = [AXES[i] for i in np.flatnonzero(held)]
            notes.append(f"Where temperature varies (run(s) {varying.tolist()}), field axis/axes {ax} are held "
                         f"constant, so their Ks coefficients are confounded with Ko.")
    return tuple(notes)


@dataclasses.dataclass(frozen=True)
class _Problem:
    model: PhysicsModel

    def solve(self, theta0, inputs, y):
        def one(th0, yy):
            return levenberg_marquardt(lambda th: yy - self.model.predict(th, inputs), th0)
        return jax.vmap(one)(theta0, y.T)

    def jacobian(self, theta, inputs):
        return jax.vmap(jax.jacfwd(self.model.predict), in_axes=(0, None))(theta, inputs)


_solve_jit = jax.jit(lambda prob, th0, inputs, y: prob.solve(th0, inputs, y), static_argnums=0)

@functools.partial(jax.jit, static_argnums=0)
def _solve_folds_jit(model, th0, inputs, y, weights):
    """LM per fold and axis: rows of weight 0 leave the fit (same shapes for every fold: one compile)."""
    def one(th, yy, w):
        return levenberg_marquardt(lambda t: w * (yy - model.predict(t, inputs)), th)

    per_axis = jax.vmap(one, in_axes=(0, 1, None))
    return jax.vmap(per_axis, in_axes=(None, None, 0))(th0, y, weights)


def fit_folds(data, model: PhysicsModel, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Refit ``model`` on subsets of ``data``'s rows, all folds in one compiled, vmapped LM.

    ``keep``: (F, n) bool, the rows each fold fits. Rows left out get weight 0, so every fold
    has the full data's shapes (no recompilation per fold; time-series transforms still see the
    whole record). Returns ``theta`` (F, 3, p) and ``ok`` (F,): converged on every axis and the
    kept rows inform every parameter (:func:`unidentifiable`); use ``theta[f]`` only where
    ``ok[f]``.
    """
    from bayesmag._src.core.physics import inputs_from_data

    th0 = jnp.asarray(model.init_params_all(), dtype=jnp.float64)
    model, inputs = centred(model, inputs_from_data(data))          # one program for every T0
    keep = np.asarray(keep, bool)
    sol = _solve_folds_jit(model, th0, inputs, jnp.asarray(data.b_ref), jnp.asarray(keep, jnp.float64))
    theta = np.asarray(sol.theta)
    conv = np.asarray(sol.result) == RESULTS.index("converged")
    # rows left out are zeroed, not removed: zero rows change neither the column norms nor the singular
    # vectors, so every fold and axis is one (n, p) matrix and the rank checks are one batched SVD
    J = np.asarray(_fold_jac_jit(_Problem(model), jnp.asarray(theta), inputs, jnp.asarray(keep, jnp.float64)))
    ok = conv.all(axis=1) & ~rank_deficient(J).any(axis=1)
    return theta, ok


@functools.partial(jax.jit, static_argnums=0)
def _fold_jac_jit(prob, theta, inputs, weights):
    """Jacobians (F, 3, n, p) of every fold and axis, the left-out rows zeroed."""
    return jax.vmap(lambda th, w: prob.jacobian(th, inputs) * w[None, :, None])(theta, weights)


def rank_deficient(J: np.ndarray, *, rtol: float = RANK_RTOL) -> np.ndarray:
    """:func:`unidentifiable` as a yes/no over a stack of Jacobians ``(..., n, p)``, one batched SVD."""
    J = np.asarray(J, dtype=np.float64)
    norm = np.linalg.norm(J, axis=-2, keepdims=True)
    zero = (norm <= np.finfo(np.float64).tiny).any(axis=(-2, -1))
    sv = np.linalg.svd(J / np.where(norm > 0, norm, 1.0), compute_uv=False)
    return zero | (sv.min(axis=-1) < rtol * sv.max(axis=-1))

_jac_jit = jax.jit(lambda prob, th, inputs: prob.jacobian(th, inputs), static_argnums=0)


def physics_jacobian(model: PhysicsModel, theta, inputs: Inputs) -> np.ndarray:
    """(3, n, p) Jacobian of each axis's prediction at ``theta`` (3, p); one compiled program for every T0."""
    model, inputs = centred(model, inputs)
    return np.asarray(_jac_jit(_Problem(model), jnp.asarray(theta), inputs))


def _refuse_unidentifiable(J: np.ndarray, names: tuple[str, ...]) -> None:
    from bayesmag._src.core.data import DataError
    found = {}
    for a, ax in enumerate(AXES):
        bad, ratio = unidentifiable(J[a], names)
        if bad:
            found.setdefault(f"{bad} (smallest relative singular value {ratio:.2g} < {RANK_RTOL:.2g})", []).append(ax)
    msgs = [f"axis {', '.join(axes)}: {what}" for what, axes in found.items()]
    if msgs:
        raise DataError("The data cannot inform these parameters (the Jacobian is rank-deficient): "
                        + "; ".join(msgs) + ". Their standard errors would be meaningless. Usually a measured "
                        "field axis or the temperature is constant (or zero) in the training rows: vary every "
                        "field axis, or drop the terms (e.g. [physics] temperature_terms = false).")


def _refuse_unsupported(model: PhysicsModel, theta: np.ndarray, cov: np.ndarray, time) -> None:
    """Refuse input transforms whose fitted parameters describe no effect of the data
    (:meth:`~bayesmag._src.core.physics.InputTransform.unsupported`: a thermal lag shorter than one sample)."""
    from bayesmag._src.core.data import DataError
    dt = median_step(time)
    if dt is None:
        return
    sl = model._slices()[len(model.terms):]
    msgs = []
    for tr, s in zip(model.transforms, sl):
        for a, ax in enumerate(AXES):
            why = tr.unsupported(np.asarray(theta[a, s]), np.sqrt(np.maximum(np.diag(cov[a])[s], 0.0)), dt)
            if why:
                msgs.append(f"{tr.name} on axis {ax}: {why}")
    if msgs:
        raise DataError("The model holds an effect these data do not: " + "; ".join(msgs) + ". Its parameters "
                        "and their uncertainty would be meaningless. Drop it from [physics] extra_terms "
                        "(`bayesmag discover` tests whether the data hold it).")


def fit_physics(data, model: PhysicsModel | None = None, *, covariance_method: str = "white",
                theta0: np.ndarray | None = None, check_rank: bool = True, columns: dict | None = None,
                field_unit: str | None = None, temperature_unit: str = "C", keep=None) -> PhysicsFit:
    """Fit ``model`` row-wise (each output axis separately) by Levenberg-Marquardt; returns a :class:`PhysicsFit`.

    Args:
      data: :class:`~bayesmag.CalibrationData` with a reference, a pandas DataFrame (canonical names or
        ``columns``) or a NumPy array (n, 7) in the order ``data.ARRAY_COLUMNS``
        (``bx_meas, by_meas, bz_meas, temperature, bx_ref, by_ref, bz_ref``). Time is not used:
        repeated timestamps are fine.
      columns, field_unit, temperature_unit: as ``frames.as_calibration_data``: the field is checked to
        be in uT (nT, mT, gauss refused) and the temperature in C (kelvin refused) unless a unit is
        declared (then converted).
      model: defaults to the paper's thermo-affine model.
      covariance_method: ``"white"``, ``"ar1"`` or ``"newey_west"`` (module docstring).
      theta0: optional (3, p) starting point (default: identity gain, zero elsewhere).
      check_rank: refuse (:class:`~bayesmag.DataError`) a rank-deficient Jacobian, naming the parameters
        the data cannot inform (:func:`unidentifiable`).
      keep: optional (n,) bool, the rows the fit uses; the others are held out (a split's test blocks) but
        stay in the series that input transforms (a thermal lag) see, as :func:`fit_folds`' folds do: fitted on
        the kept rows alone, a lag would run across each held-out block as if the temperature had stopped there
        (a 90 s lag fitted as 121 s, y residual 0.30 uT against 0.05). Statistics (``n``, ``s2``, covariance,
        rank) are those of the kept rows.
    """
    from bayesmag._src.core.physics import inputs_from_data

    from bayesmag._src.core.frames import as_calibration_data

    data = as_calibration_data(data, columns=columns, field_unit=field_unit, temperature_unit=temperature_unit,
                               require_reference=True, what="the data given to fit_physics")
    model = model or PhysicsModel.paper()
    inputs = inputs_from_data(data)
    y = jnp.asarray(data.b_ref)
    th0 = jnp.asarray(model.init_params_all() if theta0 is None else theta0, dtype=jnp.float64)
    model_c, inputs_c = centred(model, inputs)                          # one program for every T0
    prob = _Problem(model_c)
    if keep is None:
        sol = _solve_jit(prob, th0, inputs_c, y)
    else:
        keep = np.asarray(keep, bool)
        if keep.shape != (data.n,) or keep.sum() <= model.n_params:
            raise ValueError(f"keep must be an ({data.n},) bool mask of more than {model.n_params} rows.")
        sol = _solve_folds_jit(model_c, th0, inputs_c, y, jnp.asarray(keep[None], jnp.float64))
        sol = jax.tree_util.tree_map(lambda a: a[0], sol)
    theta = np.asarray(sol.theta)
    J = np.asarray(_jac_jit(prob, jnp.asarray(theta), inputs_c))          # (3, n, p)
    pred = np.asarray(model.predict_all(jnp.asarray(theta), inputs))
    resid = np.asarray(data.b_ref) - pred
    if keep is not None:
        J, resid, data = J[:, keep], resid[keep], data.subset(np.flatnonzero(keep))
    if check_rank:
        _refuse_unidentifiable(J, model.param_names)
    covs, infos, diags = [], [], []
    for a in range(3):
        c, info = covariance(J[a], resid[:, a], method=covariance_method, run=data.run)
        if covariance_method == "white" and data.n > 4 * model.n_params:
            # what the white covariance's independence costs: the autocorrelation-consistent sds against its own
            # (the certificate states the range when the residuals are correlated)
            c_nw, nw = covariance(J[a], resid[:, a], method="newey_west", run=data.run)
            ratio = np.sqrt(np.maximum(np.diag(c_nw), 0.0) / np.maximum(np.diag(c), 1e-300))
            info["newey_west_sd_ratio"] = [float(ratio.min()), float(ratio.max())]
            info["newey_west_lags"] = int(nw["lags"])
        covs.append(0.5 * (c + c.T))     # exactly symmetric (what is saved and what the loader checks)
        infos.append(info)
        diags.append(identifiability(c, model.param_names))
    if check_rank and model.transforms:
        _refuse_unsupported(model, theta, np.stack(covs), data.time)
    return PhysicsFit(
        model=model, theta=theta, cov=np.stack(covs), s2=np.array([i["s2"] for i in infos]), n=data.n,
        rmse_in_sample=np.sqrt(np.mean(resid**2, axis=0)),
        result=tuple(RESULTS[int(r)] for r in np.asarray(sol.result)), n_steps=np.asarray(sol.n_steps),
        covariance_method=covariance_method, cov_info=tuple(infos), diagnostics=tuple(diags),
        design_notes=_design_notes(data, model), design_warnings=_design_warnings(data, model, np.stack(covs), resid),
    )
