"""The field-calibration job: ``[measurement] kind = "scalar" | "constant"`` (or a simulated field campaign).

Writes into the output folder, atomically (staging folder renamed at the end): ``field_params.json``,
``metrics.json``, ``predictions.csv`` (held-out magnitudes with intervals), ``report.md`` (the
certificate, with the field section), the exports listed in ``[measurement] exports``, figures, and with
``[nuts] enabled = true`` the NUTS cross-check (``nuts_summary.csv``, ``nuts_summary.md``, ``nuts.nc``).
"""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np
import scipy.stats

from bayesmag._src.app.config import Config, ConfigError, to_toml
from bayesmag._src.core.data import DataError, make_split
from bayesmag._src.core.field import INVARIANT_NAMES, gauge_text
from bayesmag._src.core.measurement import measurement_from_spec

__all__ = ["run_field_job", "field_report_lines", "load_field_data", "print_summary", "check_field_nuts_config"]


def check_field_nuts_config(cfg: Config) -> None:
    """``[nuts]`` of a field run: the sampler settings as for a vector run; the likelihood and priors are the
    field fit's own (Gaussian normalised residuals, :class:`~bayesmag.field.FieldPrior`), so those keys must
    stay at their defaults. Raises :class:`ConfigError` naming the key."""
    if not cfg.nuts.enabled:
        return
    import dataclasses

    from bayesmag._src.app.config import config_error
    from bayesmag._src.pipeline.nuts.sampler import check_settings
    n = cfg.nuts
    try:
        check_settings(chains=n.chains, warmup=n.warmup, draws=n.draws, target_accept=n.target_accept,
                       chain_method=n.chain_method)
    except ValueError as e:
        raise config_error(e, "nuts", [f.name for f in dataclasses.fields(n)]) from None
    if n.likelihood != "gaussian":
        raise ConfigError(f"Config key 'nuts.likelihood' = {n.likelihood!r}: a field calibration's NUTS cross-check "
                          "uses the field fit's Gaussian likelihood; remove the key (or set \"gaussian\").")
    if n.priors:
        raise ConfigError(f"Config key 'nuts.priors' = {dict(n.priors)!r}: a field calibration's NUTS cross-check "
                          "uses the field fit's own priors (docs/field.md); remove the key.")


def print_summary(m: dict) -> int:
    """The CLI's summary lines of a field run; returns the exit status 0."""
    import sys
    f = m["field"]
    s = f["scores"]
    print(f"  held-out magnitude RMSE {s['rmse']:.4g} uT, {s['level']:.0%} coverage {s['coverage']:.1%}, "
          f"CRPS {s['crps']:.4g} uT")
    if s.get("n_outside_domain"):
        print(f"  {s['n_outside_domain']} held-out rows outside the training domain; inside it coverage "
              f"{_pct(s.get('coverage_in_domain'))}, covered or flagged {s['covered_or_flagged']:.1%}")
    if f.get("heading"):
        h = f["heading"]
        print(f"  heading error RMSE {h['rmse_deg']:.3g} deg on {h['n']} level rows, coverage {h['coverage']:.1%}")
    if f.get("vector_comparison"):
        c = f["vector_comparison"]["counts"]
        print(f"  vs vector fit: {c['agree']} agree, {c['disagree']} disagree, {c['not identified']} not identified")
    if f.get("nuts"):
        nu = f["nuts"]
        print(f"  NUTS: max R-hat {nu['max_rhat']:.3f}, min ESS {nu['min_ess']:.0f}: {nu['verdict']}")
    for w in m.get("warnings", []):
        print(f"  note: {w}", file=sys.stderr)
    return 0


def _pct(v) -> str:
    """A fraction as a percentage; ``None`` (no row to measure it on) as "n/a"."""
    return "n/a" if v is None else f"{v:.1%}"


