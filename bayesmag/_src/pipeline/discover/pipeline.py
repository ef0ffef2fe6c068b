r"""Discovery of missing physics: search the catalogue in the sensor's frame, check the set, describe the rest.

1. **Baseline**: the thermo-affine model per output; each output weighted by 1 / its
   high-frequency noise floor; folds of contiguous time blocks (or runs).
2. **Search** (:mod:`.search`): every catalogue entry on every sensor channel, every output,
   or the whole sensor, scored out of sample against the current joint model; forward
   selection.
3. **Checks** (:mod:`.checks`): drop-one refits of the whole finding set; coefficients the
   data do not identify are removed; a per-run term that is not constant within its runs is
   removed (reported as unexplained); the joint model is refitted exactly (:mod:`.frame`, one
   LM over 24 + k parameters) and nonlinear values outside the entry's physical range
   remove the effect. A finding whose rivals (``Entry.rivals``) could not be searched states
   its explanation as one possible cause.
4. **Describe** (:mod:`.diagnostics`): the final residual, mapped back to the sensor
   channels, is located again; structure left (strong autocorrelation above the noise floor,
   or located patterns) is reported as unexplained with its time scale.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time as _time

import jax.numpy as jnp
import numpy as np
from scipy import stats

from bayesmag._src.core import catalogue as C
from bayesmag._src.core.data import AXES, CalibrationData
from bayesmag._src.core.fit import covariance, lag1_autocorrelation
from bayesmag._src.core.physics import ThermoAffine, inputs_from_data
from bayesmag._src.pipeline.discover.checks import constant_within_runs, drop_one, identified, lag_or_smoothing
from bayesmag._src.pipeline.discover.diagnostics import block_z, block_ids, block_length, correlation_time, locate, \
    make_variables, noise_floor, run_starts, structure
from bayesmag._src.pipeline.discover.frame import Designs, Extension, JointModel, gain_matrix, log_noise_se, lstsq, \
    refit, temperature_log_sd
from bayesmag._src.pipeline.discover.intervals import profile_interval, profile_minimiser, step_interval
from bayesmag._src.pipeline.discover.options import DELTA_SYS_FRACTION, MIN_GAIN, N_BOOT_LAG, ROWS_PER_PARAM, \
    Z_DISTINCT, Z_MIN, DiscoverOptions
from bayesmag._src.core.physics import resolve_t0
from bayesmag._src.pipeline.discover.result import DiscoveryResult
from bayesmag._src.pipeline.discover.search import compare, cv_residuals, forward, groups, relocate, row_loss, \
    score_group, step_parts

__all__ = ["discover"]


def _folds(data, options, notes, corr_rows):
    same = ~run_starts(data.run)[1:]
    dt = float(np.median(np.diff(data.time)[same])) if same.any() else 1.0
    if options.block_s is not None:
        block_rows = max(10, int(round(options.block_s / max(dt, 1e-9))))
    else:
        block_rows = int(np.clip(max(data.n // 150, corr_rows), 10, max(10, data.n // 30)))
    blocks = block_ids(data, block_rows)
    runs = np.unique(data.run)
    if options.cv == "by_run":
        if runs.size < 2:
            notes.append(f"cv = 'by_run' needs at least two runs; the data has one (run {runs[0]}), so "
                         f"contiguous time blocks ({options.n_folds} folds) are used instead.")
        else:
            return np.searchsorted(runs, data.run), blocks, f"leave-one-run-out over {runs.size} runs"
    nb = blocks.max() + 1
    folds = blocks % int(options.n_folds) if nb >= int(options.n_folds) else blocks
    return folds, blocks, (f"{int(options.n_folds)}-fold cross-validation by contiguous time blocks "
                           f"(~{block_rows} rows each, {nb} blocks)")


def _context(data, t0, dt, W0=None) -> C.SearchContext:
    runs = tuple(int(r) for r in dict.fromkeys(data.run.tolist()))
    spans = [float(np.ptp(data.time[data.run == r])) for r in runs]
    heated = [sp for r, sp in zip(runs, spans) if np.ptp(data.temperature[data.run == r]) >= 1.0]
    bounds = tuple((r, float(data.time[data.run == r].min()), float(data.time[data.run == r].max())) for r in runs)
    b = data.b_meas
    same = ~run_starts(data.run)[1:]
    steps = [float(1.4826 * np.median(np.abs(np.diff(b[:, k])[same]))) + 1e-9 for k in range(3)]
    return C.SearchContext(t0=t0, dt=dt, time_ref=float(data.time[0]), runs=runs,
                           run_span=float(np.median(spans)) if spans else 1.0,
                           reach=tuple(float(np.quantile(np.abs(b[:, k]), 0.98)) for k in range(3)),
                           step_noise=tuple(steps),
                           cal=tuple(tuple(float(v) for v in w) for w in W0) if W0 is not None and W0.shape[1] in (4, 8)
                           else (),
                           ref_reach=tuple(float(np.quantile(np.abs(data.b_ref[:, k]), 0.98)) for k in range(3)),
                           heated_span=max(heated) if heated else (max(spans) if spans else 1.0), run_bounds=bounds,
                           magnitude_reach=float(np.quantile(np.linalg.norm(b, axis=1), 0.98)))


def _label(ext) -> str:
    c = ext.component
    fields = {f.name: getattr(c, f.name) for f in dataclasses.fields(c)
              if f.name not in ("t0", "cal", "time_ref", "run_ref", "runs", getattr(c, "start_field", None))}
    inner = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in fields.items())
    place = "whole sensor" if ext.frame == "whole" else f"{AXES[ext.slot]} {'channel' if ext.frame == 'sensor' else 'output'}"
    cols = f", {'+'.join(ext.param_names)}" if ext.frame != "whole" else ""
    return f"{c.name}({inner}{', ' if inner else ''}{place}{cols})"


def _spec(ext, value) -> dict:
    """The ``extra_terms`` table of a finding: its fields (a transform started at its fitted ``value``)."""
    c = ext.component.started(value) if value is not None else ext.component
    return {"name": c.name, **{f.name: getattr(c, f.name) for f in dataclasses.fields(c) if f.name != "t0"}}


def _scores(y, pred, e_oos_w, w, run) -> list:
    n = y.shape[0]
    e = e_oos_w.reshape(3, n).T / w
    r = y - pred
    return [{"rmse": float(np.sqrt(np.mean(e[:, a] ** 2))), "mae": float(np.mean(np.abs(e[:, a]))),
             "lag1_autocorrelation": lag1_autocorrelation(r[:, a], run),
             "rmse_in_sample": float(np.sqrt(np.mean(r[:, a] ** 2)))} for a in range(3)]


def _axis_dict(per_axis: list) -> dict:
    return {k: {ax: per_axis[a][k] for a, ax in enumerate(AXES)} for k in per_axis[0]}


def _to_channels(base, W, t, resid) -> np.ndarray:
    """Output residuals (n, 3) mapped back to the sensor channels: solve (S + Ks Tc) r_ch = r."""
    G = gain_matrix(base, W, t)
    return np.linalg.solve(G, resid[..., None])[..., 0]


def _dominant(ext, theta, sl, inputs) -> str:
    """The variable the effect is drawn against: for a linear term, the one of its column with the
    largest contribution (rms of coefficient x feature), e.g. Bz for a reading that gains mostly q_zz Bz^2."""
    if ext.frame == "whole":
        return ext.component.depends_on(ext.setting.cols)
    F = np.asarray(ext.features(inputs))
    contrib = np.sqrt(np.mean((F * theta[sl[ext]][None, :]) ** 2, axis=0))
    cols = ext.setting.cols if ext.setting.cols is not None else tuple(range(F.shape[1]))
    return ext.component.depends_on((int(cols[int(np.argmax(contrib))]),))


def _untested(skipped: list, cands: dict, step_note: str | None) -> dict:
    """Candidate name -> why it was not (reliably) searched: skipped for a missing requirement, or, when the time
    column's step suggests ms or us stamps (``step_note``), searched with time read in seconds."""
    out = {s["candidate"]: s["reason"] for s in skipped}
    if step_note:
        for name in dict.fromkeys(k[0] for k in cands):
            if "time" in C.CATALOGUE[name].requires and name not in out:
                out[name] = "searched with the time column read in seconds, whose step suggests ms or us stamps"
    return out


