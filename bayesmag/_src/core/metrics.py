r"""Accuracy, calibration and sharpness metrics for any predictions.

Point metrics take arrays; probabilistic ones take a :class:`~bayesmag.likelihoods.Likelihood`
whose batch shape matches ``y``. Reductions run over ``axis`` (default 0, the rows), so an
``(n, 3)`` input gives one value per field axis; results are Python floats for scalars and
float64 NumPy arrays otherwise (ready for ``json``).

References:
    Gneiting, T., Balabdaoui, F. & Raftery, A. E. (2007). Probabilistic forecasts,
    calibration and sharpness. JRSS B 69(2), 243-268.
    Gneiting, T. & Raftery, A. E. (2007). Strictly proper scoring rules, prediction, and
    estimation. JASA 102(477), 359-378.
    Shetty, D. K. & Marndi, A. (2026). Metrology 6(3), 45, sec. 4.4 (paired squared-error test).
"""

from __future__ import annotations

from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

from bayesmag._src.core.likelihoods import Likelihood

__all__ = ["rmse", "mae", "coverage", "interval_width", "nll", "crps", "pit",
           "calibration_curve", "paired_test", "score", "score_per_axis", "summarize", "SCORE_KEYS",
           "DEFAULT_LEVELS", "magnitude_residual", "heading_deg", "heading_error_deg", "field_metrics",
           "MIN_HORIZONTAL_UT"]

#: Default nominal levels of :func:`calibration_curve`: 0.05, 0.10, ..., 0.95 and 0.99.
DEFAULT_LEVELS = np.append(np.linspace(0.05, 0.95, 19), 0.99)
DEFAULT_LEVELS.setflags(write=False)

Axis = int | tuple[int, ...] | None


def _f64(x: Any) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def _out(x: np.ndarray) -> float | np.ndarray:
    x = np.asarray(x)
    return float(x) if x.ndim == 0 else x


def _same_shape(**arrays: np.ndarray) -> None:
    shapes = {k: np.shape(v) for k, v in arrays.items()}
    if len(set(shapes.values())) > 1:
        raise ValueError(f"inputs must have the same shape, got {shapes}")


def _prep(dist: Any, y: Any) -> jax.Array:
    """Check ``dist`` against ``y``; return ``y`` in the distribution's dtype."""
    if not isinstance(dist, Likelihood):
        raise TypeError(f"dist must be a Likelihood, got {type(dist).__name__}")
    if tuple(dist.batch_shape) != np.shape(y):
        raise ValueError(f"dist batch shape {tuple(dist.batch_shape)} does not match y shape {np.shape(y)}")
    return jnp.asarray(y, jnp.result_type(*jax.tree.leaves(dist), 1.0))


def rmse(y: Any, yhat: Any, axis: Axis = 0) -> float | np.ndarray:
    r""":math:`\sqrt{\mathrm{mean}((y - \hat y)^2)}` over ``axis``."""
    y, yhat = _f64(y), _f64(yhat)
    _same_shape(y=y, yhat=yhat)
    return _out(np.sqrt(np.mean((y - yhat) ** 2, axis=axis)))


def mae(y: Any, yhat: Any, axis: Axis = 0) -> float | np.ndarray:
    r""":math:`\mathrm{mean}|y - \hat y|` over ``axis``."""
    y, yhat = _f64(y), _f64(yhat)
    _same_shape(y=y, yhat=yhat)
    return _out(np.mean(np.abs(y - yhat), axis=axis))


def coverage(y: Any, lower: Any, upper: Any, axis: Axis = 0) -> float | np.ndarray:
    """Fraction of ``y`` inside the closed interval ``[lower, upper]`` over ``axis``."""
    y, lower, upper = _f64(y), _f64(lower), _f64(upper)
    _same_shape(y=y, lower=lower, upper=upper)
    return _out(np.mean((y >= lower) & (y <= upper), axis=axis))


def interval_width(lower: Any, upper: Any, axis: Axis = 0) -> float | np.ndarray:
    """Mean width ``upper - lower`` over ``axis`` (sharpness; smaller is sharper)."""
    lower, upper = _f64(lower), _f64(upper)
    _same_shape(lower=lower, upper=upper)
    return _out(np.mean(upper - lower, axis=axis))


def nll(dist: Likelihood, y: Any, axis: Axis = 0) -> float | np.ndarray:
    """Mean negative log-likelihood ``dist.nll(y)`` over ``axis``."""
    y = _prep(dist, y)
    return _out(np.mean(_f64(dist.nll(y)), axis=axis))


def crps(dist: Likelihood, y: Any, axis: Axis = 0) -> float | np.ndarray:
    """Mean closed-form CRPS ``dist.crps(y)`` over ``axis`` (same units as ``y``)."""
    y = _prep(dist, y)
    return _out(np.mean(_f64(dist.crps(y)), axis=axis))


def pit(dist: Likelihood, y: Any) -> np.ndarray:
    """Probability integral transform ``F(y)`` per element; uniform on (0, 1) when calibrated."""
    y = _prep(dist, y)
    return _f64(dist.pit(y))