def load_field_data(cfg: Config):
    """``(data, f_ref, campaign)``: a simulated field campaign, or the recording the config names, validated as the
    vector job validates its recording (:func:`validate_field_data`); a scalar column is converted from
    ``[data] field_unit`` to uT exactly as the readings are."""
    if cfg.data.source == "field_simulated":
        from bayesmag._src.core.field_sim import field_campaign_from_config
        try:
            c = field_campaign_from_config(dict(cfg.measurement.simulate))
        except (TypeError, ValueError) as e:
            raise ConfigError(f"[measurement.simulate]: {e}") from None
        validate_field_data(c.data, c.f_ref)
        return c.data, c.f_ref, c
    d, mc = cfg.data, cfg.measurement
    if d.path is None:
        from bayesmag._src.app.inputs import load_data
        data = load_data(cfg)
        validate_field_data(data, None)
        return data, None, None
    from bayesmag._src.core.data import FIELD_UNITS, load_column, load_csv
    # a field recording needs no reference vector: a scalar column, or one constant field, is the reference
    data = load_csv(d.path, columns=d.columns or None, temperature_unit=d.temperature_unit, field_unit=d.field_unit,
                    require_reference=False, time_unit=d.time_unit)
    f_ref = None
    if mc.scalar_column:
        f_ref = load_column(d.path, mc.scalar_column, key="[measurement] scalar_column", positive=True)
        f_ref = f_ref * FIELD_UNITS[d.field_unit or "uT"]      # the readings' unit: converted as load_csv does
    validate_field_data(data, f_ref, scalar_column=mc.scalar_column)
    return data, f_ref, None


def validate_field_data(data, f_ref=None, *, scalar_column: str = "") -> None:
    """The vector job's checks of a recording (:func:`~bayesmag._src.core.data.validate`: finite, plausible values,
    the field in uT unless ``[data] field_unit`` declared it, Celsius, no repeated timestamp within a run), the
    scalar reference column's unit checked like the readings, and rows in time order within each run: the
    time-block split and the folds of the conformal scale take contiguous rows as contiguous time (unsorted rows
    made them a random split). Raises :class:`DataError` (one line, naming the rows and the fix)."""
    from bayesmag._src.core.data import DataError, check_time_order, validate
    name = f"scalar reference column '{scalar_column or 'f_ref'}'"
    extra = () if f_ref is None else ((name, np.asarray(f_ref, np.float64).reshape(-1, 1)),)
    ok = np.isfinite(data.b_meas).all(axis=1)
    mag = np.linalg.norm(data.b_meas[ok], axis=1) if ok.any() else np.zeros(0)
    if f_ref is not None and mag.size:      # the column against the readings: one of them in another unit
        f = np.asarray(f_ref, np.float64)
        f = f[np.isfinite(f)]
        ratio = float(np.median(f) / max(np.median(mag), 1e-300)) if f.size else 1.0
        if not 1 / 50 <= ratio <= 50:
            big = "the column" if ratio > 1 else "the readings"
            raise DataError(f"The {name} in {data.source} is {ratio:.3g}x the readings' |B| (medians {np.median(f):.4g} "
                            f"and {np.median(mag):.4g} uT{' after the declared field_unit' if data.field_unit else ''}): "
                            f"{big} look{'s' if big == 'the column' else ''} like another unit (nT is x1000). Convert "
                            f"that column (or the readings) to uT; [data] field_unit converts the readings and the "
                            f"column alike, so it cannot fix one of them.")
    if data.field_unit is not None and mag.size and float(np.median(mag)) < 1.0:
        raise DataError(f"After the declared [data] field_unit = {data.field_unit!r} the readings' median |B| is "
                        f"{np.median(mag):.3g} uT; a field calibration (the Earth's field is 25-65 uT, or a scalar "
                        f"reference) cannot work at that field, so the readings are probably in uT already. Remove "
                        f"field_unit (it converts the readings and the scalar column alike), or convert the file.")
    validate(data, n_params=0, need_reference=False, need_temperature_variation=False, origin=data.source,
             extra_fields=extra)
    check_time_order(data, ["the time-block split and the conformal folds"], origin=data.source)


def field_n_params(measurement, temperature_terms, temperature) -> int:
    """The number of parameters :func:`~bayesmag.field.fit_field` will fit (``temperature_terms`` resolved as it
    resolves ``"auto"``: on when ``temperature`` spans >= 1 C)."""
    from bayesmag._src.core.field import FieldModel
    tt = bool(np.ptp(temperature) >= 1.0) if temperature_terms == "auto" else bool(temperature_terms)
    return FieldModel(measurement, t0=0.0, temperature=tt).n_params


