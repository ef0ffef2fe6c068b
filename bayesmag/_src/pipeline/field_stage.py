"""The field-calibration stage: fit a magnitude (or vector) measurement model, score held-out rows,
check heading and compare with a vector fit of the same rows where a vector reference exists.

Pure computation on arrays and :class:`~bayesmag.CalibrationData`; the job (:mod:`bayesmag._src.app.field_job`)
reads the config and writes the files.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from bayesmag._src.core.data import CalibrationData
from bayesmag._src.core.field import (INVARIANT_NAMES, FieldFit, FieldPrior, fit_field, field_target,
                                      gaussian_scores, heading_with_uncertainty, invariants, wrap_deg)
from bayesmag._src.core.measurement import MeasurementModel, Vector

__all__ = ["FieldStage", "run_field_stage", "vector_comparison", "heading_check", "conformal_plan",
           "magnitude_interval_scale", "field_domain_check", "magnitude_transfer"]


@dataclasses.dataclass(frozen=True)
class FieldStage:
    """What the field stage computed."""

    fit: FieldFit
    train: CalibrationData
    test: CalibrationData
    target_test: np.ndarray
    prediction: dict           # predictive distribution of the test magnitudes
    scores: dict               # coverage / NLL / CRPS / RMSE of the test magnitudes
    heading: dict | None       # heading check (None when heading cannot be checked)
    vector: dict | None        # comparison with a vector fit (None without a vector reference)
    timings: dict
    domain: dict | None = None  # training-domain check of the test rows (:func:`field_domain_check`)
    transfer: dict | None = None  # between-session sd of the magnitude (:func:`magnitude_transfer`; None: "off")


def heading_check(fit: FieldFit, data: CalibrationData, rows: np.ndarray, true_heading: np.ndarray,
                  alignment: np.ndarray, level: float = 0.95) -> dict:
    """Heading error (degrees) of the calibrated field on ``rows`` against ``true_heading``, with intervals.

    ``alignment`` (n_rows, 3, 3) maps the gauge frame to the body frame (known attitudes): the
    intervals are conditional on it (a magnitude calibration cannot see that rotation).
    """
    import scipy.stats
    h = heading_with_uncertainty(fit, data.b_meas[rows], data.temperature[rows], alignment)
    err = wrap_deg(h["heading"] - true_heading)
    k = scipy.stats.norm.ppf(0.5 + level / 2)
    return {"n": int(rows.sum() if rows.dtype == bool else len(rows)), "rmse_deg": float(np.sqrt(np.mean(err**2))),
            "max_abs_deg": float(np.max(np.abs(err))), "mean_sd_deg": float(np.mean(h["sd"])),
            "mean_sd_params_deg": float(np.mean(h["sd_params"])), "mean_sd_noise_deg": float(np.mean(h["sd_noise"])),
            "coverage": float(np.mean(np.abs(err) <= k * h["sd"])),
            "coverage_params_only": float(np.mean(np.abs(err) <= k * np.sqrt(h["sd_params"]**2 + 1e-30))),
            "level": level, "conditional_on": "the gauge-to-body rotation (from the known attitudes)",
            "flagged": h["flagged"], "error": err, "sd": h["sd"]}


def field_domain_check(train: CalibrationData, y_train_mag, test: CalibrationData, predicted_mag, *,
                       margin: float = 0.05, half_width=None) -> dict:
    """Which test rows lie outside the training domain of a field calibration.

    The rule of the vector predictor's :class:`~bayesmag._src.core.domain.Domain` (ranges widened by ``margin``
    of their span plus 0.5 uT / 0.5 C): each measured input Bx, By, Bz and the temperature against its
    training range (reasons ``field_range``, ``temperature``), and the predicted field magnitude against the
    training reference magnitudes (``magnitude``: a magnitude calibration is fitted on those magnitudes only;
    outside them an error that grows with the field is extrapolated); with ``half_width`` (n,), the half-width of
    each row's interval, only a row whose whole interval lies outside them
    (:func:`~bayesmag._src.core.field_calibration.range_flags`). Rates are not checked.

    Returns ``in_domain`` (n,) bool, ``reason`` (n,) strings ('' inside, else reasons joined by ``;``) and the
    ranges and counts.

    Example:
      >>> from bayesmag.simulate import simulate_field
      >>> d = simulate_field("dance", n=200, seed=0).data
      >>> r = field_domain_check(d, np.full(200, 50.0), d, np.full(200, 60.0))
      >>> int(r["in_domain"].sum()), r["by_reason"]
      (0, {'magnitude': 200})
    """
    from bayesmag._src.core.domain import _box
    from bayesmag._src.core.field_calibration import DOMAIN_KEYS, range_flags

    lo, hi = _box(np.column_stack([train.b_meas, train.temperature,
                                   np.asarray(y_train_mag, np.float64).reshape(-1)]), margin, 0.5)
    ranges = {k: [a, b] for k, a, b in zip(DOMAIN_KEYS, lo, hi)}
    reason, hits = range_flags(test.b_meas, test.temperature, predicted_mag, ranges, half_width=half_width)
    inside = reason == ""
    return {"in_domain": inside, "reason": reason, "margin": margin, "n_outside": int((~inside).sum()),
            "by_reason": {k: int(h.sum()) for k, h in hits.items() if h.any()}, "training_ranges": ranges}


def vector_comparison(fit: FieldFit, train: CalibrationData, *, covariance: str = "white") -> dict:
    """Fit the vector model to the same rows (same T0) and compare the 18 gauge-free invariants.

    Each invariant the magnitude fit identifies is ``agree`` when
    :math:`|z| = |\\Delta| / \\sqrt{sd_m^2 + sd_v^2} \\le 2`, else ``disagree``; the others are
    ``not identified``. The vector fit's covariance is per axis (as :func:`~bayesmag.fit_physics`).
    """
    import jax
    import jax.numpy as jnp

    from bayesmag._src.core.fit import fit_physics
    from bayesmag._src.core.physics import PhysicsModel

    temp = fit.model.temperature
    vf = fit_physics(train, PhysicsModel.paper(t0=fit.model.t0, temperature=temp),
                     covariance_method="ar1" if covariance == "ar1" else "white")
    th = np.asarray(vf.theta)
    p = th.shape[1]
    cov = np.zeros((3 * p, 3 * p))
    for a in range(3):
        cov[a * p:(a + 1) * p, a * p:(a + 1) * p] = vf.cov[a]

    def inv_of(flat):
        t3 = flat.reshape(3, p)
        if temp:
            return invariants(t3[:, 0:3], t3[:, 3:6], t3[:, 6], t3[:, 7])
        return invariants(t3[:, 0:3], jnp.zeros((3, 3)), t3[:, 3], jnp.zeros(3))

    flat = jnp.asarray(th.reshape(-1))
    v_val = np.asarray(inv_of(flat))
    G = np.asarray(jax.jacfwd(inv_of)(flat))
    v_sd = np.sqrt(np.clip(np.diag(G @ cov @ G.T), 0, None))
    m = fit.invariants()
    rows = []
    for k, name in enumerate(INVARIANT_NAMES):
        sd = float(np.hypot(m["sd"][k], v_sd[k]))
        z = float((m["value"][k] - v_val[k]) / sd) if sd > 0 else float("nan")
        status = ("not identified" if not m["identified"][k] else "agree" if abs(z) <= 2 else "disagree")
        rows.append({"name": name, "magnitude_fit": float(m["value"][k]), "magnitude_sd": float(m["sd"][k]),
                     "vector_fit": float(v_val[k]), "vector_sd": float(v_sd[k]), "z": z, "status": status,
                     "why_not": str(m["why"][k])})
    counts = {s: sum(r["status"] == s for r in rows) for s in ("agree", "disagree", "not identified")}
    return {"rows": rows, "counts": counts, "t0": fit.model.t0, "vector_covariance": vf.covariance_method}


def conformal_plan(test_fraction: float, n_blocks: int, split_kind: str, folds: int) -> tuple[float, int]:
    """``(fraction, folds)``: each fold one contiguous block of ``fraction`` of every run's training rows.

    The blocks are as long as the held-out test blocks (a time-block split: ``test_fraction / n_blocks`` of a
    run, i.e. ``test_fraction / n_blocks / (1 - test_fraction)`` of its training rows; otherwise 0.1), so the
    folds' errors are as hard as the test rows'; at most ``folds`` of them, fewer where they would not fit.

    Example:
      >>> conformal_plan(0.2, 4, "time_blocks", 5)
      (0.0625, 5)
    """
    fraction = test_fraction / n_blocks / (1.0 - test_fraction) if split_kind == "time_blocks" else 0.1
    while folds > 2 and folds * fraction >= 1.0:
        folds -= 1
    return min(fraction, 0.49), folds


def magnitude_interval_scale(train: CalibrationData, measurement: MeasurementModel, y_tr, *, fraction: float,
                             folds: int, level: float = 0.95, seed: int = 0, start: FieldFit | None = None,
                             **fit_kw) -> dict:
    r"""Cross-conformal scale c of the magnitude predictive sd, from time-block folds of the training rows.

    Each fold (:func:`~bayesmag._src.pipeline.conformal.conformal_folds`: one contiguous block of ``fraction`` of every run) is predicted by a fit that did not see it; c is the split-conformal quantile of
    :math:`|y - \hat y| / (z_{level}\, sd_{total})` over all fold rows (Vovk et al. 2005). The Laplace predictive
    assumes independent reading noise at the training level; slow unmodelled structure (drift, a block offset,
    autocorrelated residuals) makes a new time block err more than that, and c says by how much (c ~ 1 when the
    model's noise is right).
    """
    import scipy.stats

    from bayesmag._src.pipeline.conformal import conformal_quantile
    from bayesmag._src.pipeline.conformal import conformal_folds
    fold = conformal_folds(train.run, fraction=fraction, folds=folds, seed=seed)
    if start is not None:                   # the same model (T0, terms) as the fit it starts from
        fit_kw = {**fit_kw, "t0": start.model.t0, "temperature_terms": start.model.temperature}
    zk = scipy.stats.norm.ppf(0.5 + level / 2)
    ratios = []
    for k in range(folds):
        held = fold == k
        if not held.any() or held.all():
            continue
        f = fit_field(train.b_meas, train.temperature, y_tr, measurement, keep=~held, run=train.run, start=start,
                      diagnostics=False, **fit_kw)
        pr = f.predict_magnitude(train.b_meas, train.temperature)          # all rows: one compiled shape
        y = _magnitudes(measurement, y_tr, f)
        ratios.append(np.abs(y[held] - pr["mean"][held]) / (zk * pr["total"][held]))
    r = np.concatenate(ratios)
    c = float(conformal_quantile(r[:, None], level)[0])
    return {"scale": c, "folds": folds, "fraction": fraction, "n": int(r.size),
            "fold_coverage_before": float(np.mean(r <= 1.0))}


def _magnitudes(measurement: MeasurementModel, y, fit: FieldFit) -> np.ndarray:
    """The reference magnitudes of target rows ``y`` as ``fit`` reads them (a fitted field for ``"free"``)."""
    if isinstance(measurement, Vector):
        return np.linalg.norm(y, axis=1)
    return np.asarray(measurement.magnitude(y, fit.matrices()[4]))


def magnitude_transfer(train: CalibrationData, measurement: MeasurementModel, y_tr, fit: FieldFit, *,
                       scale: float = 1.0, level: float = 0.95, min_runs: int = 3, **fit_kw) -> dict:
    r"""Between-session sd of the calibrated magnitude: leave one run out, conformal over runs.

    The field calibration's version of :func:`~bayesmag._src.core.predictor.estimate_transfer`: every training run
    is a session (a flight, a campaign); for each, a refit without it (warm-started from ``fit``, its T0 and terms)
    predicts the run's rows that lie inside the other runs' domain (:func:`field_domain_check` on the readings, the
    temperature and the *reference* magnitude: a predicted magnitude far from the reference is the error measured
    here, not extrapolation), and row ``i`` is
    covered by a variance :math:`s_i^2 + \tau^2` (:math:`s_i`: the refit's predictive sd times the run's conformal
    ``scale``, the within-session part) iff :math:`\tau^2 \ge (e_i/z)^2 - s_i^2`. The grouped ``level`` quantile of
    that bound, every run weighted equally, bounded over the R usable runs
    (:func:`~bayesmag._src.core.predictor.session_variance_bound`, on the runs' mean :math:`s_i^2`), is
    :math:`\tau^2`; the part of :math:`s_i^2` that is white reading noise (the second differences of the pooled
    fit's magnitude residuals within runs, :func:`~bayesmag._src.core.data.second_difference_sd`: thousands of
    differences, not R runs) is taken as exact, so a sensor whose sessions do not differ is not widened by the bound
    on its noise level (simulated: 1.45x -> 1.02x the width, coverage 99.5 -> 95.6 %). A hard-iron change between sessions (a payload, a battery, a power state) moves every
    magnitude by up to its size: it is what this term measures. With fewer than ``min_runs`` usable runs there is
    no estimate (``sd`` None), with a warning.

    Returns ``{"sd", "method", "n_runs", "per_run", "warning"}`` (``method``: ``"leave_one_run_out"``, or
    ``"not_estimated"`` with ``sd`` None and a warning saying why: fewer than ``min_runs`` runs, or fewer whose rows
    lie inside the others' ranges). With fewer than :data:`FEW_SESSIONS` usable runs, or a run whose mean error stands
    apart from the others', ``warning`` says so.
    """
    import scipy.stats

    from bayesmag._src.core.data import second_difference_sd
    from bayesmag._src.core.predictor import session_variance_bound
    fit_kw = {**fit_kw, "t0": fit.model.t0, "temperature_terms": fit.model.temperature}
    z = scipy.stats.norm.ppf(0.5 + level / 2)
    runs = [int(r) for r in np.unique(train.run)]
    per_run, need, weight, within = {}, [], [], []
    if len(runs) >= min_runs:
        for r in runs:
            held = train.run == r
            f = fit_field(train.b_meas, train.temperature, y_tr, measurement, keep=~held, run=train.run, start=fit,
                          diagnostics=False, **fit_kw)
            pr = f.predict_magnitude(train.b_meas, train.temperature)          # all rows: one compiled shape
            y = _magnitudes(measurement, y_tr, f)
            other, left = train.subset(np.flatnonzero(~held)), train.subset(np.flatnonzero(held))
            # the left-out run's reference magnitudes, not its predicted ones, against the others': a predicted
            # magnitude far from the reference is the session change measured here, not extrapolation
            inside = field_domain_check(other, y[~held], left, y[held])["in_domain"]
            per_run[str(r)] = {"n_rows": int(held.sum()), "n_in_domain": int(inside.sum()), "rmse": None,
                               "mean_error": None, "converged": bool(f.converged)}
            if inside.sum() < 2 or not f.converged:     # extrapolation only, or an unidentifiable fold: skipped
                continue
            e = (y[held] - pr["mean"][held])[inside]
            s2 = (scale * pr["total"][held][inside]) ** 2
            need.append((e / z) ** 2 - s2)
            weight.append(np.full(e.size, 1.0 / e.size))
            within.append(float(np.mean(s2)))
            per_run[str(r)].update(rmse=float(np.sqrt(np.mean(e**2))), mean_error=float(np.mean(e)))
    resid = _magnitudes(measurement, y_tr, fit) - fit.predict_magnitude(train.b_meas, train.temperature)["mean"]
    if len(need) >= min_runs:
        # the within-session white noise, from thousands of row-to-row differences, is known well: only the rest of
        # the new-session variance is uncertain by the few runs it comes from (the bound's R - 1 dof)
        w = second_difference_sd(resid[:, None], train.run, min_rows=20, time=train.time)
        white = 0.0 if w is None else float(w[0]) ** 2
        tau = session_variance_bound(np.concatenate(need), np.concatenate(weight), float(np.mean(within)),
                                     len(need), level, exact=white)
        notes = _session_warnings(per_run, float(np.sqrt(white)))
        return {"sd": tau, "method": "leave_one_run_out", "n_runs": len(need), "per_run": per_run,
                "warning": " ".join(notes) or None, "white_noise_sd": float(np.sqrt(white))}
    # Fewer usable runs: no estimate. (The vector calibration's stand-in, the largest change of a run's mean
    # residual, is about zero here by construction: over a turn a hard-iron change averages out of the mean |B|
    # residual, while it moves every row's |B| by up to its size; one or two simulated training flights gave
    # 0.02-0.12 uT and covered 20-89 % of new flights.)
    if len(runs) < min_runs:
        why = (f"the training data hold {len(runs)} run(s) (sessions: flights, or campaigns on different days), and "
               f"a between-session term needs at least {min_runs}")
    else:
        why = (f"of the {len(runs)} training runs only {len(need)} have rows inside the other runs' ranges of field, "
               f"temperature and reference magnitude (at least {min_runs} must, to be predicted as a new session "
               f"rather than extrapolated)")
    warning = (f"The field calibration holds no between-session (transfer) term: {why}. Its magnitude intervals for a "
               f"new session cover only the error within a session and can be far too narrow (simulated vehicles "
               f"whose hard iron moves 0.3 uT between flights: one or two training flights covered 20-89 % of new "
               f"flights). Record at least {min_runs} sessions that overlap in field and temperature.")
    return {"sd": None, "method": "not_estimated", "n_runs": len(need), "per_run": per_run, "warning": warning}


#: Fewer usable runs than this make the field's between-session term rough (said; docs/field.md).
FEW_SESSIONS = 6
#: A left-out run whose mean |B| error is this many times the other runs' spread from theirs is named.
RUN_OFFSET_Z = 5.0


def _session_warnings(per_run: dict, white_sd: float) -> list[str]:
    """What the leave-one-run-out table says about the sessions: few of them, and a run whose mean |B| error stands
    apart (another site's field declared as this one's, or a changed vehicle)."""
    used = {r: v for r, v in per_run.items() if v.get("mean_error") is not None}
    out = []
    if len(used) < FEW_SESSIONS:
        out.append(f"The between-session term comes from {len(used)} sessions only: it is rough (three simulated "
                   f"similar flights covered 64-100 % of a set of new flights, or needed 1.5-2.7x the width). Record "
                   f"{FEW_SESSIONS} or more.")
    me = {r: v["mean_error"] for r, v in used.items()}
    for r, e in me.items():
        others = np.array([v for k, v in me.items() if k != r])
        if others.size < 2:
            continue
        spread = max(float(np.std(others)), white_sd, 1e-3)
        if abs(e - others.mean()) > RUN_OFFSET_Z * spread:
            out.append(f"Run {r}'s |B| is {e:+.3g} uT off the fit of the other runs (theirs {others.min():+.3g} to "
                       f"{others.max():+.3g} uT): a flight at another site's field declared as this one's (give each "
                       f"site's F, or use a scalar reference), or a vehicle changed more than in the other sessions. "
                       f"It widens the between-session term of every new flight; check it, and leave it out if it "
                       f"does not belong.")
    return out


def run_field_stage(train: CalibrationData, test: CalibrationData, measurement: MeasurementModel, *,
                    f_ref_train=None, f_ref_test=None, t0="mean", temperature_terms="auto", covariance="white",
                    level: float = 0.95, prior: FieldPrior = FieldPrior(), heading: dict | None = None,
                    compare_vector: bool = True, conformal: tuple[float, int] | None = None,
                    seed: int = 0, transfer: str = "loro") -> FieldStage:
    """Fit on ``train`` (the vector reference withheld down to what ``measurement`` sees), score ``test``.

    ``heading`` = ``{"rows": bool mask of test rows, "true": degrees, "alignment": (k, 3, 3)}`` when heading
    can be checked (simulated attitudes, or a heading reference). ``conformal`` = ``(fraction, folds)``
    (:func:`conformal_plan`) scales the magnitude intervals by :func:`magnitude_interval_scale`; ``None``
    keeps the Laplace predictive as it is. ``transfer`` = ``"loro"`` estimates the between-session sd of the
    magnitude (:func:`magnitude_transfer`); it enters the test rows of runs the fit did not see (a ``by_run``
    split: new sessions); ``"off"`` leaves it out.
    """
    import scipy.stats

    from bayesmag._src.core.physics import check_t0
    check_t0(t0, train.temperature, "Config key 'physics.t0'")     # a kelvin t0 beside kelvin data: as the vector job
    timings = {}
    t = time.perf_counter()
    y_tr = field_target(measurement, b_ref=train.b_ref, f_ref=f_ref_train, n=train.n)
    fit_kw = dict(t0=t0, temperature_terms=temperature_terms, covariance=covariance, prior=prior)
    fit = fit_field(train.b_meas, train.temperature, y_tr, measurement, run=train.run,
                    field_unit=None if train.field_unit is None else "uT", **fit_kw)   # declared: converted
    timings["field_fit"] = time.perf_counter() - t
    cal = None
    if conformal is not None:
        t = time.perf_counter()
        cal = magnitude_interval_scale(train, measurement, y_tr, fraction=conformal[0], folds=conformal[1],
                                       level=level, seed=seed, start=fit, **fit_kw)
        timings["conformal"] = time.perf_counter() - t
    tr = None
    if transfer == "loro":
        t = time.perf_counter()
        tr = magnitude_transfer(train, measurement, y_tr, fit, scale=1.0 if cal is None else cal["scale"],
                                level=level, **fit_kw)
        timings["transfer"] = time.perf_counter() - t
    elif transfer != "off":
        raise ValueError(f"transfer = {transfer!r}: a field calibration's between-session term is \"loro\" or \"off\"")
    t = time.perf_counter()
    pred = fit.predict_magnitude(test.b_meas, test.temperature)
    y_mag = _magnitudes(measurement, field_target(measurement, b_ref=test.b_ref, f_ref=f_ref_test, n=test.n), fit)
    new = ~np.isin(test.run, np.unique(train.run))          # rows of sessions the fit did not see
    tau = np.where(new, 0.0 if tr is None or tr["sd"] is None else tr["sd"], 0.0)
    laplace = np.sqrt(pred["total"] ** 2 + tau**2)
    raw = gaussian_scores(y_mag, pred["mean"], laplace, level)
    c = 1.0 if cal is None else cal["scale"]
    pred = {**pred, "transfer": tau, "total": np.sqrt((c * pred["total"]) ** 2 + tau**2)}
    if cal is not None:
        pred.update(laplace_total=laplace, scale=c)
    scores = gaussian_scores(y_mag, pred["mean"], pred["total"], level)
    y_tr_mag = _magnitudes(measurement, y_tr, fit)
    zk = scipy.stats.norm.ppf(0.5 + level / 2)
    dom = field_domain_check(train, y_tr_mag, test, pred["mean"], half_width=zk * pred["total"])
    scores.update(_domain_scores(y_mag, pred["mean"], pred["total"], dom["in_domain"], level))
    scores["interval_calibration"] = (None if cal is None else
                                      {**cal, "laplace_coverage": raw["coverage"], "laplace_nll": raw["nll"],
                                       "laplace_crps": raw["crps"], "laplace_mean_width": raw["mean_width"]})
    timings["field_predict"] = time.perf_counter() - t
    hd = None
    if heading is not None and np.any(heading["rows"]):
        t = time.perf_counter()
        hd = heading_check(fit, test, heading["rows"], heading["true"], heading["alignment"], level)
        timings["heading"] = time.perf_counter() - t
    vec = None
    if compare_vector and train.has_reference and not isinstance(measurement, Vector):
        t = time.perf_counter()
        vec = vector_comparison(fit, train, covariance=covariance)
        timings["vector_comparison"] = time.perf_counter() - t
    return FieldStage(fit, train, test, y_mag, pred, scores, hd, vec, timings, dom, tr)


def _domain_scores(y, mean, sd, inside, level) -> dict:
    """Scores split by the domain flag: coverage inside, and "covered or flagged" over all rows."""
    import scipy.stats
    covered = np.abs(np.asarray(y) - mean) <= scipy.stats.norm.ppf(0.5 + level / 2) * sd
    return {"n_in_domain": int(inside.sum()), "n_outside_domain": int((~inside).sum()),
            "coverage_in_domain": float(np.mean(covered[inside])) if inside.any() else None,
            "rmse_in_domain": float(np.sqrt(np.mean((y - mean)[inside] ** 2))) if inside.any() else None,
            "covered_or_flagged": float(np.mean(covered | ~inside))}