def _explanation(comp, untested: dict, within=None) -> str:
    """The entry's explanation, or that explanation stated as one possible cause when these data cannot support it:
    rivals that can give the same pattern were not searched (``untested``: they are named with why and how to test
    them), or a per-run constant is in doubt within its runs (``within``, :class:`~.checks.WithinRun`: offsets per
    piece of a run predict >= MIN_GAIN better out of sample, though the serial contrast is below Z_DISTINCT)."""
    rv = [r for r in getattr(comp, "rivals", ()) if r in untested]
    doubt = within is not None and within.gain >= MIN_GAIN and not within.wanders
    if not rv and not doubt:
        return comp.explanation
    why = []
    if rv:
        fix = ("declare the time column's unit ([data] time_unit) to test them on their own time scale"
               if any("seconds" in untested[r] for r in rv) else
               "a recording with a time column (seconds) can test them")
        why.append(f"{', '.join(rv)} can also give this pattern and {'was' if len(rv) == 1 else 'were'} not searched "
                   f"({'; '.join(sorted({untested[r] for r in rv}))}); {fix}")
    if doubt:
        why.append(f"the offset may also wander within runs (an offset for each of up to {within.pieces} pieces of a "
                   f"run predicts {within.gain:.1%} better out of sample; neighbouring blocks alike at serial z = "
                   f"{within.z:.2f}, short of {Z_DISTINCT} by {Z_DISTINCT - within.z:.2f})")
    return (f"One possible cause: {comp.explanation[0].lower()}{comp.explanation[1:]} Not established by these data: "
            + "; and ".join(why) + ".")


