"""Apply a field calibration (``bayesmag run`` with ``[measurement] kind = "scalar"`` or ``"constant"``) to a new
recording: the calibrated field in the gauge frame, its magnitude with an interval, the training-domain flags."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from bayesmag._src.core.data import AXES, DataError

__all__ = ["apply_field_calibration", "FIELD_OUTPUT_COLUMNS"]

#: The per-row columns of a field apply's CSV, after ``time,run`` (the domain columns follow).
FIELD_OUTPUT_COLUMNS = tuple(f"{a}_calibrated" for a in AXES) + (
    "magnitude", "magnitude_epistemic", "magnitude_noise", "magnitude_transfer", "magnitude_total", "magnitude_lower",
    "magnitude_upper")


def _shown(rows) -> str:
    return ", ".join(str(int(i) + 1) for i in rows[:10]) + (f" and {rows.size - 10} more" if rows.size > 10 else "")


def _reference_magnitude(data, data_path, scalar_column, field_unit) -> tuple:
    """``(magnitude (n,) uT with NaN where unusable, where it came from, notes)``: the vector reference's |B_ref|,
    else the calibration's scalar column (CSV or Parquet) in the readings' unit; ``(None, None, notes)`` when the
    recording has neither, the notes saying why nothing is scored."""
    if data.b_ref is not None and np.isfinite(data.b_ref).any():
        return np.linalg.norm(data.b_ref, axis=1), "|B_ref| of bx_ref, by_ref, bz_ref", []
    if not scalar_column:
        return None, None, []
    from bayesmag._src.core.data import FIELD_UNITS, load_column
    missing = (f"not scored: the recording has neither bx_ref, by_ref, bz_ref nor the calibration's scalar column "
               f"'{scalar_column}'.")
    try:
        if Path(data_path).suffix.lower() in (".parquet", ".pq"):
            import pandas as pd
            try:
                f = pd.read_parquet(data_path, columns=[scalar_column])[scalar_column].to_numpy(np.float64)
            except (KeyError, ValueError):
                return None, None, [missing]
        else:
            f = load_column(data_path, scalar_column, key="the calibration's scalar column", allow_nonfinite=True)
    except DataError as e:
        return None, None, [missing if "has no column" in str(e) else f"not scored: {e}"]
    if f.shape[0] != data.n:
        return None, None, [f"not scored: column '{scalar_column}' has {f.shape[0]} rows where the readings have "
                            f"{data.n}."]
    f = f * FIELD_UNITS[field_unit or "uT"]
    notes = []
    bad = np.flatnonzero(~(np.isfinite(f) & (f > 0)))
    if bad.size:
        notes.append(f"{bad.size} row(s) of column '{scalar_column}' hold no positive finite magnitude and are not "
                     f"scored: data row(s) {_shown(bad)}.")
        f[bad] = np.nan
    return f, f"the scalar column '{scalar_column}'", notes


def _unit_mismatch(ref, magnitude, origin) -> str | None:
    """A note when the reference magnitude and the calibrated one differ by a unit's factor (nT vs uT: 1000)."""
    ok = np.isfinite(ref) & np.isfinite(magnitude)
    if not ok.any():
        return None
    r = float(np.median(ref[ok]) / max(np.median(magnitude[ok]), 1e-300))
    if 0.05 <= r <= 20:
        return None
    unit = "nT (x1000)" if r > 20 else "mT or gauss"
    return (f"not scored: {origin} has median {np.median(ref[ok]):.4g} where the calibrated |B| has median "
            f"{np.median(magnitude[ok]):.4g} uT ({r:.3g}x): it looks like {unit}. Give the reference in the readings' "
            f"unit (--field-unit converts both).")