def check_field_rows(cfg: Config, meas, data, train, split, dropped: int, plan) -> None:
    """Before any fitting: more rows than parameters in the recording (:class:`DataError`) and in the training
    rows the split leaves (:class:`ConfigError`, as the vector job), and with ``plan`` (the conformal scale's
    ``(fraction, folds)``) at least :data:`CONFORMAL_MIN_ROWS` held-out fold rows, each refit keeping more rows than
    parameters (:class:`DataError` naming ``measurement.interval_calibration = "none"``)."""
    mc = cfg.measurement
    n_params = field_n_params(meas, mc.temperature_terms, train.temperature if train.n else data.temperature)
    after = f" (after dropping {dropped} below [measurement] min_magnitude = {mc.min_magnitude} uT)" if dropped else ""
    if data.n * meas.per_row <= n_params:
        raise DataError(f"The recording {data.source} has {data.n} rows{after} but the field model has {n_params} "
                        f"parameters: a fit needs more rows than parameters (many more for a useful calibration). "
                        f"Record more rows.")
    if train.n * meas.per_row <= n_params:
        raise ConfigError(f"[split] leaves {train.n} training rows of {data.n} ({split.description}), but the field "
                          f"model has {n_params} parameters: a fit needs more rows than parameters. Lower "
                          f"split.test_fraction or give more data.")
    if plan is None:
        return
    from bayesmag._src.pipeline.conformal import conformal_folds
    fold = conformal_folds(train.run, fraction=plan[0], folds=plan[1], seed=cfg.split.seed)
    sizes = [int(np.sum(fold == k)) for k in range(plan[1])]
    sizes = [s for s in sizes if 0 < s < train.n]           # the folds magnitude_interval_scale refits
    n_held = sum(sizes)
    if n_held < CONFORMAL_MIN_ROWS or (train.n - max(sizes, default=0)) * meas.per_row <= n_params:
        raise DataError(f"The conformal interval scale needs at least {CONFORMAL_MIN_ROWS} held-out fold rows, each "
                        f"fold refitted on more rows than the {n_params} parameters; the {train.n} training rows "
                        f"give {n_held} in {len(sizes)} folds. Set measurement.interval_calibration = \"none\" "
                        f"(the Laplace intervals as they are) or record more rows.")