def _established(comp, untested: dict, within=None) -> dict:
    """``untested_rivals`` and ``cause_established = False`` where :func:`_explanation` qualifies the cause."""
    rv = [{"effect": r, "reason": untested[r]} for r in getattr(comp, "rivals", ()) if r in untested]
    doubt = within is not None and within.gain >= MIN_GAIN and not within.wanders
    return ({**({"untested_rivals": rv} if rv else {}), "cause_established": False} if rv or doubt else {})


def _wander_text(w) -> str:
    return (f"neighbouring blocks of a run are more alike than in random order (serial z = {w.z:.2f} >= "
            f"{Z_DISTINCT}, p = {w.p:.2g}) and an offset for each of up to {w.pieces} pieces of every run predicts "
            f"better out of sample (a further {w.gain:.1%} of the out-of-sample mean square, >= {MIN_GAIN:.0%})")


def _within_json(w) -> dict:
    return {"serial_z": w.z, "serial_p": w.p, "pieces": w.pieces, "gain_pieces": w.gain,
            "wanders": bool(w.wanders)}


def _add_wander(unexplained: list, e, w, sc, place: np.ndarray, run: np.ndarray, dt: float, time_ok: bool) -> list:
    """``unexplained`` with the structure of a run-localised term that was not constant within its runs (``w``,
    :func:`~.checks.constant_within_runs`) added to its place's entry (a sensor channel's, or a new one for an
    output): per-run offsets were accepted, pieces of each run predict better still."""
    label = AXES[e.slot]
    acc = (f"{sc.decided_by} = {sc.z_decisive:.2f}, gain {sc.gain:.1%}" if sc is not None else "accepted by the search")
    ct = correlation_time(place - place.mean(), dt)
    scale = f"{ct:.3g} s" if time_ok else f"{ct / max(dt, 1e-12):.3g} rows (no time column)"
    text = (f"the offset differs between runs and wanders within them: {e.name} was accepted by the search ({acc}), "
            f"but {_wander_text(w)}, so it is not a constant per run; correlation time {scale}")
    rec = {"within_run": _within_json(w), "rejected_term": e.name}
    for u in unexplained:
        if u["channel"] == label and e.frame == "sensor":
            u.update(rec, description=u["description"] + "; " + text)
            return unexplained
    floor = noise_floor(place, run)
    return unexplained + [{
        "channel": label, "axis": label, "frame": e.frame,
        "rho1": float(lag1_autocorrelation(place - place.mean(), run)),
        "floor_ratio": float(np.var(place) / max(floor ** 2, 1e-300)), "noise_floor": floor,
        "time_scale_s": ct if time_ok else None, "time_scale_rows": ct / max(dt, 1e-12), "basis": "correlation time",
        "variable": "run", "where": "differs between runs and within them", "fraction": None, "p_value": None,
        "description": text, **rec}]


def _localised_ext(ext) -> bool:
    return ext.frame != "whole" and getattr(ext.component, "localised", None) == "run"


def _unstated_run(designs, kept, ext, run_k, e_fin, folds3, blocks, run) -> str | None:
    """Why the run whose mean stands out most in a run-localised finding has no stated offset:
    its offset alone, added to the final model (value +- Newey-West se), and the block z of that
    addition out of sample; None when the finding reports that run's offset."""
    name = f"o_{run_k}"
    runs = list(ext.component.runs[1:])
    if name in ext.param_names or run_k not in runs:
        return None
    alone = Extension(dataclasses.replace(ext.setting, cols=(runs.index(run_k),)), ext.frame, ext.slot)
    model = tuple(kept) + (alone,)
    X = designs.matrix(model)
    beta = lstsq(X, designs.y)
    run3 = np.concatenate([run + a * (int(run.max()) + 1) for a in range(3)])
    cov, _ = covariance(X, designs.y - X @ beta, method="newey_west", run=run3)
    v, sd = float(beta[-1]), float(np.sqrt(max(cov[-1, -1], 0.0)))
    e_new, _, _, _ = cv_residuals(designs, model, [None], folds3)
    z = block_z(row_loss(e_fin, designs.n) - row_loss(e_new, designs.n), blocks)
    if z >= Z_MIN:
        return None
    return (f"run {run_k}'s mean stands out most in the by-run contrast, but an offset of run {run_k} alone, added "
            f"to the final model, fits {name} = {v:.3g} +- {sd:.2g} in sample (t = {abs(v) / max(sd, 1e-300):.2f}) "
            f"and predicts no better out of sample (block z = {z:.2f} < {Z_MIN}): the step of run {run_k} cannot be "
            f"stated as a finding from these data")


