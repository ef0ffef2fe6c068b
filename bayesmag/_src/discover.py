r"""Discovery of missing physics: locate structure in the physics residuals, name it, model it.

Three stages, per output axis (x, y, z):

1. **Locate** (:func:`locate`). Fit the current physics model and look for structure in
   its residuals against each input (reference field components, :math:`|B|`,
   temperature), the rates of change of field and temperature, the direction of travel,
   run, time, and a periodogram. Each variable's share of the residual variance is the
   :math:`R^2` of the residual's binned means; its p-value comes from a *block*
   permutation of the residual (blocks longer than its correlation length), so
   autocorrelated noise is not mistaken for structure.
2. **Name** (:func:`select`). Every catalogue extension
   (:mod:`bayesmag._src.catalogue`) is added to the model in turn; nonlinear parameters
   (thermal time constant, timing delay, hysteresis threshold) are profiled on a grid,
   chosen on the training rows only. A candidate is accepted on an axis only if it

   * lowers the out-of-sample squared error (cross-validation by contiguous time blocks
     or by run) by at least :data:`MIN_GAIN` of the residual variance, with a one-sided
     block z-score :math:`\ge` :data:`Z_MIN` (block sums of the loss differences, AR(1)
     variance inflation), and
   * lowers the BIC computed with the effective sample size
     :math:`n_\mathrm{eff} = n (1-\rho_1)/(1+\rho_1)` by at least :data:`DBIC_MIN`.

   The best accepted candidate is added and the search repeats (forward selection, at most
   :data:`MAX_TERMS` per axis). Accepted candidates whose out-of-sample losses cannot be
   told apart from the chosen one (pairwise block z < :data:`Z_DISTINCT`) and that are not
   selected later are reported as *indistinguishable* alternatives.
3. **Model** (:func:`discover`). The selected extensions are refitted per axis by
   Levenberg-Marquardt (nonlinear parameters included) with Newey-West standard errors;
   before/after scores are computed out of sample; the residuals of the final model are
   located again, and structure that remains is reported as *unexplained*, described by
   where it is and its shape.

Run ``python -m bayesmag._src.discover CONFIG`` or ``... --data FILE.csv --out DIR``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time as _time
from pathlib import Path
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from . import catalogue as C
from .data import AXES, CalibrationData, load_csv
from .fit import covariance, lag1_autocorrelation, levenberg_marquardt
from .physics import InputTransform, Inputs, PhysicsModel, Term, ThermoAffine, inputs_from_data

__all__ = ["discover", "DiscoveryResult", "DiscoverOptions", "locate", "load_discover_config", "main",
           "Z_MIN", "MIN_GAIN", "DBIC_MIN", "LOCATE_P", "LOCATE_FRACTION"]

#: One-sided block z-score of the out-of-sample gain needed to accept a candidate
#: (p ~ 1.3e-3 per test; ~24 tests per recording keeps the clean-data false-discovery rate ~3 %).
Z_MIN = 3.0
#: Smallest out-of-sample gain (fraction of the residual mean square) worth reporting.
MIN_GAIN = 0.01
#: BIC (effective n) must drop by at least this much ("very strong" on Kass & Raftery's scale).
DBIC_MIN = 10.0
#: Two accepted candidates whose out-of-sample losses differ by less than this block z are indistinguishable.
Z_DISTINCT = 2.0
#: Most extensions added per axis.
MAX_TERMS = 3
#: A located mismatch needs a block-permutation p-value <= LOCATE_P ...
LOCATE_P = 0.002
#: ... and must hold at least this fraction of the residual variance.
LOCATE_FRACTION = 0.02
#: Structure left after the final model is reported as unexplained above this share of the residual variance.
UNEXPLAINED_FRACTION = 0.05
#: Permutations for the locate p-values (smallest attainable p = 1/(N_PERM+1)).
N_PERM = 499
#: Candidates fitted on fewer training rows than this many per parameter are skipped.
ROWS_PER_PARAM = 10

#: Systematic (type-B) standard uncertainty of a timing offset from linear interpolation of the
#: readings, as a fraction of the sampling step (noise-free simulations: |bias| <= dt/10).
DELTA_SYS_FRACTION = 0.1
TIME_DOMAIN = ("thermal_lag", "timing_offset", "offset_drift")
THERMAL = ("thermal_lag", "temperature_quadratic")


# --------------------------------------------------------------------------- options


@dataclasses.dataclass(frozen=True)
class DiscoverOptions:
    """Settings of :func:`discover` (the ``[discover]`` table of a config).

    Attributes:
      candidates: catalogue names to try (default: all of :data:`~bayesmag._src.catalogue.CATALOGUE`).
      cv: out-of-sample scheme, ``"time_blocks"`` (contiguous blocks inside every run,
        assigned to ``n_folds`` folds) or ``"by_run"`` (leave one run out).
      n_folds: folds for ``"time_blocks"``.
      block_s: length of a time block in seconds (default: 1/60 of the record, >= 10 rows).
      t0: reference temperature of the base model, or ``"mean"``.
      max_terms: most extensions per axis.
      seed: seeds the permutations.
      figures: write figures.
      time_available: whether ``data.time`` holds real time stamps (None: inferred; a time
        column equal to the row index counts as absent).
    """

    candidates: tuple[str, ...] | None = None
    cv: str = "time_blocks"
    n_folds: int = 5
    block_s: float | None = None
    t0: float | str = "mean"
    max_terms: int = MAX_TERMS
    seed: int = 0
    figures: bool = True
    time_available: bool | None = None

    def __post_init__(self):
        if self.candidates is not None:
            object.__setattr__(self, "candidates", tuple(self.candidates))
            unknown = sorted(set(self.candidates) - set(C.CATALOGUE))
            if unknown:
                raise ValueError(f"discover candidates {unknown} are not in the catalogue; valid: {sorted(C.CATALOGUE)}.")
        if self.cv not in ("time_blocks", "by_run"):
            raise ValueError(f"discover cv is {self.cv!r}; it must be one of ['time_blocks', 'by_run'].")
        if int(self.n_folds) < 2:
            raise ValueError(f"discover n_folds is {self.n_folds!r}; it must be >= 2.")
        if isinstance(self.t0, str) and self.t0 != "mean":
            raise ValueError(f"discover t0 is {self.t0!r}; it must be a number or 'mean'.")
        if int(self.max_terms) < 1:
            raise ValueError(f"discover max_terms is {self.max_terms!r}; it must be >= 1.")


# --------------------------------------------------------------------------- helpers


def _run_starts(run):
    return np.concatenate([[True], run[1:] != run[:-1]])


def _smooth_rate(x: np.ndarray, time: np.ndarray, run: np.ndarray, half: int) -> np.ndarray:
    """Central difference over +-half rows inside each run (per second)."""
    out = np.zeros_like(x, dtype=np.float64)
    bounds = np.flatnonzero(np.concatenate([_run_starts(run), [True]]))
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        m = hi - lo
        if m < 3:
            continue
        i = np.arange(m)
        a, b = np.clip(i - half, 0, m - 1), np.clip(i + half, 0, m - 1)
        dt = time[lo:hi][b] - time[lo:hi][a]
        dx = x[lo:hi][b] - x[lo:hi][a]
        out[lo:hi] = np.where(dt > 0, dx / np.where(dt > 0, dt, 1.0), 0.0)
    return out


def _lstsq(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares by normal equations on column-scaled X (eigen-solve; rank-deficiency safe)."""
    s = np.sqrt((X * X).sum(0))
    s = np.where(s > 0, s, 1.0)
    Xs = X / s
    return _solve_sym(Xs.T @ Xs, Xs.T @ y) / s