def calibration_curve(dist: Likelihood, y: Any, levels: Sequence[float] | None = None,
                      axis: Axis = 0) -> tuple[np.ndarray, np.ndarray]:
    r"""Observed coverage of central intervals against their nominal level.

    ``y`` lies in the central interval of level :math:`\ell` iff its PIT satisfies
    :math:`|F(y) - 1/2| \le \ell/2`, so one CDF evaluation serves every level.

    Args:
        dist: predictive distribution with batch shape ``y.shape``.
        y: observations.
        levels: nominal levels in (0, 1); default :data:`DEFAULT_LEVELS` (20 levels).
        axis: axes to average over (``None``: all).

    Returns:
        ``(nominal, observed)``: ``nominal`` has shape ``(L,)``; ``observed`` has shape ``(L,)``
        plus the axes left after reducing over ``axis``. Perfect calibration is the diagonal.
    """
    nominal = _f64(DEFAULT_LEVELS if levels is None else levels)
    if nominal.ndim != 1 or not np.all((nominal > 0) & (nominal < 1)):
        raise ValueError(f"levels must be a 1-D sequence in (0, 1), got {levels}")
    dev = np.abs(pit(dist, y) - 0.5)
    inside = dev[None] <= 0.5 * nominal.reshape((-1,) + (1,) * dev.ndim)
    axes = range(dev.ndim) if axis is None else np.atleast_1d(axis)
    return nominal, np.mean(inside, axis=tuple(int(a) % dev.ndim + 1 for a in axes))


def paired_test(err_a: Any, err_b: Any, axis: int = 0) -> dict[str, Any]:
    r"""Paired t-test on squared errors, :math:`d = e_a^2 - e_b^2` (Shetty & Marndi 2026, sec. 4.4).

    :math:`H_0: E[d] = 0` against :math:`H_1: E[d] > 0` ("b is better"; a = physics,
    b = hybrid). With :math:`\bar d`, sample sd :math:`s_d` and :math:`n` pairs,

    .. math::  t = \frac{\bar d}{s_d/\sqrt n},\quad \mathrm{CI}_{95} = \bar d \pm
               t_{0.975,\,n-1}\, s_d/\sqrt n,\quad d_{\mathrm{Cohen}} = \bar d / s_d .

    Args:
        err_a, err_b: paired errors of the same shape, pairs along ``axis``.

    Returns:
        dict with ``mean_diff``, ``t``, ``p`` (one-sided), ``p_two_sided``, ``ci95``
        (``[lo, hi]``), ``cohens_d`` and ``n``; floats for 1-D inputs, arrays (one entry per
        remaining index, ``ci95`` of shape ``(2, ...)``) otherwise.
    """
    a, b = _f64(err_a), _f64(err_b)
    _same_shape(err_a=a, err_b=b)
    if a.ndim == 0:
        raise ValueError("paired_test needs at least one axis of pairs")
    n = a.shape[axis]
    if n < 2:
        raise ValueError(f"paired_test needs at least 2 pairs, got {n}")
    d = a ** 2 - b ** 2
    mean = np.mean(d, axis=axis)
    sd = np.std(d, axis=axis, ddof=1)
    se = sd / np.sqrt(n)
    t = mean / se
    dof = n - 1
    half = scipy.stats.t.ppf(0.975, dof) * se
    return {
        "mean_diff": _out(mean),
        "t": _out(t),
        "p": _out(scipy.stats.t.sf(t, dof)),
        "p_two_sided": _out(2.0 * scipy.stats.t.sf(np.abs(t), dof)),
        "ci95": [_out(mean - half), _out(mean + half)] if np.ndim(mean) == 0
        else np.stack([mean - half, mean + half]),
        "cohens_d": _out(mean / sd),
        "n": int(n),
    }


#: The keys of :func:`score`, in order.
SCORE_KEYS = ("rmse", "mae", "coverage", "nll", "crps", "mean_width")


def score(y: Any, dist: Likelihood, level: float = 0.95, *, mean: Any = None) -> dict[str, np.ndarray]:
    """The one scorer: ``rmse``, ``mae`` (of ``mean``, default ``dist.mean``), ``coverage`` and
    ``mean_width`` of the central ``level`` interval, ``nll`` and ``crps`` of ``dist``, each
    reduced over the rows (axis 0) of ``y``.
    """
    y = _f64(y)
    _prep(dist, y)
    lower, upper = (_f64(v) for v in dist.interval(level))
    mean = _f64(dist.mean if mean is None else mean)
    return {"rmse": rmse(y, mean), "mae": mae(y, mean), "coverage": coverage(y, lower, upper),
            "nll": nll(dist, y), "crps": crps(dist, y), "mean_width": interval_width(lower, upper)}


def score_per_axis(y: Any, dist: Likelihood, level: float = 0.95, *, mean: Any = None,
                   axes: Sequence[str] = ("x", "y", "z")) -> dict[str, dict[str, float]]:
    """:func:`score` of ``(n, k)`` arrays as ``{metric: {axis: float}}`` (the layout of metrics.json)."""
    y = _f64(y)
    if y.ndim != 2 or y.shape[1] != len(axes):
        raise ValueError(f"scores need y of shape (n, {len(axes)}), got {y.shape}")
    return {k: {ax: float(v[i]) for i, ax in enumerate(axes)} for k, v in score(y, dist, level, mean=mean).items()}