def _tau_interval(designs, others, lag, log_tau, se_log, block_rows, seed, se_t=0.0) -> dict:
    """95 % interval of a thermal lag's tau by the block bootstrap of its profile
    (:func:`~.intervals.profile_interval`, on log tau), moved so that the profile's minimiser
    on all rows falls on the joint fit's value; widened while replicates pile up at a grid edge.
    ``se_t``: the se of log tau from the temperature log's noise (:func:`~.frame.log_noise_se`),
    added in quadrature to each side of the bootstrap interval and to the Newey-West se."""
    half = float(np.clip(6 * se_log, 0.1, 1.5))
    for _ in range(3):
        grid = log_tau + np.linspace(-half, half, 25)
        lo, hi, best, edge = profile_interval(
            lambda v: designs.matrix(others + (Extension(dataclasses.replace(lag.setting, nl=float(v)), "whole"),)),
            designs.y, grid, block_rows, outputs=3, n_boot=N_BOOT_LAG, seed=seed)
        if edge <= 0.01:
            break
        half *= 2
    shift = log_tau - best
    # the bootstrap resamples residuals with the designs fixed: the log's noise (an input of the
    # lag) is added in quadrature; never narrower than +-1.96 of the joint fit's Newey-West se
    # with that share added (on the chamber generator the bootstrap alone covered tau in 15/18
    # first-order campaigns)
    se_all = math.hypot(se_log, se_t)
    lo = log_tau - math.hypot(log_tau - (lo + shift), 1.96 * se_t)
    hi = log_tau + math.hypot(hi + shift - log_tau, 1.96 * se_t)
    lo, hi = min(lo, log_tau - 1.96 * se_all), max(hi, log_tau + 1.96 * se_all)
    form = {}
    comp = lag.component
    if int(getattr(comp, "nodes", 1)) == 2:
        # the housing's share of the delay is not fitted: the interval also covers tau's minimiser
        # for shares 0.2 and 0.8 (a steady ramp fixes the sum, the transients the share)
        for share in (0.2, 0.8):
            alt = dataclasses.replace(lag.setting, component=dataclasses.replace(comp, split=share))
            m = profile_minimiser(lambda v: designs.matrix(others + (Extension(dataclasses.replace(alt, nl=float(v)),
                                                                               "whole"),)), designs.y, grid) + shift
            lo, hi = min(lo, m), max(hi, m)
        form = {"interval_form": "widened to cover tau for housing shares 0.2 to 0.8 of the delay"}
    return {"interval95": [float(math.exp(lo)), float(math.exp(hi))], **form,
            "interval_method": (f"moving-block bootstrap ({N_BOOT_LAG} replicates, blocks of {block_rows} rows) of "
                                f"the least-squares profile over log tau with the temperature log's noise added in "
                                f"quadrature, joined with +-1.96 se (Newey-West and the log's noise)"),
            **({"interval_open": f"{edge:.0%} of the replicates at the edge of +-{half:.2g} in log tau"}
               if edge > 0.01 else {})}


def _locate_interval(designs, others, ext, ctx, block_rows, seed) -> dict:
    """Where a located effect (a step inside a run) sits, with a 95 % interval (block bootstrap of its profile).

    A step: the exact profile over every sample time of its run (:func:`~.intervals.step_interval`),
    the estimate the minimiser of that same profile given the other findings (the value the
    model uses once :func:`discover` has relocated it), so the interval is about the estimate
    it is printed with."""
    comp = ext.component
    field = comp.located
    if hasattr(comp, "run_id") and field == "at":
        Z, col, rows, time = step_parts(designs, others, ext)
        s = step_interval(Z, col, designs.y, rows, time, block_rows, n_boot=N_BOOT_LAG, seed=seed)
        lo, hi, value, edge = s["lower"], s["upper"], s["estimate"], s["edge"]
        method = (f"moving-block bootstrap ({N_BOOT_LAG} replicates, blocks of {block_rows} rows) of the exact "
                  f"least-squares profile over every sample time of run {int(comp.run_id)}; the interval spans the "
                  f"sample pairs between which the replicates place the step")
        where = "the first or last 2 % of the run"
    else:
        grid = comp.located_grid(ctx)
        move = lambda v: Extension(dataclasses.replace(ext.setting, component=dataclasses.replace(comp, **{field: float(v)})),  # noqa: E731
                                   ext.frame, ext.slot)
        lo, hi, _, edge = profile_interval(lambda v: designs.matrix(others + (move(v),)), designs.y, grid, block_rows,
                                           outputs=3, n_boot=N_BOOT_LAG, seed=seed)
        value = float(getattr(comp, field))
        method = (f"moving-block bootstrap ({N_BOOT_LAG} replicates, blocks of {block_rows} rows) of "
                  f"the least-squares profile over {field}")
        where = "the searched window"
    return {"field": field, "value": float(value), "interval95": [float(lo), float(hi)], "unit": "s",
            **({"run": int(comp.run_id)} if hasattr(comp, "run_id") else {}),
            "interval_method": method,
            **({"interval_open": f"{edge:.0%} of the replicates at the edge of {where}"} if edge > 0.01 else {})}