#: the fewest held-out rows the split-conformal quantile is taken from (pipeline/conformal.py)
CONFORMAL_MIN_ROWS = 20


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def field_report_lines(m: dict, params: dict) -> list[str]:
    """The field calibration section of the certificate (markdown lines)."""
    f = m["field"]
    L = ["## Field calibration", "",
         f"- Measurement model: **{params['measurement']['name']}**"
         + (f" (field {params['measurement'].get('field')} uT)" if params["measurement"]["name"] == "constant" else ""),
         f"- Gauge: {params['gauge']}.",
         f"- T0 = {params['t0']:.4g} C; temperature terms: {params['temperature_terms']}; covariance: "
         f"{params['covariance']} (residual lag-1 autocorrelation {params['rho1']:.3f}, inflation "
         f"{params['inflation']:.3g})." + (f" **The white covariance takes the residuals as independent: with this "
                                           f"autocorrelation every parameter's and invariant's sd below is about "
                                           f"{_ar1_factor(params['rho1']):.2g}x too small** (`[measurement] covariance = "
                                           f"\"ar1\"` states them)." if _white_understates(params) else ""),
         f"- Rows: {f['n_train']} training, {f['n_test']} held out ({m['split']['description']})"
         + (f"; {f['dropped_low_magnitude']} rows dropped below the minimum magnitude {f['min_magnitude']} uT"
            if f["dropped_low_magnitude"] else "") + ".",
         f"- Residual sd (reading units): {np.sqrt(params['s2']):.4g} uT"
         + (f" (the white reading noise, from row-to-row differences: {f['transfer']['white_noise_sd']:.3g} uT; the "
            f"rest is slow misfit or the sessions' scatter)" if (f.get("transfer") or {}).get("white_noise_sd")
            and np.sqrt(params["s2"]) > 2 * f["transfer"]["white_noise_sd"] else "") + ".", "",
         "### Held-out magnitude", "",
         "| RMSE (uT) | coverage | mean width (uT) | NLL | CRPS (uT) |", "|---|---|---|---|---|",
         f"| {_fmt(f['scores']['rmse'])} | {f['scores']['coverage']:.3f} (nominal {f['scores']['level']:g}) | "
         f"{_fmt(f['scores']['mean_width'])} | {_fmt(f['scores']['nll'])} | {_fmt(f['scores']['crps'])} |", ""]
    sc = f["scores"]
    if sc.get("n_outside_domain"):
        dm = f.get("domain") or {}
        L += [f"{sc['n_outside_domain']} held-out rows lie outside the training domain ("
              + ", ".join(f"{k}: {v}" for k, v in dm.get("by_reason", {}).items())
              + f"; in_domain = false in predictions.csv). Inside it ({sc['n_in_domain']} rows) the intervals cover "
              + (f"{sc['coverage_in_domain']:.3f}" if sc.get("coverage_in_domain") is not None else
                 "n/a (no held-out row lies inside it)")
              + f"; covered or flagged: {sc['covered_or_flagged']:.3f}.", ""]
    else:
        L += ["Every held-out row lies inside the training domain (measured inputs, temperature, magnitude).", ""]
    ic = f["scores"].get("interval_calibration")
    if ic:
        L += [f"Intervals: the Laplace predictive sd times the conformal scale c = {ic['scale']:.3g}, from {ic['folds']} "
              f"time-block folds of the training rows ({ic['n']} rows, each predicted by a fit that did not see it; "
              f"unscaled they covered {ic['fold_coverage_before']:.3f}). Unscaled on the held-out rows: coverage "
              f"{ic['laplace_coverage']:.3f}, CRPS {_fmt(ic['laplace_crps'])} uT.", ""]
    else:
        L += ["Intervals: the Laplace predictive as it is (measurement.interval_calibration = \"none\").", ""]
    L += _transfer_lines(f["transfer"]) if f.get("transfer") else []
    L += ["### Gauge-free quantities (at T0)", "",
          "Q = S^T S (scale and non-orthogonality), dQ/dT, d = S^-1 O (offset in the sensor frame, uT), dd/dT (uT/C).",
          "", "| quantity | value | sd | prior sd | identified |", "|---|---|---|---|---|"]
    for name in INVARIANT_NAMES:
        r = params["invariants"][name]
        L.append(f"| {name} | {_fmt(r['value'])} | {_fmt(r['sd'])} | {_fmt(r['prior_sd'])} | "
                 + ("yes" if r["identified"] else f"no: {r['why_not']}") + " |")
    L += ["", "### Parameters (gauge frame)", "", "| parameter | value | sd |", "|---|---|---|"]
    L += [f"| {n} | {_fmt(v)} | {_fmt(s)} |" for n, v, s in zip(params["param_names"], params["theta"], params["std"])]
    cov = params["direction_coverage"]
    L += ["", "### Direction coverage", "",
          "Eigenvalues of the covariance of the field direction B/|B| (a full tumble: about 0.33 each; below 0.01 = "
          "not visited): " + ", ".join(f"{w:.3g}" for w in cov["eigenvalues"]) + ".",
          f"Temperature bands (5 C) with spread directions: {cov['bands_spread']} of {len(cov['bands'])}.", ""]
    L += ["### Identifiability notes", ""] + ([f"- {n}" for n in params["notes"]] or ["- none: every quantity identified"])
    hd = f.get("heading")
    L += ["", "### Heading check", ""]
    if hd:
        L += [f"- {hd['n']} level held-out rows: heading error RMSE {hd['rmse_deg']:.3f} deg (max {hd['max_abs_deg']:.3f}); "
              f"{hd['level']:g} intervals cover {hd['coverage']:.3f} (parameters only: {hd['coverage_params_only']:.3f}); "
              f"mean sd {hd['mean_sd_deg']:.3f} deg (parameters {hd['mean_sd_params_deg']:.3f}, noise "
              f"{hd['mean_sd_noise_deg']:.3f}).",
              f"- Conditional on {hd['conditional_on']}: a magnitude calibration cannot see the rotation between its "
              "gauge frame and the body frame; it needs known attitudes, gravity or a heading reference."]
    else:
        L += ["- not checked: the recording has no level segments with known heading (simulated attitudes or a "
              "heading reference)."]
    vc = f.get("vector_comparison")
    if vc:
        c = vc["counts"]
        L += ["", "### Against a vector fit of the same rows", "",
              f"The vector reference was withheld from the field fit; the vector model fitted to the same training rows "
              f"(T0 = {vc['t0']:.4g} C, covariance {vc['vector_covariance']}) gives: {c['agree']} agree (|z| <= 2), "
              f"{c['disagree']} disagree, {c['not identified']} not identified by these recordings.", "",
              "| quantity | field fit | sd | vector fit | sd | z | status |", "|---|---|---|---|---|---|---|"]
        L += [f"| {r['name']} | {_fmt(r['magnitude_fit'])} | {_fmt(r['magnitude_sd'])} | {_fmt(r['vector_fit'])} | "
              f"{_fmt(r['vector_sd'])} | {r['z']:+.2f} | {r['status']} |" for r in vc["rows"]]
    nuts = f.get("nuts")
    if nuts:
        L += ["", "### NUTS cross-check", "",
              f"{nuts['chains']} chains x {nuts['draws']} draws (warm-up {nuts['warmup']}); max R-hat "
              f"{nuts['max_rhat']:.3f}, min ESS {nuts['min_ess']:.0f}, {nuts['divergences']} divergences; largest "
              f"|Laplace - NUTS| mean / NUTS sd: {nuts['max_mean_shift_sd']:.2f}; sd ratio Laplace/NUTS in "
              f"[{nuts['sd_ratio_min']:.2f}, {nuts['sd_ratio_max']:.2f}] (parameters).",
              f"- {nuts['verdict']} (parameters and identified invariants; nuts_summary.md, nuts_summary.csv, nuts.nc)."]
    if f.get("exports"):
        L += ["", "### Exports", "", "Written: " + ", ".join(f["exports"])
              + " (coefficients in the symmetric frame: the gauge frame rotated by R^T, R the rotation of the polar "
              "decomposition S = R P at T0, in calibration.export.json's field_frame; |B| unchanged; docs/field.md)."]
    return L