def _block_ids(data: CalibrationData, block_rows: int) -> np.ndarray:
    """Contiguous blocks of about ``block_rows`` rows inside each run, numbered globally."""
    ids = np.empty(data.n, dtype=np.int64)
    bounds = np.flatnonzero(np.concatenate([_run_starts(data.run), [True]]))
    nxt = 0
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        k = max(1, int(round((hi - lo) / block_rows)))
        ids[lo:hi] = nxt + (np.arange(hi - lo) * k) // (hi - lo)
        nxt += k
    return ids


def _block_z(d: np.ndarray, blocks: np.ndarray, e: np.ndarray | None = None) -> float:
    """One-sided z that the block sums of ``d`` are centred above 0.

    Wilcoxon signed-rank statistic of the block sums (robust to the heavy right tail of loss
    gains). Blocks are chosen longer than the residual's correlation length (:func:`_folds`),
    so block sums are close to independent under the null; ``e`` is unused (kept for API)."""
    sums = np.bincount(blocks, weights=d)
    counts = np.bincount(blocks)
    keep = counts > 0
    sums = sums[keep]
    nz = sums[sums != 0]
    if nz.size < 3:
        return 0.0
    r = stats.rankdata(np.abs(nz)) * np.sign(nz)
    z = float(r.sum() / np.sqrt((r * r).sum()))
    return z


# --------------------------------------------------------------------------- locate


@dataclasses.dataclass(frozen=True)
class _Variable:
    name: str
    label: str          # for sentences
    unit: str
    values: np.ndarray
    categorical: bool = False


def _variables(data: CalibrationData, time_ok: bool) -> list[_Variable]:
    ref = data.b_ref
    dt = np.median(np.diff(data.time)[~_run_starts(data.run)[1:]]) if data.n > 1 else 1.0
    half_b = 2
    half_t = max(2, int(round(10.0 / max(dt, 1e-9)))) if time_ok else 8
    out = []
    for k, ax in enumerate(AXES):
        out.append(_Variable(f"B{ax}", f"B{ax}", "uT", ref[:, k]))
    out.append(_Variable("|B|", "|B|", "uT", np.linalg.norm(ref, axis=1)))
    out.append(_Variable("T", "temperature", "C", data.temperature))
    unit_rate = "/s" if time_ok else "/row"
    rates = np.stack([_smooth_rate(ref[:, k], data.time, data.run, half_b) for k in range(3)], 1)
    for k, ax in enumerate(AXES):
        out.append(_Variable(f"dB{ax}/dt", f"rate of change of B{ax}", f"uT{unit_rate}", rates[:, k]))
    out.append(_Variable("dT/dt", "rate of change of temperature", f"C{unit_rate}",
                         _smooth_rate(data.temperature, data.time, data.run, half_t)))
    for k, ax in enumerate(AXES):
        thr = 3.0 * (np.median(np.abs(rates[:, k])) + 1e-9)
        sign = np.where(np.abs(rates[:, k]) > thr, np.sign(rates[:, k]), 0.0)
        held = _hold_last_np(sign, sign != 0, data.run)
        out.append(_Variable(f"dir{ax}", f"direction of travel of B{ax}", "", held, categorical=True))
    if np.unique(data.run).size > 1:
        out.append(_Variable("run", "run", "", data.run.astype(np.float64), categorical=True))
    out.append(_Variable("time", "time", "s" if time_ok else "row", data.time))
    return out


def _hold_last_np(value, has_value, run):
    starts = _run_starts(run)
    idx = np.where(has_value | starts, np.arange(value.size), 0)
    idx = np.maximum.accumulate(idx)
    return np.where(has_value, value, 0.0)[idx]


def _bins(v: _Variable, n_bins: int = 10) -> tuple[np.ndarray, list[str]]:
    if v.categorical:
        cats, idx = np.unique(v.values, return_inverse=True)
        return idx.reshape(-1), [f"{c:g}" for c in cats]
    edges = np.unique(np.quantile(v.values, np.linspace(0, 1, n_bins + 1)))
    if edges.size < 3:
        return np.zeros(v.values.size, dtype=np.int64), ["all"]
    idx = np.clip(np.searchsorted(edges, v.values, side="right") - 1, 0, edges.size - 2)
    labels = [f"{edges[i]:.3g}..{edges[i + 1]:.3g}" for i in range(edges.size - 1)]
    return idx, labels