def _domain_warning(pred, ok, n_out: int, n: int, trained) -> str:
    """The out-of-domain warning; when only the predicted magnitude is outside training's (readings and temperature
    inside), it says what that usually is -- another site's field or a local disturbance -- rather than that the
    rows are extrapolated (every row of a flight 4 % away from a constant-F site was flagged so, while its magnitude
    intervals covered 95 %)."""
    reasons = np.asarray(pred["in_domain_reason"]).astype(str)[~np.asarray(pred["in_domain"]) & ok]
    if trained is not None and reasons.size and np.all(reasons == "magnitude"):
        mag = float(np.median(np.asarray(pred["magnitude"])[~np.asarray(pred["in_domain"]) & ok]))
        return (f"{n_out} of {n} rows are flagged magnitude (in_domain=false) only: their calibrated |B| (median "
                f"{mag:.4g} uT) lies outside the magnitudes training saw ({trained[0]:.4g} to {trained[1]:.4g} uT) "
                f"while their readings and temperatures lie inside, and beyond their own intervals. A whole recording "
                f"so is another site's field (IGRF/WMM differ by site: then the calibration holds), or, on a vehicle, "
                f"a hard-iron change larger than between the training sessions (a payload, a battery, a repair: then "
                f"recalibrate; the rows' errors are then about the same size in every direction of one turn); "
                f"scattered rows are a local disturbance (steel, currents), which the calibration cannot remove.")
    kinds = {k: int(np.sum([k in r.split(";") for r in reasons])) for k in ("field_range", "temperature", "magnitude")}
    return (f"{n_out} of {n} rows lie outside the field calibration's training domain (in_domain=false; "
            + ", ".join(f"{k} {v}" for k, v in kinds.items() if v) + "): their values are extrapolation and their "
            "intervals may be far too narrow.")