def _write_predictions(path: Path, test, rows, y, pred, level, domain=None):
    k = scipy.stats.norm.ppf(0.5 + level / 2)
    lo, hi = pred["mean"] - k * pred["total"], pred["mean"] + k * pred["total"]
    inside = np.ones(test.n, bool) if domain is None else domain["in_domain"]
    reason = np.full(test.n, "", object) if domain is None else domain["reason"]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["row", "time", "run", "temperature", "reference_magnitude", "predicted_magnitude", "epistemic",
                    "noise", "transfer", "total", "lower", "upper", "covered", "in_domain", "in_domain_reason"])
        for i in range(test.n):
            w.writerow([int(rows[i]), f"{test.time[i]:.6f}", int(test.run[i]), f"{test.temperature[i]:.6g}",
                        f"{y[i]:.8g}", f"{pred['mean'][i]:.8g}", f"{pred['epistemic'][i]:.6g}", f"{pred['noise'][i]:.6g}",
                        f"{pred['transfer'][i]:.6g}", f"{pred['total'][i]:.6g}", f"{lo[i]:.8g}", f"{hi[i]:.8g}", bool(lo[i] <= y[i] <= hi[i]),
                        bool(inside[i]), reason[i]])


def _transfer_block(tr, pred, test, train, level) -> dict:
    """metrics.json's ``field.transfer``: the between-session sd and how it was found, the held-out rows of new
    sessions, and the expanded uncertainty of |B| (k = the Gaussian's at ``level``) at the median held-out row,
    within a training session and for a new one."""
    k = float(scipy.stats.norm.ppf(0.5 + level / 2))
    within = np.sqrt(np.maximum(pred["total"] ** 2 - pred["transfer"] ** 2, 0.0))
    block = {"sd": None, "method": "off", "n_runs": 0, "per_run": {}, "warning": None} if tr is None else dict(tr)
    block.update(n_train_runs=int(np.unique(train.run).size),
                 n_test_new_session=int(np.sum(~np.isin(test.run, np.unique(train.run)))), k=k,
                 U_same_session=float(k * np.median(within)),
                 U_new_session=None if tr is None or tr["sd"] is None else
                 float(k * np.median(np.sqrt(within**2 + tr["sd"] ** 2))))
    return block


def _transfer_lines(tr: dict) -> list[str]:
    """The certificate's new-session paragraph of a field run."""
    L = ["### A new session", ""]
    if tr["method"] == "off":
        return L + ["No between-session (transfer) term ([uq] transfer = \"off\"): the intervals are for the session the "
                    f"calibration was fitted in (U = {tr['U_same_session']:.2g} uT at the median held-out row, k = "
                    f"{tr['k']:.3g}); no U for a new session is stated.", ""]
    if tr["method"] == "leave_one_run_out":
        L += [f"Between-session sd of |B|: {tr['sd']:.2g} uT, from leave-one-run-out over {tr['n_runs']} of the "
              f"{tr['n_train_runs']} training runs (every run a session; each left-out run's rows inside the other runs' "
              "domain, every run weighted equally, the 95 % quantile bounded at 80 % confidence over the runs; "
              "docs/field.md).", "",
              "| left-out run | rows | in the others' domain | RMSE of the magnitude (uT) | mean error (uT) |",
              "|---|---|---|---|---|"]
        L += [f"| {r} | {v['n_rows']} | {v['n_in_domain']} | "
              + ("-" if v["rmse"] is None else f"{v['rmse']:.3g}") + " | "
              + ("-" if v["mean_error"] is None else f"{v['mean_error']:+.3g}") + " |" for r, v in tr["per_run"].items()]
        L.append("")
        if tr.get("warning"):
            L += [f"> **Warning.** {tr['warning']}", ""]
    else:                       # not estimated: no U for a new session can be stated
        return L + [tr["warning"], "", f"U same session {tr['U_same_session']:.2g} uT at the median held-out row (k = "
                    f"{tr['k']:.3g}; rows of the training sessions). **No U for a new session is stated**: a later "
                    "flight or campaign can be off by more.", ""]
    L += [f"Expanded uncertainty of |B| at the median held-out row (k = {tr['k']:.3g}): U same session "
          f"{tr['U_same_session']:.2g} uT (rows of the training sessions), U new session {tr['U_new_session']:.2g} uT "
          "(any later flight or campaign: what `bayesmag apply` gives, column magnitude_transfer)."
          + (f" {tr['n_test_new_session']} held-out rows are of runs the fit did not see and carry it." if
             tr["n_test_new_session"] else ""), ""]
    return L