def discover(data, options: DiscoverOptions | None = None, *, progress=None, columns: dict | None = None,
             field_unit: str | None = None, temperature_unit: str = "C", **kwargs) -> DiscoveryResult:
    """Locate, name and model physics missing from the thermo-affine calibration model.

    Args:
      data: a recording with a reference: :class:`~bayesmag.CalibrationData`, a pandas DataFrame
        (canonical names or ``columns``) or a NumPy array (n, 7) in the order ``data.ARRAY_COLUMNS``.
      columns, field_unit, temperature_unit: as ``frames.as_calibration_data`` (field checked to be in
        uT and temperature in C unless a unit is declared, then converted).
      options: :class:`DiscoverOptions`; or give its fields as keyword arguments.
      progress: optional callable receiving one line per stage.

    Returns:
      :class:`DiscoveryResult` (``bayesmag.write_discovery(res, dir)`` writes findings.json, report.md, figures).

    Example:
      >>> from bayesmag.simulate import simulate, get_effect
      >>> d = simulate(3000, design="campaign", seed=0, effects=[get_effect("cubic", out="x", inp="x")])
      >>> r = discover(d, figures=False)
      >>> [(f["channel"], f["effect"]) for f in r.findings][:1]
      [('x', 'cubic_nonlinearity')]
    """
    t_start = _time.perf_counter()
    say = progress or (lambda msg: None)
    if options is None:
        options = DiscoverOptions(**kwargs)
    elif kwargs:
        raise TypeError(f"give options or keyword arguments, not both; got keywords {sorted(kwargs)}.")
    if not isinstance(data, CalibrationData) or columns or field_unit is not None or temperature_unit != "C":
        from bayesmag._src.core.frames import as_calibration_data
        if not isinstance(data, CalibrationData) and not hasattr(data, "shape") and not hasattr(data, "columns"):
            raise TypeError(f"data must be a CalibrationData, a DataFrame or a NumPy array; got {type(data).__name__}.")
        data = as_calibration_data(data, columns=columns, field_unit=field_unit, temperature_unit=temperature_unit,
                                   require_reference=True, what="the data given to discover")
    if data.b_ref is None:
        raise ValueError("discovery needs a recording with reference columns (b_ref); this one has none.")
    from bayesmag._src.core.data import validate_for_discover
    # finite, plausible uT/Celsius values, rows sorted by time (issue 11), no timestamp repeated within a run
    validate_for_discover(data, time_available=options.time_available)
    if data.n < 50:
        raise ValueError(f"discovery needs at least 50 rows; the data has {data.n}.")
    notes, skipped, rejected = [], [], []
    # ---- baseline
    time_ok = options.time_available
    step_note = None
    if time_ok is None:
        time_ok = not np.array_equal(data.time, np.arange(data.n, dtype=np.float64))
        if not time_ok:
            notes.append("The data have no time column (time equals the row index): time-domain candidates "
                         "and the periodicity check are skipped.")
    if time_ok:
        from bayesmag._src.core.data import time_step_warning
        step_note = time_step_warning(data)
        if step_note:
            notes.append(step_note)
    t_std = float(np.std(data.temperature))
    temp_terms = t_std > 0.05
    t0 = resolve_t0(options.t0, data.temperature)
    base = ThermoAffine(t0=t0, temperature=temp_terms)
    if not temp_terms:
        notes.append(f"Temperature varies by only {t_std:.3g} C (sd): the base model has no temperature terms.")
    inputs = inputs_from_data(data)
    y = np.asarray(data.b_ref)
    run = np.asarray(data.run)
    X0 = np.asarray(base.features(inputs))
    W0 = np.stack([lstsq(X0, y[:, a]) for a in range(3)])
    base_resid = y - X0 @ W0.T
    floors = np.array([noise_floor(base_resid[:, a], run) for a in range(3)])
    w = 1.0 / np.maximum(floors, 1e-12)
    corr_rows = max(block_length(base_resid[:, a]) for a in range(3))
    folds, blocks, cv_desc = _folds(data, options, notes, corr_rows)
    folds3 = np.tile(folds, 3)
    same = ~run_starts(run)[1:]
    dt = float(np.median(np.diff(data.time)[same])) if same.any() else 1.0
    designs = Designs(base, inputs, y, w, gain_matrix(base, W0, np.asarray(data.temperature)))
    ctx = _context(data, t0, dt, W0)
    say(f"baseline thermo-affine fit on {data.n} rows; {cv_desc}")

    # ---- candidate groups from the registry
    has = set()
    if time_ok:
        has.add("time")
        if not (np.diff(data.time)[same] <= 0).any():
            has.add("increasing_time")
    if temp_terms:
        has.add("temperature")
    if len(ctx.runs) >= 2 and options.cv != "by_run":
        has.add("runs")
    names = list(options.candidates or C.CATALOGUE)
    n_train_min = int(np.min([np.sum(folds != k) for k in np.unique(folds)]))
    for name in names:
        missing = sorted(set(C.CATALOGUE[name].requires) - has)
        if missing:
            why = {"time": "a time column", "increasing_time": "time increasing within each run",
                   "temperature": f"temperature variation (sd {t_std:.3g} C)",
                   "runs": "two or more runs and cv = 'time_blocks'"}
            skipped.append({"candidate": name, "reason": "needs " + ", ".join(why[m] for m in missing)})
    cands = groups(ctx, [n for n in names if n not in {s["candidate"] for s in skipped}], has)
    k_base = 3 * len(base.param_names())
    too_big = sorted({k[0] for k, opts in cands.items()
                      if n_train_min < ROWS_PER_PARAM * (k_base + max(o.n_linear for o in opts))})
    for name in too_big:
        skipped.append({"candidate": name, "reason": f"needs at least {ROWS_PER_PARAM} training rows per parameter; "
                                                     f"a fold has {n_train_min}"})
    cands = {k: v for k, v in cands.items() if k[0] not in too_big}
    for s in skipped:
        notes.append(f"Candidate {s['candidate']} skipped: {s['reason']}.")
    untested = _untested(skipped, cands, step_note)

    def n_eff_fn(r):
        rho = np.mean([max(lag1_autocorrelation(r.reshape(3, -1)[a], run), 0.0) for a in range(3)])
        return r.size * (1 - rho) / (1 + rho)

    e0, r0, _, k0 = cv_residuals(designs, (), [None], folds3)
    say(f"searching {len(cands)} candidate groups ({sum(len(v) for v in cands.values())} settings)")
    selected, steps, _, closest = forward(designs, cands, folds3, blocks, (e0, r0, k0), n_eff_fn,
                                          int(options.max_terms), progress=say, ctx=ctx)
    kept, dropped = drop_one(designs, selected, folds3, blocks, n_eff_fn, progress=say)
    for ext, s in dropped:
        rejected.append({"effect": ext.name, "where": _label(ext),
                         "reason": f"does not survive the drop-one check: given the other findings its out-of-sample "
                                   f"gain is {s.gain:.1%} (block z = {s.z:.1f}, BIC_eff change {s.dbic:.1f})"})
    kept, not_ident = identified(designs, kept, run)
    # a run-localised finding claims a constant per run: its columns split into pieces of each run must
    # not predict better (a random walk or an untested lag/drift wanders within runs; a re-seat does not)
    within, wander = {}, []
    step_score = {st["score"].key: st["score"] for st in steps}
    for e in [x for x in kept if _localised_ext(x)]:
        wr = constant_within_runs(designs, kept, e, folds3, blocks, seed=options.seed)
        if wr is None:
            continue
        within[e] = wr
        if wr.wanders:
            kept = tuple(x for x in kept if x != e)
            wander.append((e, wr, step_score.get((e.name, e.frame, e.slot))))
            rejected.append({"effect": e.name, "where": _label(e),
                             "reason": f"not constant within its runs: {_wander_text(wr)}; the offset wanders within "
                                       f"runs, which a per-run re-seat does not do (reported as unexplained)"})
    z_smoothing = {}
    for lag in [e for e in kept if e.name == "thermal_lag"]:
        z_lag, tau_sm = lag_or_smoothing(designs, kept, lag, folds3, blocks)
        z_smoothing[lag.setting.component] = (float(z_lag), float(tau_sm))
        if z_lag < Z_DISTINCT:
            kept = tuple(e for e in kept if e != lag)
            rejected.append({"effect": "thermal_lag", "where": _label(lag),
                             "reason": f"a zero-phase smoothing of the temperature log (tau {tau_sm:.3g} s, no delay) "
                                       f"fits as well out of sample (lag better by block z = {z_lag:.1f} < "
                                       f"{Z_DISTINCT}): the gain is smoothing of the log's noise, not heat flow"})
            notes.append(f"Smoothing the logged temperature (tau ~{tau_sm:.3g} s) improves the fit, but a delay does "
                         f"not: the temperature log is noisy; no thermal lag is reported.")
    if "thermal_lag" in {k[0] for k in cands} and not any(e.name == "thermal_lag" for e in kept):
        # a lag of a few samples is outside the grid (not heat flow); say so if it would help
        few = [Extension(C.Setting(C.ThermalLag(tau0=m * dt), nl=float(np.log(m * dt))), "whole") for m in (2, 4)]
        e_k, r_k, _, k_k = cv_residuals(designs, kept, [None], folds3)
        sm = score_group(designs, kept, ("thermal_lag", "whole", None), few, folds3, blocks, (e_k, r_k, k_k),
                         n_eff_fn(r_k))
        if sm.accepted:
            notes.append(f"Smoothing the logged temperature over a few samples (a first-order lag of "
                         f"{math.exp(sm.ext.setting.nl):.3g} s) improves the fit out of sample (block z = {sm.z:.1f}): "
                         f"the temperature log is noisy. That is not heat flow, so no thermal lag is reported.")

    # a located effect (a step's time) moved to its least-squares value given the final other
    # findings: forward selection placed it given the findings before it, and its interval is
    # computed given them all (the estimate must be the minimiser of the profile it is stated with)
    for i, e in enumerate(kept):
        if getattr(e.component, "located", None):
            kept = kept[:i] + (relocate(designs, kept[:i] + kept[i + 1:], e, folds3, ctx),) + kept[i + 1:]

    # ---- exact joint refit, plausibility of nonlinear values
    while True:
        model = JointModel(base, kept)
        X = designs.matrix(kept)
        beta = lstsq(X, designs.y)
        theta0 = np.concatenate([beta, [e.setting.nl for e in model.transforms]])
        say(f"joint Levenberg-Marquardt refit: {model.n_params} parameters")
        theta, cov, resid, converged = refit(model, theta0, inputs, y, w, run)
        sl = model.slices()
        bad = [(e, e.component.implausible(float(theta[sl[e][0]]), ctx)) for e in model.transforms]
        bad = [(e, why) for e, why in bad if why]
        if not bad:
            break
        for e, why in bad:
            rejected.append({"effect": e.name, "where": _label(e), "reason": why})
        kept = tuple(e for e in kept if e not in {b[0] for b in bad})
    if not converged:
        notes.append("The joint Levenberg-Marquardt refit did not report convergence; parameters are its last iterate.")

    # ---- findings
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    e_fin, r_fin, _, k_fin = cv_residuals(designs, kept, [None], folds3)
    n_eff = n_eff_fn(r_fin)
    pred = np.asarray(model.predict(jnp.asarray(theta), inputs))
    base_scores = _scores(y, X0 @ W0.T, e0, w, run)
    final_scores = _scores(y, pred, e_fin, w, run)
    variables = make_variables(data, time_ok)
    findings, extra_terms, effects = [], [], []
    step_of = {st["score"].key: st for st in steps}
    block_rows = int(np.median(np.bincount(blocks)[np.bincount(blocks) > 0]))
    sd_log = temperature_log_sd(data.temperature, run)
    for e in kept:
        others = tuple(x for x in kept if x != e)
        e_wo, r_wo, _, k_wo = cv_residuals(designs, others, [None], folds3)
        s = compare((e.name, e.frame, e.slot), e, e_fin, r_fin, k_fin, e_wo, r_wo, k_wo, blocks, n_eff, data.n, 1,
                    designs)
        if e.frame == "whole":
            m_wo = JointModel(base, others)
            th_wo = np.delete(theta, sl[e])
            eff = pred - np.asarray(m_wo.predict(jnp.asarray(th_wo), inputs))
        else:
            eff = pred - np.asarray(model.predict(jnp.asarray(theta), inputs, drop=e))
        rms = np.sqrt(np.mean(eff**2, axis=0))
        outputs = [AXES[a] for a in range(3) if rms[a] >= 0.2 * rms.max() and rms.max() > 0]
        params = {n: {"value": float(theta[i]), "se": float(se[i])} for n, i in zip(e.param_names, sl[e])}
        location = None
        if e.name == "thermal_lag":
            lt = params.pop("log_tau")
            tau = math.exp(lt["value"])
            # the residuals' share (Newey-West) and the temperature log's noise, which the lag and
            # each run's starting state take as input (errors in the variable; neither the
            # residual covariance nor the bootstrap, which holds the designs fixed, sees it)
            se_t = log_noise_se(model, theta, inputs, w, sl[e][0], sd_log)
            params["tau"] = {"value": tau, "se": tau * math.hypot(lt["se"], se_t), "unit": "s",
                             "se_residual": tau * lt["se"], "se_temperature_log": tau * se_t,
                             "temperature_log_sd": sd_log,
                             **_tau_interval(designs, others, e, lt["value"], lt["se"], block_rows, options.seed,
                                             se_t)}
            if int(getattr(e.component, "nodes", 1)) == 2:
                params["tau"]["nodes"] = 2
                params["tau"]["tau_housing"] = float(e.component.split * tau)
                params["tau"]["tau_die"] = float((1 - e.component.split) * tau)
        if getattr(e.component, "located", None):
            location = _locate_interval(designs, others, e, ctx, block_rows, options.seed)
        if e.name == "timing_offset":
            p = params["delta"]
            sys_se = DELTA_SYS_FRACTION * dt
            p.update({"se": math.hypot(p["se"], sys_se), "se_statistical": p["se"], "se_interpolation": sys_se,
                      "unit": "s"})
        st = step_of.get((e.name, e.frame, e.slot))
        sc = st["score"] if st else s
        e_before = (e_wo.reshape(3, -1).T / w)
        channel = AXES[e.slot] if e.frame == "sensor" else ("all" if e.frame == "whole" else None)
        findings.append({
            "effect": e.name, "frame": e.frame, "channel": channel,
            "axis": channel if e.frame != "output" else AXES[e.slot],
            "outputs": outputs, "description": e.component.describe(e.setting.cols), "setting": _label(e),
            "parameters": params,
            "not_identified": [p for p in not_ident if (p["effect"], p["frame"], p["slot"]) == (e.name, e.frame, e.slot)],
            "rmse_before": {a: float(np.sqrt(np.mean(e_before[:, k] ** 2))) for k, a in enumerate(AXES)},
            "rmse_after": dict(_axis_dict(final_scores)["rmse"]),
            **({"location": location} if location else {}),
            "evidence": {"oos_gain": s.gain, "decided_by": sc.decided_by, "z_decisive": float(sc.z_decisive),
                         "p_value": float(stats.norm.sf(sc.z_decisive)),
                         "z": float(sc.z), "p_value_block": float(stats.norm.sf(sc.z)),
                         "delta_bic_eff": float(sc.dbic),
                         "drop_one_z": s.z, "drop_one_gain": s.gain, "drop_one_decided_by": s.decided_by,
                         "drop_one_z_decisive": float(s.z_decisive), "cv": cv_desc,
                         **({"within_run": _within_json(within[e])} if e in within else {}),
                         **({"z_run": float(sc.z_run), "drop_one_z_run": s.z_run,
                             "run_mean_furthest_from_the_others": s.run}
                            if getattr(e.component, "localised", None) == "run" else {}),
                         **({"form": st["form"]} if st and st.get("form", {}).get("tried") else {}),
                         **({"z_lag_vs_zero_phase_smoothing": z_smoothing[e.setting.component][0],
                             "zero_phase_smoothing_tau": z_smoothing[e.setting.component][1]}
                            if e.setting.component in z_smoothing else {})},
            "explanation": _explanation(e.component, untested, within.get(e)),
            **_established(e.component, untested, within.get(e)),
            "indistinguishable_from": [{"effect": a.ext.name, "where": _label(a.ext), "oos_gain": a.gain}
                                       for a in (st["alternatives"] if st else [])],
            "config": _spec(e, theta[sl[e][0]] if e.frame == "whole" else None),
        })
        if _localised_ext(e) and s.run is not None:
            unstated = _unstated_run(designs, kept, e, s.run, e_fin, folds3, blocks, run)
            if unstated:
                findings[-1]["furthest_run_not_stated"] = unstated
        if getattr(e.component, "localised", None) == "run" or getattr(e.component, "located", None):
            findings[-1]["applies_to"] = ("the training sessions only: it describes the runs of this recording "
                                          "and cannot be applied to a new session")
        effects.append({"effect": eff, "before": e_before, "depends_on": _dominant(e, theta, sl, inputs)})
        spec = json.dumps(findings[-1]["config"], sort_keys=True, default=str)
        if spec not in {json.dumps(x, sort_keys=True, default=str) for x in extra_terms}:
            extra_terms.append(findings[-1]["config"])
    say(f"{len(findings)} finding(s); checking the residual for structure left")

    # ---- unexplained structure, in the sensor channels
    W = theta[: k_base].reshape(3, -1)
    t_arr = np.asarray(data.temperature)
    ch_base = _to_channels(base, W0, t_arr, base_resid)
    ch_final = _to_channels(base, W, t_arr, y - pred)
    located = locate(data, ch_base, time_available=time_ok, seed=options.seed, variables=variables)
    located_final = locate(data, ch_final, time_available=time_ok, seed=options.seed + 1, variables=variables)
    for l in located + located_final:
        l["channel"] = l["axis"]
    unexplained = structure(data, ch_final, located_final, dt=dt, time_available=time_ok)
    for e, wr, sc in wander:
        place = ch_final[:, e.slot] if e.frame == "sensor" else (y - pred)[:, e.slot]
        unexplained = _add_wander(unexplained, e, wr, sc, place, run, dt, time_ok)
    for u in unexplained:
        u.setdefault("frame", "sensor")
        if untested:
            u["not_searched"] = [{"effect": k, "reason": v} for k, v in untested.items()]
            by = {}
            for k, v in untested.items():
                by.setdefault(v, []).append(k)
            u["description"] += "; not searched: " + "; ".join(f"{', '.join(ks)} ({v})" for v, ks in by.items())
    baseline, final = _axis_dict(base_scores), _axis_dict(final_scores)
    baseline["cv"] = final["cv"] = cv_desc
    arrays = {"variables": variables, "effects": effects, "base_resid": ch_base, "final_resid": ch_final, "X0": X0}
    say(f"done: {len(findings)} finding(s), {len(unexplained)} unexplained")
    near = None
    if closest is not None:
        near = {"effect": closest.ext.name, "where": _label(closest.ext), "decided_by": closest.decided_by,
                "z_decisive": float(closest.z_decisive), "p_value": float(stats.norm.sf(closest.z_decisive)),
                "z": float(closest.z), "p_value_block": float(stats.norm.sf(closest.z)),
                **({"z_run": float(closest.z_run)} if _localised_ext(closest.ext) else {}),
                "oos_gain": float(closest.gain), "delta_bic_eff": float(closest.dbic),
                "not_accepted_because": closest.shortfall, "short_by": closest.short_by}
    return DiscoveryResult(findings, unexplained, located, baseline, final, extra_terms, notes, skipped, options,
                           data.source, _time.perf_counter() - t_start, rejected, arrays, near)