def apply_field_calibration(model_dir, data_path, out_path, *, level=None, temperature_unit="C", field_unit=None,
                            time_unit="s",
                            columns=None, force: bool = False, method: str = "auto", n_params: int = 100,
                            n_qmc: int = 256) -> dict:
    """Calibrate every row of ``data_path`` with the field calibration in ``model_dir``; write ``out_path``.

    Output columns (after ``time,run``): :data:`FIELD_OUTPUT_COLUMNS`, then ``in_domain_reason`` (bits: 1 a reading
    outside training's range, 2 temperature, 16 the predicted magnitude outside the training reference
    magnitudes), ``in_domain``, ``valid``. The calibrated field is in the calibration's gauge frame (docs/field.md);
    the interval is the magnitude's: Laplace predictive sd times the run's conformal scale, with the run's
    between-session sd (``magnitude_transfer``: the recording is a new session) in quadrature. With a reference in the
    recording (``bx_ref, by_ref, bz_ref``, or the run's scalar column) the summary has the magnitude RMSE and
    coverage (rows without a usable reference, or a reference in another unit, are not scored, and a note says so).
    ``method``, ``n_params`` and ``n_qmc`` (the vector apply's) are ignored, with a warning when set. The same
    path checks as the vector apply (:func:`~bayesmag._src.app.apply_io.check_apply_paths`).
    """
    from bayesmag._src.app.apply_io import (check_apply_options, check_apply_paths, check_units_against,
                                            refuse_training_recording, write_apply_csv, _check_magnitudes)
    from bayesmag._src.app.artifact import load_field
    from bayesmag._src.app.inputs import protected_recordings
    from bayesmag._src.core.frames import load_table

    t0 = time.perf_counter()
    check_apply_options(level, 2, 2)
    out_path = check_apply_paths(model_dir, data_path, out_path, force=force)
    cal = load_field(model_dir)
    doc_cfg = Path(model_dir) / "config.resolved.toml"
    if doc_cfg.exists():
        import tomllib
        try:
            data_cfg = tomllib.loads(doc_cfg.read_text()).get("data")
        except (tomllib.TOMLDecodeError, UnicodeDecodeError):
            data_cfg = None
        refuse_training_recording(out_path, protected_recordings(data_cfg, model_dir))
    data = load_table(data_path, columns=columns, temperature_unit=temperature_unit, field_unit=field_unit,
                      require_reference=False, time_unit=time_unit, mapping_hint="--columns (NAME=COL,...)")
    _check_magnitudes(data)
    warnings = check_units_against(data, cal.train_max_ut)
    pred = cal.predict(data.b_meas, data.temperature, level=level, field_unit="uT",   # checked above, with the
                       warn=False)           # command line's wording (declared: converted); warned below, as lines
    level = pred["level"]
    if not pred["valid"].any():
        raise DataError(f"No row of {data_path} could be calibrated ({data.n} rows, every one with a non-finite "
                        f"reading or temperature); nothing was written. Check the file's values and column mapping.")
    bad = np.flatnonzero(~pred["valid"])
    if bad.size:
        warnings.append(f"{bad.size} row(s) have a non-finite reading or temperature and were not calibrated "
                        f"(marked valid=false): data row(s) {_shown(bad)}.")
    if not data.time_given:
        warnings.append(f"{data_path} has no time column: the output's time column is nan (the rows are in file "
                        f"order).")
    ok = pred["valid"]
    n_out = int((~pred["in_domain"] & ok).sum())
    if n_out:
        warnings.append(_domain_warning(pred, ok, n_out, data.n, cal.ranges.get("magnitude") if cal.ranges else None))
    if cal.transfer_sd is None:
        warnings.append(cal.no_transfer_warning())
    meas = cal.fit.model.measurement
    relative = bool(getattr(meas, "scale_gauge", False))
    if relative:
        warnings.append("the calibration fitted the field magnitude itself (field = \"free\"): the calibrated field "
                        "and its magnitude are relative (trace(S) = 3), not in uT.")
    ignored = [flag for flag, v, default in (("--uq", method, "auto"), ("--n-params", n_params, 100),
                                             ("--n-qmc", n_qmc, 256)) if v != default]
    if ignored:
        warnings.append(f"{', '.join(ignored)} set the vector calibration's physics uncertainty and are ignored for a "
                        f"field calibration (its magnitude sd is the Laplace one, times the run's conformal scale).")
    notes = ["x/y/z_calibrated are in the calibration's gauge frame (x along the sensor's x axis, y in its x-y "
             "plane), not the vehicle's body frame: a magnitude fit cannot see that rotation (docs/field.md)."]
    metrics = None
    ref, origin, ref_notes = _reference_magnitude(data, data_path, cal.reference_column, field_unit)
    notes += ref_notes
    if ref is not None and relative:
        notes.append(f"not scored: the calibrated magnitudes are relative (field = \"free\"), {origin} is in uT.")
        ref = None
    if ref is not None:
        mismatch = _unit_mismatch(ref, pred["magnitude"], origin)
        if mismatch:
            notes.append(mismatch)
            ref = None
    if ref is not None:
        m = ok & np.isfinite(ref)
        if m.any():
            err = ref[m] - pred["magnitude"][m]
            inside = (ref[m] >= pred["magnitude_lower"][m]) & (ref[m] <= pred["magnitude_upper"][m])
            dom = pred["in_domain"][m]
            metrics = {
                "reference": origin, "n": int(m.sum()), "rmse": float(np.sqrt(np.mean(err ** 2))),
                "rmse_in_domain": float(np.sqrt(np.mean(err[dom] ** 2))) if dom.any() else None,
                "mean_error": float(np.mean(err)), "mean_error_is": "reference - calibrated",
                "coverage": float(inside.mean()),
                "coverage_in_domain": float(inside[dom].mean()) if dom.any() else None,
                "covered_or_flagged": float(np.mean(inside | ~dom))}
    cols = [(f"{a}_calibrated", pred["calibrated"][:, i]) for i, a in enumerate(AXES)]
    cols += [(c, pred[c]) for c in FIELD_OUTPUT_COLUMNS[3:]]
    write_apply_csv(out_path, data, cols, pred)
    reasons = pred["in_domain_reason"][ok]
    summary = {"n_rows": data.n, "n_valid": int(ok.sum()), "n_outside_domain": n_out,
               "outside_domain_by_reason": {k: int(np.sum(reasons == k)) for k in sorted(set(reasons)) if k},
               "kind": "field", "measurement": meas.name, "interval_scale": cal.interval_scale,
               "transfer_sd": cal.transfer_sd, "transfer_method": cal.transfer_method, "warnings": warnings, "notes": notes, "level": level,
               "seconds": time.perf_counter() - t0}
    if metrics is not None:
        summary["magnitude_metrics"] = metrics
    return summary