def _ar1_factor(rho: float) -> float:
    """How much an AR(1) residual autocorrelation ``rho`` widens a white covariance's sds: sqrt((1+rho)/(1-rho))."""
    r = min(max(float(rho), 0.0), 0.99)
    return float(np.sqrt((1 + r) / (1 - r)))


def _white_understates(params: dict) -> bool:
    """A white covariance whose residuals are autocorrelated enough to understate its sds by 1.5x or more."""
    return params.get("covariance") == "white" and _ar1_factor(params.get("rho1", 0.0)) >= 1.5


def _transfer_warning(tr) -> list[str]:
    """The run's between-session warning: few runs (``magnitude_transfer``'s), or none estimated (``"off"``)."""
    if tr is None:
        return ["[uq] transfer = \"off\": the field calibration holds no between-session (transfer) term, so its "
                "magnitude intervals for a new session (another flight or campaign of the sensor) cover only the "
                "error within a session and can be far too narrow. Use transfer = \"loro\" with 3 or more recorded "
                "sessions."]
    return [tr["warning"]] if tr.get("warning") else []


def _domain_warning(dom, n) -> list[str]:
    if not dom or not dom["n_outside"]:
        return []
    why = ", ".join(f"{k} ({v} rows)" for k, v in dom["by_reason"].items())
    return [f"{dom['n_outside']} of {n} held-out rows lie outside the training domain ({why}; in_domain=false in "
            "predictions.csv): their predictions are extrapolation and their intervals may be too narrow."]


def _not_converged_message(meas, train, f_ref_train, mc) -> str:
    """The job's one line when the field fit did not converge: the declared field (or the scalar column's level)
    against the field the readings support (:func:`~bayesmag._src.core.field.supported_field`) first, as a field off
    by a factor is the likely cause (F = 5 uT for a 49 uT site did not converge), then outliers."""
    from bayesmag._src.core.field import supported_field
    from bayesmag._src.core.measurement import Constant
    f_sup = supported_field(train.b_meas)
    if isinstance(meas, Constant) and meas.field is not None:
        declared = f"the declared field ([measurement] field = {meas.field:g} uT"
    elif isinstance(meas, Constant):
        declared = None
    else:
        ref = (f_ref_train if f_ref_train is not None else
               np.linalg.norm(train.b_ref, axis=1) if train.b_ref is not None else None)
        col = f"'{mc.scalar_column}'" if mc.scalar_column else "(|B_ref|)"
        declared = (None if ref is None else
                    f"the scalar reference {col} (median {float(np.median(ref)):.4g} uT")
    if declared is None:
        return "The field fit did not converge; check the data for outliers."
    return (f"The field fit did not converge. Likely cause: {declared}, while the readings support about "
            f"{f_sup:.3g} uT after their hard-iron offset): give the site's total intensity F in uT (not H; IGRF/WMM), "
            f"or a reference column in uT. Else check the data for outliers.")