def summarize(y: Any, dist: Likelihood, level: float = 0.95,
              axes: Sequence[str] = ("x", "y", "z")) -> dict[str, dict[str, float]]:
    """Per-axis ``rmse``, ``mae`` (of ``dist.mean``), ``coverage`` and ``width`` of the central
    ``level`` interval, ``nll`` and ``crps`` for ``(n, k)`` arrays, keyed by ``axes``
    (:func:`score`, transposed; ``mean_width`` named ``width``).

    Returns plain floats, e.g. ``{"x": {"rmse": ..., ...}, "y": {...}, "z": {...}}``.
    """
    y = _f64(y)
    if y.ndim != 2 or y.shape[1] != len(axes):
        raise ValueError(f"summarize needs y of shape (n, {len(axes)}), got {y.shape}")
    per = score(y, dist, level)
    names = {"mean_width": "width"}
    order = ("rmse", "mae", "coverage", "mean_width", "nll", "crps")
    return {ax: {names.get(k, k): float(per[k][i]) for k in order} for i, ax in enumerate(axes)}


# --------------------------------------------------------------------------- field metrics

#: Rows whose horizontal reference field is weaker than this (uT) have no usable heading.
MIN_HORIZONTAL_UT = 5.0


def magnitude_residual(b_cal: Any, b_ref: Any) -> np.ndarray:
    r"""Per row :math:`|B_{\mathrm{cal}}| - |B_{\mathrm{ref}}|` (uT) of ``(n, 3)`` fields."""
    b_cal, b_ref = _f64(b_cal), _f64(b_ref)
    _same_shape(b_cal=b_cal, b_ref=b_ref)
    return np.linalg.norm(b_cal, axis=-1) - np.linalg.norm(b_ref, axis=-1)


def heading_deg(b: Any) -> np.ndarray:
    r"""Compass heading (degrees, [0, 360)) of a level sensor, x forward, y right, z down:
    :math:`\psi = \mathrm{atan2}(-B_y, B_x)`; only the horizontal components count."""
    b = _f64(b)
    return np.mod(np.degrees(np.arctan2(-b[..., 1], b[..., 0])), 360.0)


def heading_error_deg(b_cal: Any, b_ref: Any) -> np.ndarray:
    """Per row heading(calibrated) - heading(reference), wrapped into [-180, 180) degrees."""
    d = heading_deg(b_cal) - heading_deg(b_ref)
    return np.mod(d + 180.0, 360.0) - 180.0


def _summary(v: np.ndarray) -> dict[str, float]:
    a = np.abs(v)
    if v.size == 0:
        return {"n_rows": 0}
    return {"n_rows": int(v.size), "mean": float(v.mean()), "sd": float(v.std(ddof=1)) if v.size > 1 else 0.0,
            "rms": float(np.sqrt(np.mean(v**2))), "p95_abs": float(np.quantile(a, 0.95)), "max_abs": float(a.max())}


def field_metrics(b_cal: Any, b_ref: Any, run: Any, *, min_horizontal: float = MIN_HORIZONTAL_UT) -> dict:
    r"""What a compass or drone engineer signs off on: the field magnitude residual
    :math:`|B_{\mathrm{cal}}| - |B_{\mathrm{ref}}|` (uT) and the heading error (degrees, from the
    horizontal components, :func:`heading_error_deg`), overall and per run.

    Rows whose horizontal reference field is below ``min_horizontal`` uT are left out of the
    heading error (a heading of a near-vertical field is undefined) and counted.

    Returns:
        ``{"magnitude": {...}, "heading": {...}}``, each with ``n_rows``, ``mean``, ``sd``, ``rms``,
        ``p95_abs``, ``max_abs`` and ``per_run`` (the same per run); heading also ``n_excluded`` and
        ``min_horizontal_uT``.

    Example:
        >>> ref = np.array([[20.0, 0.0, 40.0]]); cal = np.array([[20.0, -20.0 * np.tan(np.radians(1)), 40.0]])
        >>> round(field_metrics(cal, ref, [1])["heading"]["max_abs"], 6)
        1.0
    """
    b_cal, b_ref, run = _f64(b_cal), _f64(b_ref), np.asarray(run)
    _same_shape(b_cal=b_cal, b_ref=b_ref)
    dm = magnitude_residual(b_cal, b_ref)
    ok = np.hypot(b_ref[:, 0], b_ref[:, 1]) >= min_horizontal
    dh = heading_error_deg(b_cal, b_ref)
    runs = [r for r in np.unique(run)]
    mag = {**_summary(dm), "per_run": {str(int(r)): _summary(dm[run == r]) for r in runs}}
    head = {**_summary(dh[ok]), "n_excluded": int((~ok).sum()), "min_horizontal_uT": float(min_horizontal),
            "per_run": {str(int(r)): _summary(dh[ok & (run == r)]) for r in runs}}
    return {"magnitude": mag, "heading": head}