def _block_length(r: np.ndarray) -> int:
    """Rows per permutation block: 5x the integrated autocorrelation time, at least 20."""
    r = r - r.mean()
    n = r.size
    f = np.fft.rfft(r, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[: min(n, 2000)]
    acf = acf / acf[0] if acf[0] > 0 else acf
    neg = np.flatnonzero(acf < 0.05)
    cut = int(neg[0]) if neg.size else acf.size
    tau = 1.0 + 2.0 * acf[1:cut].sum()
    return int(np.clip(5 * tau, 20, max(20, n // 20)))


def _block_perms(n: int, L: int, n_perm: int, rng: np.random.Generator) -> np.ndarray:
    starts = np.arange(0, n, L)
    out = np.empty((n_perm, n), dtype=np.int64)
    within = np.arange(L)
    for p in range(n_perm):
        idx = (starts[rng.permutation(starts.size)][:, None] + within).ravel()
        out[p] = idx[idx < n]
    return out


def _shape(means: np.ndarray, counts: np.ndarray, v: _Variable) -> str:
    if v.categorical or means.size < 4:
        return f"differs between values of {v.label}"
    x = np.arange(means.size, dtype=np.float64)
    w = counts / counts.sum()
    X1 = np.stack([np.ones_like(x), x], 1)
    X2 = np.stack([np.ones_like(x), x, (x - x.mean()) ** 2], 1)
    tot = float(w @ (means - w @ means) ** 2) + 1e-300
    r1 = 1 - float(w @ (means - X1 @ np.linalg.lstsq(X1 * np.sqrt(w)[:, None], means * np.sqrt(w), rcond=None)[0]) ** 2) / tot
    b2 = np.linalg.lstsq(X2 * np.sqrt(w)[:, None], means * np.sqrt(w), rcond=None)[0]
    r2 = 1 - float(w @ (means - X2 @ b2) ** 2) / tot
    if r1 > 0.8:
        return f"rises with {v.label}" if np.polyfit(x, means, 1, w=np.sqrt(w))[0] > 0 else f"falls with {v.label}"
    if r2 > 0.8:
        return f"is U-shaped in {v.label}" if b2[2] > 0 else f"is inverted-U in {v.label}"
    return f"varies irregularly (not a straight line or a parabola) with {v.label}"


def locate(data: CalibrationData, resid: np.ndarray, *, time_available: bool = True, n_perm: int = N_PERM,
           seed: int = 0, variables: list | None = None) -> list[dict]:
    """Structure in residuals ``resid`` (n, 3) of ``data``: one entry per axis and variable.

    Each entry: ``axis, variable, fraction`` (share of the residual variance held by the
    variable's binned means), ``p_value`` (block permutation), ``significant``, ``where``
    (the bin/group with the largest mean residual), ``shape`` and ``bin_means``; plus one
    ``periodic`` entry per axis when ``time_available``.
    """
    rng = np.random.default_rng(seed)
    variables = variables if variables is not None else _variables(data, time_available)
    out = []
    for a, ax in enumerate(AXES):
        r = np.asarray(resid[:, a], dtype=np.float64)
        r = r - r.mean()
        ss = float(r @ r) + 1e-300
        L = _block_length(r)
        perms = _block_perms(r.size, L, n_perm, rng)
        rp = r[perms]                                                     # (P, n)
        for v in variables:
            idx, labels = _bins(v)
            nb = len(labels)
            if nb < 2:
                continue
            G = np.zeros((r.size, nb))
            G[np.arange(r.size), idx] = 1.0
            counts = G.sum(0)
            sums = r @ G
            frac = float((sums**2 / counts).sum() / ss)
            psums = rp @ G
            pfrac = (psums**2 / counts).sum(1) / ss
            p = float((1 + np.sum(pfrac >= frac)) / (n_perm + 1))
            means = sums / counts
            k = int(np.argmax(np.abs(means)))
            where = (f"{v.label} = {labels[k]}" if v.categorical else f"{v.label} in {labels[k]} {v.unit}").strip()
            out.append({
                "axis": ax, "variable": v.name, "fraction": frac, "p_value": p,
                "significant": bool(p <= LOCATE_P and frac >= LOCATE_FRACTION),
                "where": where, "mean_there": float(means[k]), "shape": _shape(means, counts, v),
                "bin_labels": labels, "bin_means": means.tolist(), "block_rows": L,
            })
        if time_available:
            out.append(_periodic(r, data, ax))
    return out


def _periodic(r: np.ndarray, data: CalibrationData, ax: str) -> dict:
    """Sharpest periodogram line, whitened by the local median (red-noise robust)."""
    n = r.size
    same = ~_run_starts(data.run)[1:]
    dt = float(np.median(np.diff(data.time)[same])) if same.any() else 1.0
    # residual on a regular time grid (zeros in gaps keep the phase across runs), then FFT
    tt = data.time - data.time[0]
    slot = np.round(tt / dt).astype(np.int64)
    m = int(slot.max()) + 1
    if m > 50 * n:
        return {"axis": ax, "variable": "periodic", "fraction": 0.0, "p_value": 1.0, "significant": False,
                "where": "", "shape": "", "period_s": None}
    grid = np.zeros(m)
    np.add.at(grid, slot, r)
    P = np.abs(np.fft.rfft(grid)) ** 2
    f = np.fft.rfftfreq(m, d=dt)
    lo = 4                                                    # periods up to a quarter of the record
    P, f = P[lo:-1], f[lo:-1]
    if f.size < 60:
        return {"axis": ax, "variable": "periodic", "fraction": 0.0, "p_value": 1.0, "significant": False,
                "where": "", "shape": "", "period_s": None}
    half = 25
    pad = np.pad(P, half, mode="reflect")
    from numpy.lib.stride_tricks import sliding_window_view
    med = np.median(sliding_window_view(pad, 2 * half + 1), axis=1)[: P.size]
    score = P / (med / math.log(2) + 1e-300)
    k = int(np.argmax(score))
    p_one = math.exp(-float(score[k]))
    p_any = float(-np.expm1(P.size * np.log1p(-min(p_one, 1 - 1e-16))))
    tt = data.time
    df = float(f[1] - f[0]) if f.size > 1 else 0.0
    best = (-1.0, None, None)
    for freq in np.linspace(f[k] - 2 * df, f[k] + 2 * df, 81):       # refine on the real time axis
        if freq <= 0:
            continue
        X = np.stack([np.sin(2 * np.pi * freq * tt), np.cos(2 * np.pi * freq * tt)], 1)
        beta = np.linalg.lstsq(X, r, rcond=None)[0]
        fit = X @ beta
        frac = float(fit @ fit / (r @ r + 1e-300))
        if frac > best[0]:
            best = (frac, float(freq), beta)
    frac, freq, beta = best
    period = 1.0 / freq
    amp = float(np.hypot(*beta))
    return {"axis": ax, "variable": "periodic", "fraction": frac, "p_value": p_any,
            "significant": bool(p_any <= LOCATE_P and frac >= LOCATE_FRACTION),
            "where": f"periodic, about {period:.3g} s", "mean_there": amp,
            "shape": f"sinusoid of period {period:.3g} s and amplitude {amp:.3g} uT", "period_s": period}


# --------------------------------------------------------------------------- candidates


@dataclasses.dataclass(frozen=True)
class _Variant:
    """One concrete setting of a candidate: a catalogue component and its fixed nonlinear value."""

    name: str
    component: object
    nl: float | None = None      # log_tau or delta for transforms

    @property
    def n_params(self) -> int:
        return len(self.component.param_names()) - (1 if self.nl is not None else 0)

    @property
    def label(self) -> str:
        c = self.component
        if self.name == "thermal_lag":
            return f"thermal_lag(tau={math.exp(self.nl):.3g} s)"
        if self.name == "timing_offset":
            return f"timing_offset(delta={self.nl:.3g} s)"
        if self.name == "hysteresis":
            extra = f"threshold={c.threshold:.3g}" if c.mode == "excursion" else f"min_step={c.min_step:.3g}"
            return (f"hysteresis({c.axis}, {c.mode}, {extra}{', calibrated' if c.cal else ''}"
                    f"{', thermal' if c.thermal else ''})")
        if self.name == "offset_drift":
            return f"offset_drift(rate={c.rate}, steps={c.steps})"
        if self.name == "temperature_quadratic":
            return f"temperature_quadratic(scale={c.scale}, cubic={c.cubic})"
        if getattr(c, "thermal", False):
            return f"{self.name}(thermal)"
        return self.name


def _candidate_variants(name: str, data: CalibrationData, t0: float, dt: float,
                        cal: Sequence[np.ndarray] = ()) -> list[_Variant]:
    """Settings of candidate ``name``; ``cal``: the baseline thermo-affine coefficients per output
    axis (hysteresis thresholds in calibrated uT)."""
    if name in ("axis_quadratic", "cross_axis_quadratic", "cubic_nonlinearity"):
        # plain, and with coefficients linear in T (a reading distortion seen through the
        # temperature-dependent gain S + Ks T)
        return [_Variant(name, C.CATALOGUE[name]()), _Variant(name, C.CATALOGUE[name](t0=t0, thermal=True))]
    if name == "temperature_quadratic":
        return [_Variant(name, C.TemperatureQuadratic(t0=t0)), _Variant(name, C.TemperatureQuadratic(t0=t0, scale=True)),
                _Variant(name, C.TemperatureQuadratic(t0=t0, cubic=True))]
    if name == "thermal_lag":
        taus = np.geomspace(max(2 * dt, 1.0), 1000.0, 14)
        return [_Variant(name, C.ThermalLag(tau0=float(t)), float(np.log(t))) for t in taus]
    if name == "timing_offset":
        deltas = np.arange(-8, 9) * dt / 2
        return [_Variant(name, C.TimingOffset(delta0=float(d)), float(d)) for d in deltas if d != 0]
    if name == "hysteresis":
        out = []
        for k, ax in enumerate(AXES):
            m = float(np.quantile(np.abs(data.b_meas[:, k]), 0.98))
            if m <= 0:
                continue
            d = np.diff(data.b_meas[:, k])
            noise = 1.4826 * np.median(np.abs(d - np.median(d))) + 1e-6
            for thermal in (False, True):
                for frac in (0.3, 0.5, 0.7):
                    out.append(_Variant(name, C.Hysteresis(axis=ax, mode="excursion", threshold=round(frac * m, 3),
                                                           t0=t0, thermal=thermal)))
                for mult in (6.0,):
                    out.append(_Variant(name, C.Hysteresis(axis=ax, mode="direction", min_step=round(mult * noise, 3),
                                                           lag=4, t0=t0, thermal=thermal)))
            if len(cal) == 3:
                # excursions of the calibrated field: a fixed field threshold even where the
                # axis' gain changes with temperature
                coef = tuple(round(float(c), 8) for c in cal[k])
                probe = C.Hysteresis(axis=ax, t0=t0, cal=coef)
                fc = np.asarray(probe.drive(inputs_from_data(data)))
                mc = float(np.quantile(np.abs(fc), 0.98))
                if mc > 0:
                    for thermal in (False, True):
                        for frac in (0.2, 0.3, 0.4, 0.5, 0.6, 0.7):
                            out.append(_Variant(name, C.Hysteresis(axis=ax, mode="excursion",
                                                                   threshold=round(frac * mc, 3), t0=t0,
                                                                   thermal=thermal, cal=coef)))
        return out
    if name == "offset_drift":
        t_ref = float(data.time[0])
        r_ref = int(data.run.min())
        out = [_Variant(name, C.OffsetDrift(time_ref=t_ref, run_ref=r_ref, rate=True, steps=False))]
        if np.unique(data.run).size > 2:
            out += [_Variant(name, C.OffsetDrift(time_ref=t_ref, run_ref=r_ref, rate=False, steps=True)),
                    _Variant(name, C.OffsetDrift(time_ref=t_ref, run_ref=r_ref, rate=True, steps=True))]
        return out
    raise ValueError(f"candidate {name!r} is not in the catalogue; valid: {sorted(C.CATALOGUE)}.")


_features_jit = jax.jit(lambda term, inp: term.features(inp), static_argnums=0)
_hyst_jit = jax.jit(lambda f, run, level, mode, lag: C.hysteresis_state(f, run, level, mode=mode, lag=lag),
                    static_argnums=(3, 4))
_apply_transform = jax.jit(lambda tr, p, inp: tr(p, inp), static_argnums=0)


class _Designs:
    """Design matrices of the base model plus extension variants, cached by transform setting."""

    def __init__(self, base: ThermoAffine, inputs: Inputs):
        self.base = base
        self.inputs = inputs
        self._inputs_cache: dict = {}
        self._feat_cache: dict = {}

    def _transformed(self, transforms: tuple) -> Inputs:
        if transforms not in self._inputs_cache:
            inp = self.inputs
            for v in transforms:
                inp = _apply_transform(type(v.component)(), jnp.array([v.nl]), inp)
            self._inputs_cache[transforms] = inp
        return self._inputs_cache[transforms]

    def matrix(self, variants: tuple) -> np.ndarray:
        transforms = tuple(v for v in variants if v.nl is not None)
        terms = [v for v in variants if v.nl is None]
        cols = []
        for term in [self.base] + [v.component for v in terms]:
            key = (transforms, term)
            if key not in self._feat_cache:
                inp = self._transformed(transforms)
                if isinstance(term, C.Hysteresis):       # one compile for every threshold of the grid
                    level = term.threshold if term.mode == "excursion" else term.min_step
                    f = _hyst_jit(term.drive(inp), inp.run, jnp.asarray(level), term.mode,
                                  int(term.lag))[:, None]
                    if term.thermal:
                        f = jnp.concatenate([f, f * (inp.t - term.t0)[:, None]], axis=1)
                else:
                    f = _features_jit(term, inp)
                self._feat_cache[key] = np.asarray(f)
            cols.append(self._feat_cache[key])
        return np.concatenate(cols, axis=1)


@dataclasses.dataclass
class _Score:
    name: str
    variant: _Variant            # chosen on all rows
    e_oos: np.ndarray            # out-of-sample residuals (n,)
    resid: np.ndarray            # in-sample residuals at the chosen variant
    gain: float
    z: float
    dbic: float
    n_params: int
    accepted: bool = False
    reason: str = ""


def _solve_sym(G: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Minimum-norm solution of G b = c for a symmetric PSD G (tiny eigenvalues dropped)."""
    w, V = np.linalg.eigh(G)
    keep = w > 1e-11 * max(w.max(), 1e-300)
    return V[:, keep] @ ((V[:, keep].T @ c) / w[keep])


def _fold_fits(X: np.ndarray, y: np.ndarray, folds: np.ndarray, fold_ids: np.ndarray):
    """Per fold: (beta, training SSE) by normal equations on column-scaled X (fast, rank-safe)."""
    s = np.sqrt((X * X).sum(0))
    s = np.where(s > 0, s, 1.0)
    Xs = X / s
    G, c, yy = Xs.T @ Xs, Xs.T @ y, float(y @ y)
    out = []
    for k in fold_ids:
        te = folds == k
        Xt, yt = Xs[te], y[te]
        Gk, ck = G - Xt.T @ Xt, c - Xt.T @ yt
        b = _solve_sym(Gk, ck)
        sse = (yy - float(yt @ yt)) - 2 * float(b @ ck) + float(b @ Gk @ b)
        out.append((b / s, sse))
    return out


def _cv_residuals(designs: _Designs, current: tuple, options: list, y: np.ndarray, folds: np.ndarray) -> np.ndarray:
    """Out-of-sample residuals; per fold the variant in ``options`` with the least training SSE."""
    e = np.empty_like(y)
    fold_ids = np.unique(folds)
    mats = [designs.matrix(current + ((o,) if o is not None else ())) for o in options]
    fits = [_fold_fits(X, y, folds, fold_ids) for X in mats]
    for j, k in enumerate(fold_ids):
        te = folds == k
        m = int(np.argmin([f[j][1] for f in fits]))
        e[te] = y[te] - mats[m][te] @ fits[m][j][0]
    return e


def _in_sample(designs: _Designs, current: tuple, options: list, y: np.ndarray):
    best = None
    for o in options:
        X = designs.matrix(current + ((o,) if o is not None else ()))
        beta = _lstsq(X, y)
        r = y - X @ beta
        sse = float(r @ r)
        if best is None or sse < best[0]:
            best = (sse, o, r, X.shape[1])
    return best


def _bic(sse: float, n_eff: float, k: int) -> float:
    return n_eff * math.log(max(sse, 1e-300) / max(n_eff, 1.0)) + k * math.log(max(n_eff, 2.0))


#: Candidates (by single out-of-sample gain) tried in pairs when none passes alone.
PAIR_TOP = 3


def _best_pair(scores, cands, designs, current, y, folds, blocks, e_cur, r_cur, k_cur, n_eff):
    """(first, joint score of first + second) of the best accepted pair among the top single
    candidates, or None. The joint score is of the pair against the model without either,
    held to the same acceptance criteria as a single term, and each member must also improve
    the out-of-sample loss given the other with z >= Z_MIN (so a pair is not one real term
    plus a passenger)."""
    top = sorted((s for s in scores if s.gain > 0), key=lambda s: -s.gain)[:PAIR_TOP]
    best = None
    for i, a in enumerate(top):
        for b in top[i + 1:]:
            if a.name == b.name:
                continue
            joint = _score_candidate(b.name, cands[b.name], designs, current + (a.variant,), y, folds, blocks,
                                     e_cur, r_cur, k_cur, n_eff)
            extra = (1 if a.variant.nl is not None else 0) + (1 if len(cands[a.name]) > 1 else 0)
            joint.n_params += extra
            joint.dbic += extra * math.log(n_eff)
            joint.accepted = joint.z >= Z_MIN and joint.gain >= MIN_GAIN and joint.dbic <= -DBIC_MIN
            if joint.accepted:
                # each member must be needed given the other (out of sample, same z threshold)
                z_a = _block_z(b.e_oos**2 - joint.e_oos**2, blocks, joint.e_oos)
                z_b = _block_z(a.e_oos**2 - joint.e_oos**2, blocks, joint.e_oos)
                joint.accepted = min(z_a, z_b) >= Z_MIN
            if joint.accepted and (best is None or joint.gain > best[1].gain):
                best = (a, joint)
    return best


def _score_candidate(name, options, designs, current, y, folds, blocks, e_base, r_base, k_base, n_eff) -> _Score:
    e = _cv_residuals(designs, current, options, y, folds)
    sse, chosen, r, k = _in_sample(designs, current, options, y)
    k_eff = k + (1 if chosen.nl is not None else 0) + (1 if len(options) > 1 else 0)
    d = e_base**2 - e**2
    gain = float(d.sum() / (e_base @ e_base))
    z = _block_z(d, blocks, e)
    scale = n_eff / y.size
    dbic = _bic(sse, n_eff, k_eff) - _bic(float(r_base @ r_base), n_eff, k_base)
    del scale
    return _Score(name, chosen, e, r, gain, z, dbic, k_eff - k_base)


# --------------------------------------------------------------------------- per-axis refit (LM + Newey-West)


def _model_of(base: ThermoAffine, variants: Sequence[_Variant]) -> PhysicsModel:
    terms = (base,) + tuple(v.component for v in variants if v.nl is None)
    transforms = tuple(v.component for v in variants if v.nl is not None)
    return PhysicsModel(terms, transforms)


@jax.jit
def _noop(x):
    return x


_lm_jit = jax.jit(lambda model, th0, inputs, y: levenberg_marquardt(lambda th: y - model.predict(th, inputs), th0),
                  static_argnums=0)
_jac_jit = jax.jit(lambda model, th, inputs: jax.jacfwd(model.predict)(th, inputs), static_argnums=0)


def _refit_axis(designs: _Designs, base, variants: tuple, y: np.ndarray, run: np.ndarray):
    """(theta, cov, names, resid, model) of one axis' model with ``variants`` (LM if nonlinear)."""
    model = _model_of(base, variants)
    X = designs.matrix(variants)
    beta = _lstsq(X, y)
    # parameter order: base, linear terms (in variants order), then transforms
    nl = [v.nl for v in variants if v.nl is not None]
    th0 = np.concatenate([beta, np.array(nl, dtype=np.float64)])
    inputs = designs.inputs
    if nl:
        sol = _lm_jit(model, jnp.asarray(th0), inputs, jnp.asarray(y))
        theta = np.asarray(sol.theta)
        if not np.all(np.isfinite(theta)) or int(sol.result) == 2:
            theta = th0
        J = np.asarray(_jac_jit(model, jnp.asarray(theta), inputs))
        r = y - np.asarray(model.predict(jnp.asarray(theta), inputs))
    else:
        theta, J = beta, X
        r = y - X @ beta
    cov, info = covariance(J, r, method="newey_west", run=run)
    return theta, cov, model.param_names, r, model


# --------------------------------------------------------------------------- result


@dataclasses.dataclass
class DiscoveryResult:
    """What :func:`discover` found. ``to_json()`` is the content of findings.json."""

    findings: list
    unexplained: list
    located: list
    baseline: dict
    final: dict
    extra_terms: list
    notes: list
    skipped: list
    options: DiscoverOptions
    source: str
    seconds: float
    arrays: dict = dataclasses.field(default_factory=dict, repr=False)

    @property
    def no_missing_physics(self) -> bool:
        return not self.findings and not self.unexplained

    def to_json(self) -> dict:
        return {
            "source": self.source,
            "no_missing_physics": self.no_missing_physics,
            "baseline": self.baseline,
            "final": self.final,
            "findings": self.findings,
            "unexplained": self.unexplained,
            "extra_terms": self.extra_terms,
            "located": [{k: v for k, v in l.items() if k not in ("bin_labels", "bin_means")} for l in self.located],
            "notes": self.notes,
            "skipped": self.skipped,
            "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self.options).items()},
            "thresholds": {"z_min": Z_MIN, "min_gain": MIN_GAIN, "dbic_min": DBIC_MIN, "z_distinct": Z_DISTINCT,
                           "locate_p": LOCATE_P, "locate_fraction": LOCATE_FRACTION, "n_perm": N_PERM},
            "seconds": self.seconds,
        }

    def write(self, out: str | Path) -> Path:
        """Write findings.json, report.md and the figures to ``out`` atomically (temp folder, then rename)."""
        from .outdir import staging_dir

        out = Path(out)
        with staging_dir(out) as tmp:
            figures = []
            if self.options.figures:
                from . import discover_plots
                figures = discover_plots.discovery_figures(tmp, self)
            (tmp / "findings.json").write_text(json.dumps(_jsonable(self.to_json()), indent=2))
            (tmp / "report.md").write_text(report_markdown(self, figures))
        return out


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    return x


# --------------------------------------------------------------------------- discover


def _folds(data: CalibrationData, options: DiscoverOptions, notes: list,
           corr_rows: int = 0) -> tuple[np.ndarray, np.ndarray, str]:
    """Fold and block id per row. Blocks: ``block_s`` seconds, or max(n/150 rows, ``corr_rows``)
    (the residual correlation length), at most n/30 rows."""
    same = ~_run_starts(data.run)[1:]
    dt = float(np.median(np.diff(data.time)[same])) if same.any() else 1.0
    if options.block_s is not None:
        block_rows = max(10, int(round(options.block_s / max(dt, 1e-9))))
    else:
        block_rows = int(np.clip(max(data.n // 150, corr_rows), 10, max(10, data.n // 30)))
    blocks = _block_ids(data, block_rows)
    runs = np.unique(data.run)
    if options.cv == "by_run":
        if runs.size < 2:
            notes.append(f"cv = 'by_run' needs at least two runs; the data has one (run {runs[0]}), so "
                         f"contiguous time blocks ({options.n_folds} folds) are used instead.")
        else:
            folds = np.searchsorted(runs, data.run)
            return folds, blocks, f"leave-one-run-out over {runs.size} runs"
    nb = blocks.max() + 1
    folds = blocks % int(options.n_folds)
    if nb < int(options.n_folds):
        folds = blocks
    return folds, blocks, (f"{int(options.n_folds)}-fold cross-validation by contiguous time blocks "
                           f"(~{block_rows} rows each, {nb} blocks)")


def _infer_time(data: CalibrationData, options: DiscoverOptions, notes: list) -> bool:
    if options.time_available is not None:
        return bool(options.time_available)
    if np.array_equal(data.time, np.arange(data.n, dtype=np.float64)):
        notes.append("The data have no time column (time equals the row index): time-domain candidates "
                     f"{list(TIME_DOMAIN)} and the periodicity check are skipped.")
        return False
    return True


def _oos_scores(y, e, e_train_sd=None) -> dict:
    sd = float(np.sqrt(np.mean(e**2))) if e_train_sd is None else float(e_train_sd)
    nll = float(np.mean(0.5 * np.log(2 * np.pi * sd**2) + 0.5 * e**2 / sd**2))
    return {"rmse": float(np.sqrt(np.mean(e**2))), "mae": float(np.mean(np.abs(e))), "nll": nll}


def _stage_scores(e_oos: np.ndarray, resid: np.ndarray, folds: np.ndarray, k: int, run: np.ndarray) -> dict:
    # NLL with the training-fold residual sd (out of sample): sd from the in-sample residual of the other folds.
    nll = []
    for f in np.unique(folds):
        te = folds == f
        sd = float(np.sqrt(np.mean(resid[~te] ** 2)))
        nll.append(0.5 * np.log(2 * np.pi * sd**2) + 0.5 * e_oos[te] ** 2 / sd**2)
    n = resid.size
    sse = float(resid @ resid)
    rho = lag1_autocorrelation(resid, run)
    n_eff = n * (1 - max(rho, 0.0)) / (1 + max(rho, 0.0))
    return {"rmse": float(np.sqrt(np.mean(e_oos**2))), "mae": float(np.mean(np.abs(e_oos))),
            "nll": float(np.mean(np.concatenate(nll))), "bic": _bic(sse, n, k), "bic_eff": _bic(sse, n_eff, k),
            "aic": n * math.log(sse / n) + 2 * k, "lag1_autocorrelation": float(rho), "n_params": int(k),
            "rmse_in_sample": float(np.sqrt(sse / n))}


def _axis_dict(per_axis: list[dict]) -> dict:
    keys = per_axis[0].keys()
    return {k: {ax: per_axis[a][k] for a, ax in enumerate(AXES)} for k in keys}


def _spec_of(v: _Variant, theta_nl: float | None) -> dict:
    c = v.component
    d = {"name": v.name}
    for f in dataclasses.fields(c):
        if f.name == "t0":
            continue
        d[f.name] = getattr(c, f.name)
    if v.name == "thermal_lag" and theta_nl is not None:
        d["tau0"] = round(float(math.exp(theta_nl)), 4)
    if v.name == "timing_offset" and theta_nl is not None:
        d["delta0"] = round(float(theta_nl), 4)
    return d


def discover(data: CalibrationData, options: DiscoverOptions | None = None, **kwargs) -> DiscoveryResult:
    """Locate, name and model physics missing from the thermo-affine calibration model.

    Args:
      data: a recording with a reference (:class:`~bayesmag.CalibrationData`).
      options: :class:`DiscoverOptions`; or give its fields as keyword arguments.

    Returns:
      :class:`DiscoveryResult` (``.write(dir)`` writes findings.json, report.md, figures).

    Example:
      >>> from bayesmag.simulate import simulate, get_effect
      >>> d = simulate(3000, design="campaign", seed=0, effects=[get_effect("cubic", out="x", inp="x")])
      >>> r = discover(d, figures=False)
      >>> [(f["axis"], f["effect"]) for f in r.findings][:1]
      [('x', 'cubic_nonlinearity')]
    """
    t_start = _time.perf_counter()
    if options is None:
        options = DiscoverOptions(**kwargs)
    elif kwargs:
        raise TypeError(f"give options or keyword arguments, not both; got keywords {sorted(kwargs)}.")
    if not isinstance(data, CalibrationData):
        raise TypeError(f"data must be a CalibrationData; got {type(data).__name__}.")
    if data.b_ref is None:
        raise ValueError("discovery needs a recording with reference columns (b_ref); this one has none.")
    from .data import validate_for_discover
    validate_for_discover(data)             # finite, plausible uT/Celsius values, rows sorted by time (issue 11)
    if data.n < 50:
        raise ValueError(f"discovery needs at least 50 rows; the data has {data.n}.")
    notes, skipped = [], []
    time_ok = _infer_time(data, options, notes)
    t_std = float(np.std(data.temperature))
    temp_terms = t_std > 0.05
    t0 = float(np.mean(data.temperature)) if options.t0 == "mean" else float(options.t0)
    base = ThermoAffine(t0=t0, temperature=temp_terms)
    if not temp_terms:
        notes.append(f"Temperature varies by only {t_std:.3g} C (sd): the base model has no temperature terms.")
    inputs = inputs_from_data(data)
    designs = _Designs(base, inputs)
    y_all = np.asarray(data.b_ref)
    X0 = designs.matrix(())
    base_theta = [_lstsq(X0, y_all[:, a]) for a in range(3)]
    base_resid = np.stack([y_all[:, a] - X0 @ base_theta[a] for a in range(3)], 1)
    corr_rows = max(_block_length(base_resid[:, a]) for a in range(3))
    folds, blocks, cv_desc = _folds(data, options, notes, corr_rows)
    same = ~_run_starts(data.run)[1:]
    dt = float(np.median(np.diff(data.time)[same])) if same.any() else 1.0

    names = list(options.candidates or C.CATALOGUE)
    cands: dict[str, list[_Variant]] = {}
    n_train_min = int(np.min([np.sum(folds != k) for k in np.unique(folds)]))
    for name in names:
        if name in TIME_DOMAIN and not time_ok:
            skipped.append({"candidate": name, "reason": "needs a time column (the data have none)"})
            continue
        if name in THERMAL and not temp_terms:
            skipped.append({"candidate": name, "reason": f"needs temperature variation (sd {t_std:.3g} C)"})
            continue
        if name == "timing_offset" and (np.diff(data.time)[same] <= 0).any():
            skipped.append({"candidate": name, "reason": "needs time increasing within each run"})
            continue
        vs = _candidate_variants(name, data, t0, dt, cal=base_theta)
        if not vs:
            skipped.append({"candidate": name, "reason": "no usable setting for these data"})
            continue
        p = len(base.param_names()) + max(v.n_params for v in vs)
        if n_train_min < ROWS_PER_PARAM * p:
            skipped.append({"candidate": name, "reason": f"needs at least {ROWS_PER_PARAM * p} training rows "
                                                         f"({ROWS_PER_PARAM} per parameter, {p} parameters); "
                                                         f"a fold has {n_train_min}"})
            continue
        cands[name] = vs
    for s in skipped:
        notes.append(f"Candidate {s['candidate']} skipped: {s['reason']}.")

    k0 = len(base.param_names())
    _thermal = lambda v: bool(getattr(v.component, "thermal", False))     # noqa: E731
    tiers = ({n: [v for v in vs if not _thermal(v)] for n, vs in cands.items()},
             {n: [v for v in vs if _thermal(v)] for n, vs in cands.items()})
    tiers = (tiers[0], {n: vs for n, vs in tiers[1].items() if vs})

    # ---- baseline fit and locate
    base_oos = np.empty_like(y_all)
    for a in range(3):
        base_oos[:, a] = _cv_residuals(designs, (), [None], y_all[:, a], folds)
    variables = _variables(data, time_ok)
    located = locate(data, base_resid, time_available=time_ok, seed=options.seed, variables=variables)

    # ---- forward selection per axis
    findings, per_axis_final, per_axis_base, selected_all = [], [], [], []
    arrays = {"base_resid": base_resid, "final_resid": np.empty_like(y_all), "variables": variables,
              "effects": {}, "base_oos": base_oos, "final_oos": np.empty_like(y_all)}
    for a, ax in enumerate(AXES):
        y = y_all[:, a]
        current: tuple = ()
        e_cur, r_cur, k_cur = base_oos[:, a], base_resid[:, a], k0
        steps = []
        considered: dict[str, _Score] = {}
        for step in range(int(options.max_terms)):
            if len(current) >= int(options.max_terms):
                break
            rho = lag1_autocorrelation(r_cur, data.run)
            n_eff = y.size * (1 - max(rho, 0.0)) / (1 + max(rho, 0.0))
            # tier 1: constant coefficients; tier 2 (only if tier 1 finds nothing): coefficients
            # with a temperature slope (a reading distortion seen through the gain S + Ks T).
            # Offering both at once lets the richer variant win folds and overfit.
            for tier in tiers:
                scores = []
                for name, vs in tier.items():
                    if any(v.name == name for v in current):
                        continue
                    if name in ("thermal_lag", "timing_offset") and any(v.nl is not None and v.name == name
                                                                        for v in current):
                        continue
                    s = _score_candidate(name, vs, designs, current, y, folds, blocks, e_cur, r_cur, k_cur, n_eff)
                    s.accepted = s.z >= Z_MIN and s.gain >= MIN_GAIN and s.dbic <= -DBIC_MIN
                    scores.append(s)
                    considered.setdefault(name, s)
                ok = [s for s in scores if s.accepted]
                if ok:
                    break
                if tier is tiers[0]:
                    first_scores = scores
            if not ok:
                scores = first_scores
                # two effects on one axis can each explain too little of the mixed residual
                # to pass alone: try the best pairs of candidates jointly (same criteria)
                pair = _best_pair(scores, tiers[0], designs, current, y, folds, blocks, e_cur, r_cur, k_cur, n_eff)
                if pair is None or len(current) + 2 > int(options.max_terms):
                    break
                first, second = pair
                steps.append({"score": first, "alternatives": [], "e_before": e_cur, "r_before": r_cur,
                              "joint_with": second.name})
                steps.append({"score": second, "alternatives": [], "e_before": e_cur, "r_before": first.resid,
                              "joint_with": first.name})
                current = current + (first.variant, second.variant)
                e_cur, r_cur = second.e_oos, second.resid
                k_cur = k_cur + second.n_params
                continue
            best = max(ok, key=lambda s: s.gain)
            alts = []
            for s in ok:
                if s is best:
                    continue
                zpair = _block_z(s.e_oos**2 - best.e_oos**2, blocks, best.e_oos)
                if zpair < Z_DISTINCT:
                    alts.append({"effect": s.name, "setting": s.variant.label, "oos_gain": s.gain,
                                 "z_vs_selected": zpair})
            steps.append({"score": best, "alternatives": alts, "e_before": e_cur, "r_before": r_cur})
            current = current + (best.variant,)
            e_cur, r_cur = best.e_oos, best.resid
            k_cur = k_cur + best.n_params
        # final refit of this axis (LM + Newey-West)
        theta, cov, pnames, r_fin, model = _refit_axis(designs, base, current, y, data.run)
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
        arrays["final_resid"][:, a] = r_fin
        arrays["final_oos"][:, a] = e_cur
        per_axis_base.append(_stage_scores(base_oos[:, a], base_resid[:, a], folds, k0, data.run))
        per_axis_final.append(_stage_scores(e_cur, r_fin, folds, k_cur, data.run))
        selected_names = [v.name for v in current]
        # parameter slices of each variant in the refit model
        offs, i = {}, k0
        for v in current:
            if v.nl is None:
                m = len(v.component.param_names())
                offs[v] = list(range(i, i + m))
                i += m
        for v in current:
            if v.nl is not None:
                offs[v] = [i]
                i += 1
        for st in steps:
            s: _Score = st["score"]
            v = s.variant
            idx = offs[v]
            params = {}
            for j in idx:
                params[pnames[j]] = {"value": float(theta[j]), "se": float(se[j])}
            if v.name == "thermal_lag":
                lt = params.pop("log_tau")
                tau = math.exp(lt["value"])
                params["tau"] = {"value": tau, "se": tau * lt["se"], "unit": "s"}
            if v.name == "timing_offset":
                # delta's Newey-West SE is statistical only; the readings are linearly
                # interpolated between samples, which biases delta by up to ~dt/10 even on
                # noise-free data (measured; docs/discovery.md). Type-B term, in quadrature.
                p = params["delta"]
                sys_se = DELTA_SYS_FRACTION * dt
                p.update({"se": math.hypot(p["se"], sys_se), "se_statistical": p["se"],
                          "se_interpolation": sys_se, "unit": "s"})
            # which located mismatch it removed
            revealed, drop = None, 0.0
            for loc in located:
                if loc["axis"] != ax or not loc["significant"] or loc["variable"] == "periodic":
                    continue
                var = next(vv for vv in variables if vv.name == loc["variable"])
                after = locate_fraction(st["r_before"] - (st["r_before"] - s.resid), var)
                before = locate_fraction(st["r_before"], var)
                if before - after > drop:
                    revealed, drop = loc, before - after
            if revealed is None:
                best_var = max((vv for vv in variables), key=lambda vv: locate_fraction(st["r_before"], vv)
                               - locate_fraction(s.resid, vv))
                revealed_var = best_var.name
            else:
                revealed_var = revealed["variable"]
            alts = [al for al in st["alternatives"] if al["effect"] not in selected_names]
            rmse_b = float(np.sqrt(np.mean(st["e_before"] ** 2)))
            rmse_a = float(np.sqrt(np.mean(s.e_oos**2)))
            finding = {
                "axis": ax, "effect": s.name, "setting": v.label, "parameters": params,
                "rmse_before": rmse_b, "rmse_after": rmse_a,
                "evidence": {
                    "oos_gain": s.gain, "z": s.z, "p_value": float(stats.norm.sf(s.z)), "delta_bic_eff": s.dbic,
                    "revealed_by": revealed_var,
                    "where": revealed["where"] if revealed else None,
                    "located_fraction": revealed["fraction"] if revealed else None,
                    "located_p_value": revealed["p_value"] if revealed else None,
                    "cv": cv_desc,
                },
                "explanation": C.explanation(s.name),
                "indistinguishable_from": alts,
                "accepted_jointly_with": st.get("joint_with"),
                "config": _spec_of(v, theta[offs[v][0]] if v.nl is not None else None),
            }
            findings.append(finding)
            # fitted effect and its band for the figure
            eff, eff_sd = _effect_band(model, theta, cov, offs[v], v, designs.inputs)
            arrays["effects"][(ax, s.name)] = {"effect": eff, "sd": eff_sd, "revealed_by": revealed_var,
                                               "r_before": st["r_before"], "r_after": s.resid}
            selected_all.append(finding["config"])
    # ---- unexplained structure after the final model
    final_loc = locate(data, arrays["final_resid"], time_available=time_ok, seed=options.seed + 1,
                       variables=variables)
    unexplained = []
    for loc in final_loc:
        if not loc["significant"]:
            continue
        if loc["fraction"] < UNEXPLAINED_FRACTION:
            notes.append(f"Minor residual structure remains on {loc['axis']}: {_describe(loc)} It is below the "
                         f"{UNEXPLAINED_FRACTION:.0%} share needed to report it as unexplained physics.")
            continue
        unexplained.append({"axis": loc["axis"], "where": loc["where"],
                            "description": _describe(loc), "variable": loc["variable"],
                            "fraction": loc["fraction"], "p_value": loc["p_value"]})
    unexplained = _dedupe_unexplained(unexplained)
    # union of extensions for `bayesmag run`
    extra_terms, seen = [], set()
    for spec in selected_all:
        key = json.dumps(_jsonable({k: v for k, v in spec.items() if k not in ("tau0", "delta0")}), sort_keys=True)
        if key not in seen:
            seen.add(key)
            extra_terms.append(spec)
    baseline = _axis_dict(per_axis_base)
    final = _axis_dict(per_axis_final)
    baseline["cv"] = final["cv"] = cv_desc
    arrays["located_final"] = final_loc
    return DiscoveryResult(findings, unexplained, located, baseline, final, extra_terms, notes, skipped, options,
                           data.source, _time.perf_counter() - t_start, arrays)


def locate_fraction(r: np.ndarray, v: _Variable) -> float:
    """Share of the variance of ``r`` held by its binned means against variable ``v``."""
    idx, labels = _bins(v)
    r = r - r.mean()
    counts = np.bincount(idx, minlength=len(labels)).astype(float)
    sums = np.bincount(idx, weights=r, minlength=len(labels))
    ok = counts > 0
    return float((sums[ok] ** 2 / counts[ok]).sum() / (r @ r + 1e-300))


def _describe(loc: dict) -> str:
    if loc["variable"] == "periodic":
        return (f"a periodic residual, {loc['shape']}, holding {loc['fraction']:.0%} of the residual variance "
                f"(p = {loc['p_value']:.2g}); no catalogue term is periodic.")
    return (f"the residual {loc['shape']}; largest where {loc['where']} (mean {loc['mean_there']:+.3g} uT); it "
            f"holds {loc['fraction']:.0%} of the residual variance (block-permutation p = {loc['p_value']:.2g}).")


def _dedupe_unexplained(items: list) -> list:
    """Keep per axis the strongest entries (time/run/direction often echo one another)."""
    out = []
    for ax in AXES:
        mine = sorted([u for u in items if u["axis"] == ax], key=lambda u: -u["fraction"])
        out.extend(mine[:3])
    return out


def _effect_band(model: PhysicsModel, theta, cov, idx, v: _Variant, inputs: Inputs):
    """The fitted effect of one extension (prediction with it minus without it) and its sd (delta method)."""
    idx = np.asarray(idx)

    def effect(th):
        if v.nl is None:
            off = th.at[idx].set(0.0)
        elif v.name == "thermal_lag":
            off = th.at[idx].set(math.log(1e-6))
        else:
            off = th.at[idx].set(0.0)
        return model.predict(th, inputs) - model.predict(off, inputs)

    th = jnp.asarray(theta)
    e = np.asarray(effect(th))
    G = np.asarray(jax.jacfwd(effect)(th))
    sd = np.sqrt(np.clip(np.einsum("np,pq,nq->n", G, cov, G), 0, None))
    return e, sd


# --------------------------------------------------------------------------- report


def report_markdown(res: DiscoveryResult, figures: Sequence[str] = ()) -> str:
    """A plain-words report for a metrologist."""
    L = ["# Discovery of missing physics", "", f"Data: {res.source}", "",
         f"Out-of-sample scores: {res.baseline['cv']}. Discovery took {res.seconds:.1f} s.", ""]
    if res.no_missing_physics:
        L += ["**No missing physics was found.** The thermo-affine model leaves no residual structure that a "
              "catalogue extension explains out of sample, and no structure beyond noise remains "
              f"(thresholds: block z >= {Z_MIN}, gain >= {MIN_GAIN:.0%}, BIC_eff drop >= {DBIC_MIN}; located "
              f"structure needs p <= {LOCATE_P} and >= {LOCATE_FRACTION:.0%} of the residual variance).", ""]
    L += ["## Before and after, per axis (out of sample unless noted)", "",
          "| axis | RMSE before | RMSE after | MAE before | MAE after | NLL before | NLL after | BIC_eff before | "
          "BIC_eff after | lag-1 autocorr. before | after |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    b, f = res.baseline, res.final
    for ax in AXES:
        L.append(f"| {ax} | {b['rmse'][ax]:.4g} | {f['rmse'][ax]:.4g} | {b['mae'][ax]:.4g} | {f['mae'][ax]:.4g} | "
                 f"{b['nll'][ax]:.4g} | {f['nll'][ax]:.4g} | {b['bic_eff'][ax]:.1f} | {f['bic_eff'][ax]:.1f} | "
                 f"{b['lag1_autocorrelation'][ax]:.2f} | {f['lag1_autocorrelation'][ax]:.2f} |")
    L += ["", "RMSE/MAE in uT; NLL per row (Gaussian, sd from the training folds); BIC_eff in-sample with the "
              "effective sample size n(1-rho)/(1+rho).", ""]
    if res.findings:
        L += ["## Findings", ""]
        for i, fd in enumerate(res.findings, 1):
            ev = fd["evidence"]
            ps = ", ".join(f"{k} = {p['value']:.4g} +- {p['se']:.2g}" for k, p in fd["parameters"].items())
            L += [f"### {i}. {fd['effect']} on the {fd['axis']} axis", "",
                  f"*{fd['explanation']}*", "",
                  f"- Setting: {fd['setting']}; fitted parameters (+- one standard error, Newey-West): {ps}.",
                  f"- Out-of-sample RMSE on {fd['axis']}: {fd['rmse_before']:.4g} -> {fd['rmse_after']:.4g} uT "
                  f"({ev['oos_gain']:.1%} of the residual mean square removed; block z = {ev['z']:.1f}, "
                  f"p = {ev['p_value']:.2g}; BIC_eff change {ev['delta_bic_eff']:.1f}).",
                  f"- Revealed by the residual against {ev['revealed_by']}"
                  + (f" (largest where {ev['where']}; {ev['located_fraction']:.0%} of the baseline residual "
                     f"variance, p = {ev['located_p_value']:.2g})." if ev.get("where") else ".")]
            if fd["indistinguishable_from"]:
                alts = ", ".join(f"{al['effect']} ({al['setting']}, gain {al['oos_gain']:.1%})"
                                 for al in fd["indistinguishable_from"])
                L.append(f"- **Indistinguishable** on these data from: {alts}. The data cannot tell these "
                         f"explanations apart; a design that excites them differently is needed.")
            L.append("")
    if res.unexplained:
        L += ["## Unexplained structure", "",
              "Nothing in the catalogue explains the following; it is described, not named:", ""]
        for u in res.unexplained:
            L.append(f"- {u['axis']} axis, {u['where']}: {u['description']}")
        L.append("")
    if res.extra_terms:
        L += ["## Using the extended model", "", "Add to the `[physics]` table of a `bayesmag run` config:", "",
              "```toml", "[physics]", "extra_terms = " + _toml_list(res.extra_terms), "```", "",
              "(thermal_lag's `tau0` and timing_offset's `delta0` are starting values; the fit re-estimates them.)",
              ""]
    if res.notes:
        L += ["## Notes", ""] + [f"- {n}" for n in res.notes] + [""]
    if figures:
        L += ["## Figures", ""] + [f"![{Path(p).stem}]({Path(p).name})" for p in figures] + [""]
    return "\n".join(L)


def _toml_list(specs: list) -> str:
    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        return repr(float(v)) if isinstance(v, float) else str(v)
    items = ["{" + ", ".join(f"{k} = {val(v)}" for k, v in s.items()) + "}" for s in specs]
    return "[" + ", ".join(items) + "]"


# --------------------------------------------------------------------------- config / CLI


def load_discover_config(path: str | Path, overrides: Sequence[str] = ()):
    """(Config, DiscoverOptions) from a TOML file whose optional ``[discover]`` table holds
    :class:`DiscoverOptions` fields (validated; unknown keys are errors naming the valid set)."""
    from .config import ConfigError, config_from_dict, read_config_dict

    raw = read_config_dict(path, overrides)
    disc = raw.pop("discover", {})
    cfg = config_from_dict(raw)
    valid = [f.name for f in dataclasses.fields(DiscoverOptions)]
    unknown = sorted(set(disc) - set(valid))
    if unknown:
        raise ConfigError(f"Unknown config key(s) {['discover.' + k for k in unknown]}. Valid keys in [discover]: {valid}.")
    try:
        opts = DiscoverOptions(**disc)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"[discover]: {e}") from None
    if "t0" not in disc and cfg.physics.t0 != 0.0:
        opts = dataclasses.replace(opts, t0=cfg.physics.t0)
    return cfg, opts


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bayesmag discover", description="Find physics missing from the calibration model.")
    p.add_argument("config", nargs="?", help="config file with [data] and optional [discover]")
    p.add_argument("--data", help="a canonical CSV instead of a config (defaults for everything else)")
    p.add_argument("--out", help="output folder (default runs/discover_<name>)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config key")
    p.add_argument("--no-figures", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from .config import ConfigError
    from .data import DataError
    from .job import load_data

    try:
        if args.data and args.config:
            raise ConfigError("give a CONFIG or --data FILE.csv, not both.")
        if args.data:
            data = load_csv(args.data)
            opts = DiscoverOptions()
            if "time" not in Path(args.data).read_text().splitlines()[0].split(","):
                opts = dataclasses.replace(opts, time_available=False)
            name = Path(args.data).stem
        elif args.config:
            cfg, opts = load_discover_config(args.config, args.set or [])
            data = load_data(cfg)
            name = cfg.name
        else:
            raise ConfigError("give a CONFIG or --data FILE.csv.")
        if args.no_figures:
            opts = dataclasses.replace(opts, figures=False)
        out = Path(args.out) if args.out else Path("runs") / f"discover_{name}"
        res = discover(data, opts)
        res.write(out)
    except (ConfigError, DataError, FileNotFoundError, ValueError) as e:
        print(f"bayesmag discover: error: {e}", file=sys.stderr)
        return 2
    print(f"bayesmag discover: wrote {out}/ in {res.seconds:.1f} s")
    if res.no_missing_physics:
        print("  no missing physics found")
    for f in res.findings:
        ps = ", ".join(f"{k}={p['value']:.4g}+-{p['se']:.2g}" for k, p in f["parameters"].items())
        print(f"  {f['axis']}: {f['effect']} ({ps}); OOS RMSE {f['rmse_before']:.4g} -> {f['rmse_after']:.4g} uT")
    for u in res.unexplained:
        print(f"  {u['axis']}: unexplained, {u['where']}")
    for n in res.notes:
        print(f"  note: {n}")
    return 0


if __name__ == "__main__":
    import bayesmag  # noqa: F401  (float64)
    sys.exit(main())