def run_field_job(cfg: Config, out: str | Path, *, progress: bool = False) -> dict:
    """Run the field calibration the config describes and write its outputs into ``out``."""
    from bayesmag._src.app.field_export import field_export_texts, field_uncertainty_doc
    from bayesmag._src.app.outdir import staging_dir
    from bayesmag._src.pipeline.field_stage import conformal_plan, run_field_stage

    mc = cfg.measurement
    timings: dict[str, float] = {}
    t_all = t = time.perf_counter()
    try:
        meas = measurement_from_spec(mc.kind, mc.field, mc.reference_sd)
    except ValueError as e:
        raise ConfigError(f"[measurement]: {e}") from None
    check_field_nuts_config(cfg)
    data, f_ref, campaign = load_field_data(cfg)
    if data.b_ref is None and f_ref is None and mc.kind != "constant":
        raise DataError(f"The {mc.kind} measurement model needs a reference: a magnitude column named by "
                        "[measurement] scalar_column, or the columns bx_ref, by_ref, bz_ref; the recording has "
                        "neither. Name the column, or use [measurement] kind = \"constant\" with the site's field.")
    mag = f_ref if f_ref is not None else (np.linalg.norm(data.b_ref, axis=1) if data.b_ref is not None else None)
    keep = np.ones(data.n, bool) if mag is None else mag >= mc.min_magnitude
    dropped = int((~keep).sum())
    idx_all = np.flatnonzero(keep)
    data = data.subset(idx_all)
    f_ref = None if f_ref is None else f_ref[idx_all]
    try:
        split = make_split(data, kind=cfg.split.kind, test_fraction=cfg.split.test_fraction, seed=cfg.split.seed,
                           test_runs=cfg.split.test_runs, n_blocks=cfg.split.n_blocks)
    except ValueError as e:
        raise ConfigError(f"[split]: {e}") from None
    train, test = data.subset(split.train), data.subset(split.test)
    plan = (None if mc.interval_calibration == "none" else
            conformal_plan(cfg.split.test_fraction, cfg.split.n_blocks, cfg.split.kind, mc.conformal_folds))
    check_field_rows(cfg, meas, data, train, split, dropped, plan)
    timings["load"] = time.perf_counter() - t
    heading = None
    if campaign is not None and mc.heading_check:
        tr = campaign.truth
        full = idx_all[split.test]
        lv = tr.level[full]
        heading = None if not lv.any() else {"rows": lv, "true": tr.heading[full][lv], "alignment": tr.alignment(test.temperature[lv])}
    fs = run_field_stage(train, test, meas, f_ref_train=None if f_ref is None else f_ref[split.train],
                         f_ref_test=None if f_ref is None else f_ref[split.test], t0=cfg.physics.t0,
                         temperature_terms=mc.temperature_terms, covariance=mc.covariance, level=cfg.uq.level,
                         heading=heading, compare_vector=mc.compare_vector, seed=cfg.split.seed,
                         conformal=plan, transfer=cfg.uq.transfer)
    timings.update(fs.timings)
    if not fs.fit.converged:
        from bayesmag._src.pipeline.stages import CalibrationError as JobError
        raise JobError(_not_converged_message(meas, fs.train, None if f_ref is None else f_ref[split.train], mc))
    nuts = None
    if cfg.nuts.enabled:
        from bayesmag._src.core.field import field_target
        from bayesmag._src.pipeline.field_nuts import field_nuts
        t = time.perf_counter()
        n = cfg.nuts
        y_tr = field_target(meas, b_ref=train.b_ref, f_ref=None if f_ref is None else f_ref[split.train], n=train.n)
        nuts = field_nuts(fs.fit, train.b_meas, train.temperature, y_tr, chains=n.chains, warmup=n.warmup,
                          draws=n.draws, seed=n.seed, target_accept=n.target_accept, chain_method=n.chain_method)
        timings["nuts"] = time.perf_counter() - t
    from bayesmag._src.core.field_calibration import FieldCalibration
    tr = fs.transfer
    estimated = tr is not None and tr["sd"] is not None
    saved = FieldCalibration(fs.fit, float(fs.prediction.get("scale", 1.0)), cfg.uq.level,
                             {k: tuple(v) for k, v in fs.domain["training_ranges"].items()}, mc.scalar_column or None,
                             tr["sd"] if estimated else None, tr["method"] if estimated else None)
    params = saved.to_json()      # what `bayesmag apply` reads back (FieldCalibration.from_json)
    field_m = {"n_train": int(train.n), "n_test": int(test.n), "dropped_low_magnitude": dropped,
               "min_magnitude": mc.min_magnitude, "scores": fs.scores,
               "heading": None if fs.heading is None else {k: v for k, v in fs.heading.items()
                                                           if not isinstance(v, np.ndarray)},
               "vector_comparison": fs.vector, "exports": list(mc.exports),
               "transfer": _transfer_block(tr, fs.prediction, test, train, cfg.uq.level),
               "domain": None if fs.domain is None else {k: v for k, v in fs.domain.items()
                                                         if not isinstance(v, np.ndarray)}}
    if campaign is not None:
        inv, truth = fs.fit.invariants(), campaign.truth.invariants(fs.fit.model.t0)
        z = (inv["value"] - truth) / np.maximum(inv["sd"], 1e-300)
        k = scipy.stats.norm.ppf(0.5 + cfg.uq.level / 2)
        ok = inv["identified"]
        field_m["truth_check"] = {"identified": int(ok.sum()),
                                  "coverage_identified": float(np.mean(np.abs(z[ok]) <= k)) if ok.any() else None,
                                  "abs_z": {n: float(abs(v)) for n, v in zip(INVARIANT_NAMES, z)}}
    if nuts is not None:
        field_m["nuts"] = {k: v for k, v in nuts.items() if k not in ("samples", "rows")}
    from bayesmag._src.app.report import certificate_record
    white = ([f"The field fit's covariance is white, but its residuals' lag-1 autocorrelation is {params['rho1']:.2f}: "
              f"every parameter's and invariant's sd in the certificate is about {_ar1_factor(params['rho1']):.2g}x too "
              f"small. Set [measurement] covariance = \"ar1\" to state them (the magnitude intervals are not affected: "
              f"the conformal scale and the transfer term hold the rest)."] if _white_understates(params) else [])
    metrics = {"field": field_m, "split": split.as_dict(),
               "data": {"source": data.source, "n_rows": int(data.n), "runs": [int(r) for r in data.runs],
                        "train_runs": [int(r) for r in np.unique(train.run)]},
               "certificate": certificate_record(cfg, data),
               "warnings": [n for n in fs.fit.notes] + white + ([] if nuts is None else list(nuts["warnings"]))
               + _domain_warning(fs.domain, test.n) + _transfer_warning(tr)}
    with staging_dir(Path(out), kind="run") as tmp:
        t = time.perf_counter()
        (tmp / "field_params.json").write_text(json.dumps(params, indent=2))
        (tmp / "config.resolved.toml").write_text(to_toml(cfg.to_dict()))
        _write_predictions(tmp / "predictions.csv", test, split.test, fs.target_test, fs.prediction, cfg.uq.level,
                           fs.domain)
        u_doc = field_uncertainty_doc(field_m["transfer"], cfg.uq.level, relative=meas.scale_gauge)
        for fmt, text in field_export_texts(fs.fit, train, mc.exports, held_out=test, uncertainty=u_doc).items():
            from bayesmag._src.app.formats import FORMATS
            (tmp / f"calibration{FORMATS[fmt]}").write_text(text)
        if nuts is not None:
            from bayesmag._src.pipeline.field_nuts import write_field_nuts_outputs
            write_field_nuts_outputs(nuts, tmp, fs.fit.param_names)
        figures = []
        if cfg.output.figures:
            from bayesmag._src.app.field_plots import field_figures
            figures = field_figures(tmp, fs)
        timings["write"] = time.perf_counter() - t
        timings["total"] = time.perf_counter() - t_all
        metrics["timings"] = {k: round(v, 4) for k, v in timings.items()}
        (tmp / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
        rec = metrics["certificate"]
        unset = lambda v, key: v or f"not stated (set `[certificate] {key} = \"...\"`)"  # noqa: E731
        lines = [f"# Calibration certificate: {cfg.name}", "", "| item | value |", "|---|---|",
                 f"| calibration ID | {rec['calibration_id']} |", f"| date (UTC) | {rec['date_utc']} |",
                 f"| bayesmag version | {rec['bayesmag_version']} |", f"| device under test | {unset(rec['dut'], 'dut')} |",
                 f"| reference | {unset(rec['reference'], 'reference')} |"]
        lines += [f"| operator | {rec['operator']} |"] if rec.get("operator") else []
        lines += [f"| data | {rec['data']} |", f"| data sha256 | `{rec['data_sha256']}` |",
                  f"| calibration file | field_params.json (content sha256 `{params['content_sha256']}`) |", "",
                  f"Data: {data.source} ({data.n} rows). Gauge: {gauge_text(meas)}.", ""]
        lines += [f"> **Warning.** {w}" for w in metrics["warnings"]] + ([""] if metrics["warnings"] else [])
        lines += field_report_lines(metrics, params)
        lines += [""] + [f"![{Path(p).stem}]({p})" for p in figures]
        from bayesmag._src.app.report import render_html
        text = "\n".join(lines) + "\n"
        (tmp / "report.md").write_text(text)
        (tmp / "report.html").write_text(render_html(text, tmp))      # the same content, figures embedded
    return {"config": cfg, "stage": fs, "metrics": metrics, "params": params, "campaign": campaign}
