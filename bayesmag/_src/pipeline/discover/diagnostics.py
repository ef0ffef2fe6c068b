"""Structure in residuals: where it is (locate), whether any is left beyond noise, and its time scale.

:func:`locate` bins a residual against each input (reference field components, |B|,
temperature), rates of change, direction of travel, run, time, and a periodogram; each
variable's share of the residual variance is the R^2 of the binned means, its p-value a
*block* permutation. :func:`structure` adds what block permutation cannot see: slow
structure, judged by the lag-1 autocorrelation and the ratio of the residual variance to the
high-frequency noise floor (half the variance of row-to-row differences), with a time scale
(a significant spectrum peak, or the correlation time).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import stats

from bayesmag._src.core.data import AXES, CalibrationData
from bayesmag._src.core.fit import lag1_autocorrelation
from bayesmag._src.pipeline.discover.options import FLOOR_RATIO, LOCATE_FRACTION, LOCATE_P, N_PERM, RHO_STRUCTURE, UNEXPLAINED_FRACTION

__all__ = ["locate", "structure", "make_variables", "block_ids", "block_z", "block_length", "run_starts",
           "locate_fraction", "describe", "run_contrast", "run_pieces", "serial_contrast"]


def run_starts(run):
    return np.concatenate([[True], run[1:] != run[:-1]])


def _smooth_rate(x: np.ndarray, time: np.ndarray, run: np.ndarray, half: int) -> np.ndarray:
    """Central difference over +-half rows inside each run (per second)."""
    out = np.zeros_like(x, dtype=np.float64)
    bounds = np.flatnonzero(np.concatenate([run_starts(run), [True]]))
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


def block_ids(data: CalibrationData, block_rows: int) -> np.ndarray:
    """Contiguous blocks of about ``block_rows`` rows inside each run, numbered globally."""
    ids = np.empty(data.n, dtype=np.int64)
    bounds = np.flatnonzero(np.concatenate([run_starts(data.run), [True]]))
    nxt = 0
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        k = max(1, int(round((hi - lo) / block_rows)))
        ids[lo:hi] = nxt + (np.arange(hi - lo) * k) // (hi - lo)
        nxt += k
    return ids


def block_z(d: np.ndarray, blocks: np.ndarray, e: np.ndarray | None = None) -> float:
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


def run_contrast(r: np.ndarray, blocks: np.ndarray, run: np.ndarray) -> tuple[float, float, int | None]:
    """(z, p, run): evidence that the means of ``r`` differ between runs, judged by the scatter of
    block means *within* runs.

    A one-way analysis of variance with the blocks as replicates: blocks are longer than the
    residual's correlation length (:func:`block_length`), so their means are close to
    independent under the null, and slow wander inside a run widens the yardstick.
    F = (between-run mean square of block means) / (pooled within-run mean square), with
    (R - 1, B - R) degrees of freedom; ``p`` its upper tail, ``z`` the one-sided normal z of
    ``p`` (comparable with the search's block z) and ``run`` the run whose mean lies furthest
    from the others'. A step confined to one run of six moves ~5 of ~30 blocks, which the block
    signed-rank z of the search cannot see; this test scores it by run. z = 0 (p = 1) with fewer
    than 2 runs or 3 within-run degrees of freedom."""
    r = np.asarray(r, dtype=np.float64)
    cnt = np.bincount(blocks)
    keep = np.flatnonzero(cnt > 0)
    means = np.bincount(blocks, weights=r)[keep] / cnt[keep]
    brun = np.zeros(blocks.max() + 1, dtype=np.asarray(run).dtype)
    brun[blocks] = run
    runs, idx = np.unique(brun[keep], return_inverse=True)
    R, B = runs.size, means.size
    if R < 2 or B - R < 3:
        return 0.0, 1.0, None
    m = np.bincount(idx, minlength=R).astype(np.float64)
    run_mean = np.bincount(idx, weights=means, minlength=R) / m
    ss_w = float(((means - run_mean[idx]) ** 2).sum())
    ss_b = float((m * (run_mean - means.mean()) ** 2).sum())
    if not ss_w > 0:
        return 0.0, 1.0, None
    F = (ss_b / (R - 1)) / (ss_w / (B - R))
    p = float(stats.f.sf(F, R - 1, B - R))
    rest = (means.sum() - run_mean * m) / (B - m)
    k = int(np.argmax(np.abs(run_mean - rest)))
    return (float(stats.norm.isf(max(p, 1e-300))) if p < 0.5 else 0.0), p, int(runs[k])


def run_pieces(blocks: np.ndarray, run: np.ndarray, pieces: int) -> np.ndarray:
    """(n,) index of each row's piece of its run: the run's CV blocks split into ``min(pieces, blocks // 2)``
    contiguous pieces of whole blocks (at least 2 blocks each; a run of fewer than 4 blocks is one piece)."""
    out = np.zeros(blocks.size, dtype=np.int64)
    for r in np.unique(run):
        rows = np.flatnonzero(run == r)
        bl, j = np.unique(blocks[rows], return_inverse=True)
        k = int(max(1, min(pieces, bl.size // 2)))
        out[rows] = (j * k) // bl.size
    return out


def serial_contrast(r: np.ndarray, blocks: np.ndarray, run: np.ndarray, *, n_perm: int = N_PERM,
                    seed: int = 0) -> tuple[float, float]:
    r"""(z, p): evidence that neighbouring blocks of a run are more alike than the run's blocks in random order.

    The statistic is :math:`S = \sum_\text{runs} \sum_j (m_{j+1} - m_j)^2` over the block means ``m`` of ``r``
    in time order within each run; its null distribution is that of the blocks permuted within their runs
    (``n_perm`` permutations, seeded). A constant per run plus noise whose correlation is shorter than a block (what
    the CV blocks are sized for) makes a run's block means exchangeable; an offset that wanders within runs (a
    random walk, a drift, a lag's footprint) makes neighbours alike and S small. ``p`` is the share of
    permutations with S at most the observed one (smallest 1 / (n_perm + 1)), ``z`` its one-sided normal z
    (0 for p >= 0.5, or with fewer than 4 neighbouring pairs in runs of >= 3 blocks)."""
    r = np.asarray(r, dtype=np.float64)
    cnt = np.bincount(blocks)
    keep = np.flatnonzero(cnt > 0)
    means = np.bincount(blocks, weights=r)[keep] / cnt[keep]
    first = np.zeros(blocks.max() + 1, dtype=np.int64)
    first[blocks[::-1]] = np.arange(blocks.size)[::-1]
    brun = np.asarray(run)[first[keep]]
    order = np.argsort(first[keep], kind="stable")
    means, brun = means[order], brun[order]
    groups = [means[brun == q] for q in dict.fromkeys(brun.tolist())]
    groups = [g for g in groups if g.size >= 3]
    if sum(g.size - 1 for g in groups) < 4:
        return 0.0, 1.0
    rng = np.random.default_rng(seed)
    obs = sum(float((np.diff(g) ** 2).sum()) for g in groups)
    perm = sum((np.diff(rng.permuted(np.tile(g, (n_perm, 1)), axis=1), axis=1) ** 2).sum(1) for g in groups)
    p = float((1 + np.sum(perm <= obs * (1 + 1e-12))) / (n_perm + 1))
    return (float(stats.norm.isf(p)) if p < 0.5 else 0.0), p


@dataclasses.dataclass(frozen=True)
class _Variable:
    name: str
    label: str          # for sentences
    unit: str
    values: np.ndarray
    categorical: bool = False


def make_variables(data: CalibrationData, time_ok: bool) -> list[_Variable]:
    ref = data.b_ref
    dt = np.median(np.diff(data.time)[~run_starts(data.run)[1:]]) if data.n > 1 else 1.0
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
    starts = run_starts(run)
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


def block_length(r: np.ndarray) -> int:
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
    variables = variables if variables is not None else make_variables(data, time_available)
    out = []
    for a, ax in enumerate(AXES):
        r = np.asarray(resid[:, a], dtype=np.float64)
        r = r - r.mean()
        ss = float(r @ r) + 1e-300
        L = block_length(r)
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
    same = ~run_starts(data.run)[1:]
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
        beta = np.linalg.solve(X.T @ X + 1e-12 * np.eye(2), X.T @ r)
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


def locate_fraction(r: np.ndarray, v: _Variable) -> float:
    """Share of the variance of ``r`` held by its binned means against variable ``v``."""
    idx, labels = _bins(v)
    r = r - r.mean()
    counts = np.bincount(idx, minlength=len(labels)).astype(float)
    sums = np.bincount(idx, weights=r, minlength=len(labels))
    ok = counts > 0
    return float((sums[ok] ** 2 / counts[ok]).sum() / (r @ r + 1e-300))


def describe(loc: dict) -> str:
    if loc["variable"] == "periodic":
        return (f"a periodic residual, {loc['shape']}, holding {loc['fraction']:.0%} of the residual variance "
                f"(p = {loc['p_value']:.2g}); no catalogue term is periodic.")
    return (f"the residual {loc['shape']}; largest where {loc['where']} (mean {loc['mean_there']:+.3g} uT); it "
            f"holds {loc['fraction']:.0%} of the residual variance (block-permutation p = {loc['p_value']:.2g}).")



def noise_floor(r: np.ndarray, run: np.ndarray) -> float:
    """High-frequency noise sd of ``r``: robust sd of row-to-row differences inside runs, / sqrt(2).

    It needs no reference model of the slow part: a smooth signal barely changes from one row to
    the next, white noise doubles its variance in a difference."""
    same = ~run_starts(run)[1:]
    d = np.diff(r)[same]
    if d.size < 3:
        return float(np.std(r))
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


def correlation_time(r: np.ndarray, dt: float) -> float:
    """Seconds until the autocorrelation of ``r`` first falls below 1/e; ``r`` clipped at 5 robust sd
    (1.4826 MAD) about its median first, so a few spikes do not make a slow residual look white (Belsten's z
    channel: 6 rows of 1.8 uT in a residual of sd 0.046 uT gave 0.25 s, one sample)."""
    r = np.asarray(r, dtype=np.float64)
    med = np.median(r)
    lim = 5.0 * 1.4826 * np.median(np.abs(r - med))
    if lim > 0:
        r = np.clip(r, med - lim, med + lim)
    r = r - r.mean()
    n = r.size
    f = np.fft.rfft(r, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[: n // 2]
    if acf[0] <= 0:
        return 0.0
    below = np.flatnonzero(acf / acf[0] < math.exp(-1))
    return float((below[0] if below.size else acf.size) * dt)


def spectrum_peak(r: np.ndarray, time: np.ndarray, run: np.ndarray, dt: float) -> tuple[float, float] | None:
    """(period s, share of the variance) of the strongest sinusoid in ``r`` on the real time axis
    (least squares per trial period, so gaps between runs do not smear the line), or None when no
    period of at most the longest run holds >= 30 % of the variance and 5x the median share."""
    r = np.asarray(r, dtype=np.float64)
    r = r - r.mean()
    spans = [np.ptp(time[run == k]) for k in np.unique(run)]
    hi = float(np.max(spans))
    lo = 4 * dt
    if hi <= 2 * lo:
        return None
    periods = np.geomspace(lo, hi, 600)
    ss = float(r @ r) + 1e-300
    share = np.empty(periods.size)
    for i, P in enumerate(periods):
        ph = 2 * np.pi * time / P
        X = np.stack([np.sin(ph), np.cos(ph)], 1)
        X = X - X.mean(0)
        c = X.T @ r
        share[i] = float(c @ np.linalg.solve(X.T @ X + 1e-12 * np.eye(2), c)) / ss
    k = int(np.argmax(share))
    if share[k] < 0.3 or share[k] < 5 * np.median(share):
        return None
    return float(periods[k]), float(share[k])


def structure(data: CalibrationData, resid: np.ndarray, located: list, *, dt: float, labels=AXES,
              time_available: bool = True) -> list[dict]:
    """Structure left in residuals ``resid`` (n, 3), one entry per column that holds some.

    A column holds structure when its lag-1 autocorrelation >= RHO_STRUCTURE *and* its variance
    exceeds FLOOR_RATIO times the high-frequency noise floor (:func:`noise_floor`), or when
    :func:`locate` (``located``, same columns) found a significant pattern holding at least
    UNEXPLAINED_FRACTION of its variance. Each entry: ``channel``, ``rho1``, ``floor_ratio``,
    ``time_scale_s`` and its ``basis`` ("spectrum peak" or "correlation time"), ``time_scale_rows``
    (the same in rows), the strongest located ``variable``, ``where`` and a ``description``. Without
    real time stamps (``time_available`` False: time is the row index) the scale is a correlation time in
    rows, ``time_scale_s`` None, and no spectrum peak is looked for (a period in rows is no period)."""
    out = []
    for a, lab in enumerate(labels):
        r = resid[:, a] - resid[:, a].mean()
        rho = lag1_autocorrelation(r, data.run)
        floor = noise_floor(r, data.run)
        ratio = float(np.var(r) / max(floor**2, 1e-300))
        mine = [l for l in located if l["axis"] == lab and l["significant"]]
        big = [l for l in mine if l["fraction"] >= UNEXPLAINED_FRACTION]
        slow = rho >= RHO_STRUCTURE and ratio >= FLOOR_RATIO
        if not (slow or big):
            continue
        peak = spectrum_peak(r, data.time, data.run, dt) if time_available else None
        if peak is not None:
            scale, basis = peak[0], "spectrum peak"
        else:
            scale, basis = correlation_time(r, dt), "correlation time"
        best = max(big or mine, key=lambda l: l["fraction"]) if (big or mine) else None
        shown = f"{scale:.3g} s ({basis})" if time_available else \
            f"{scale / max(dt, 1e-12):.3g} rows ({basis}; no time column)"
        text = (f"residual lag-1 autocorrelation {rho:.2f}, variance {ratio:.1f} x the high-frequency noise floor "
                f"({floor:.3g}); time scale {shown}")
        if best is not None:
            text += "; " + describe(best).rstrip(".")
        out.append({"channel": lab, "axis": lab, "rho1": float(rho), "floor_ratio": ratio, "noise_floor": floor,
                    "time_scale_s": scale if time_available else None, "time_scale_rows": scale / max(dt, 1e-12),
                    "basis": basis,
                    "variable": best["variable"] if best else "time",
                    "where": best["where"] if best else f"time scale {scale:.3g} s",
                    "fraction": best["fraction"] if best else None,
                    "p_value": best["p_value"] if best else None, "description": text})
    return out
