"""Apply a saved calibration to a new recording: checks, chunked prediction, CSV out, optional metrics."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from bayesmag._src.app.apply_io import (APPLY_HEADER_END, apply_about, check_apply_options,  # noqa: F401
                                        check_apply_paths, check_units_against, declared_conversions,
                                        field_intervals, interval_family, is_apply_output,
                                        missing_temperature_error, reference_unit_note, refuse_training_recording,
                                        sidecar_path, training_data_sha256, write_apply_csv, write_apply_sidecar,
                                        _check_magnitudes)
from bayesmag._src.app.artifact import load, new_session_notes, out_of_domain_note  # noqa: F401 (re-exported)
from bayesmag._src.core.data import AXES, DataError

__all__ = ["apply_calibration", "check_units", "check_apply_paths"]

OUTPUT_COLUMNS = ("calibrated", "aleatoric_physics", "epistemic_physics", "residual_physics", "aleatoric_nn",
                  "epistemic_nn", "transfer", "total", "lower", "upper")


def check_units(cal, data, *, small_ok: bool = False) -> list[str]:
    """Errors for units that cannot be right; warnings for suspicious ones (vs the training domain).

    The check is :func:`~bayesmag._src.core.data.check_units`, shared with ``run``, ``discover`` and the library;
    measured and reference columns are both checked against the training range (``small_ok``: not the mT / gauss
    test, for a part of a recording whose whole the caller checks).
    """
    return check_units_against(data, train_max_ut(cal), small_ok=small_ok, train_noise_ut=cal._train_noise())


def train_max_ut(cal) -> float:
    """The largest |field component| (uT) a calibration's training domain reaches."""
    return float(np.maximum(np.abs(np.asarray(cal.domain.low[:3])), np.abs(np.asarray(cal.domain.high[:3]))).max())


def apply_calibration(model_dir, data_path, out_path, *, level=None, method="auto", n_params=100, n_qmc=256,
                      temperature_unit="C", field_unit=None, columns=None, chunk_size=100_000,
                      progress=False, force: bool = False, time_unit: str = "s") -> dict:
    """Calibrate every row of ``data_path`` with the calibration in ``model_dir``; write ``out_path``.

    ``columns`` maps canonical names to the file's columns; ``field_unit`` and ``temperature_unit``
    are converted at load. The output never replaces the recording, the calibration's training recording, a
    file of a run folder or a read-only file, nor (without ``force``) a file ``apply`` did not write
    (:func:`check_apply_paths`); it is written to a temporary sibling first, then renamed into place. Its unit file
    ``<out>.json`` (units per column, the calibration, level and bayesmag version: :mod:`~bayesmag._src.app.apply_io`)
    follows it, written the same way (the summary's ``units_file``).
    """
    from bayesmag._src.app.artifact import is_field_run
    conversions = declared_conversions(field_unit=field_unit, temperature_unit=temperature_unit, time_unit=time_unit,
                                       columns=columns)
    if is_field_run(model_dir):
        return _apply_field(model_dir, data_path, out_path, conversions, level=level, method=method,
                            n_params=n_params, n_qmc=n_qmc, force=force)
    t0 = time.perf_counter()
    check_apply_options(level, n_params, n_qmc)
    # before loading anything; the training recordings first, so that no refusal offers a --force it would refuse
    out_path = check_apply_paths(model_dir, data_path, out_path, force=force)
    cal = load(model_dir)
    from bayesmag._src.core.frames import load_table      # CSV, or Parquet by suffix
    try:
        data = load_table(data_path, columns=columns, temperature_unit=temperature_unit, field_unit=field_unit,
                          require_reference=False, time_unit=time_unit, mapping_hint="--columns (NAME=COL,...)")
    except DataError as e:
        better = missing_temperature_error(e, columns, thermal=_uses_temperature(cal),
                                           trained=(float(cal.domain.low[3]), float(cal.domain.high[3])))
        if better is None:
            raise
        raise better from None
    _check_magnitudes(data)
    warnings = check_units(cal, data) + new_session_notes(cal)
    from bayesmag._src.app.inputs import failed_sensor_warning
    failed = failed_sensor_warning(model_dir)            # a fleet sensor that failed sign-off
    if failed:
        warnings.insert(0, failed)
    note = cal.domain.step_note(data)
    if note:
        warnings.append(note)
    if cal.domain.rate_high is not None and not data.time_given:
        warnings.append(f"{data_path} has no time column: the field and temperature rates (in_domain_reason "
                        f"field_rate / temperature_rate) were not checked (rows without times have no rate per "
                        f"second), and the output's time column is nan. Give the time in seconds (a 'time' column, "
                        f"or --columns time=NAME) to check them.")
    pred = cal.predict(data, level=level, method=method, n_params=n_params, n_qmc=n_qmc, chunk_size=chunk_size,
                       seed=run_seed(cal), progress=progress, check_units=False,
                       warn=False)                     # checked above, said below, as the CLI says it
    level = cal.level if level is None else level
    if not pred["valid"].any():
        raise DataError(f"No row of {data_path} could be calibrated ({data.n} rows, every one with a non-finite "
                        f"input or output); nothing was written. Check the file's values and column mapping.")
    bad = np.flatnonzero(~pred["valid"])
    if bad.size:
        shown = ", ".join(str(int(r) + 1) for r in bad[:10]) + (f" and {bad.size - 10} more" if bad.size > 10 else "")
        warnings.append(f"{bad.size} row(s) have non-finite inputs or outputs and were not calibrated "
                        f"(marked valid=false): data row(s) {shown}.")
    outside = ~pred["in_domain"] & pred["valid"]
    n_out = int(outside.sum())
    if n_out:
        warnings.append(out_of_domain_note(n_out, data.n, pred["in_domain_reason"][outside]))
    cols = [c for c in OUTPUT_COLUMNS if c in pred]
    write_apply_csv(out_path, data, [(f"{a}_{c}", pred[c][:, i]) for i, a in enumerate(AXES) for c in cols], pred)
    from bayesmag._src.core.datasets import sha256_of
    digest = sha256_of(Path(data_path))
    side = write_apply_sidecar(out_path, apply_about(model_dir, data_path, level, intervals=interval_family(cal, level),
                                                     conversions=conversions, data_sha256=digest))
    summary = {"n_rows": data.n, "n_valid": int(pred["valid"].sum()), "n_outside_domain": n_out,
               "outside_domain_by_reason": {k: int(np.sum(pred["in_domain_reason"][pred["valid"]] == k))
                                            for k in sorted(set(pred["in_domain_reason"][pred["valid"]])) if k},
               "transfer_sd": (None if cal.transfer_sd is None
                               else dict(zip(AXES, np.asarray(cal.transfer_sd, float).tolist()))),
               "warnings": warnings, "level": level, "units_file": str(side), "seconds": time.perf_counter() - t0}
    notes = [n for n in (method_note(cal, method), training_rows_note(model_dir, data_path, digest)) if n]
    if notes:
        summary["notes"] = notes
    ref_note = _reference_unit_note(data, cal) if data.b_ref is not None else None
    if ref_note:
        warnings.append(ref_note)
    if data.b_ref is not None and not ref_note:
        ok = pred["valid"] & np.isfinite(data.b_ref).all(axis=1)
        y, mu = data.b_ref[ok], pred["calibrated"][ok]
        inside = (y >= pred["lower"][ok]) & (y <= pred["upper"][ok])
        summary["metrics"] = {"rmse": dict(zip(AXES, np.sqrt(np.mean((y - mu) ** 2, axis=0)).tolist())),
                              "coverage": dict(zip(AXES, inside.mean(axis=0).tolist()))}
        dom = pred["in_domain"][ok]
        if dom.any():
            summary["metrics"]["coverage_in_domain"] = dict(zip(AXES, inside[dom].mean(axis=0).tolist()))
        miss = ~inside
        summary["metrics"]["misses_flagged"] = dict(zip(AXES, [float((miss[:, a] & ~dom).sum() / max(miss[:, a].sum(), 1))
                                                               for a in range(3)]))
    return summary


def run_seed(cal) -> int:
    """The seed of the calibration's run (``[uq] seed``): a Monte-Carlo apply draws as the run drew."""
    uq = cal.config.get("uq") if isinstance(cal.config, dict) else None
    seed = (uq or {}).get("seed", 0)
    return int(seed) if isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0 else 0


def method_note(cal, method: str) -> str | None:
    """A note when this apply propagates the physics uncertainty by another method than the calibration's run did
    (e.g. the run ``psqmc``, reporting Monte-Carlo means, the apply ``auto`` = exact moments): the calibrated values of
    the same rows then differ by that Monte-Carlo error (0.3 uT on Belsten's extrapolated rows with n_params = 100)."""
    from bayesmag._src.core.physics_uq import resolve_method
    ran_as = (cal.config.get("uq") or {}).get("method", "auto") if isinstance(cal.config, dict) else "auto"
    try:
        ran, used = resolve_method(ran_as, cal.model), resolve_method(method, cal.model)
    except (AttributeError, TypeError):
        return None
    if ran == used:
        return None
    uq = cal.config.get("uq") or {}
    mc = "its Monte-Carlo means" if ran in ("psqmc", "mc") else "exact moments"
    how = {"psqmc": f"--uq psqmc --n-params {uq.get('n_params', 100)} --n-qmc {uq.get('n_qmc', 256)}",
           "analytic": "--uq analytic"}.get(ran)
    return (f"the calibration's run propagated the physics uncertainty with [uq] method = {ran_as!r} ({ran}: {mc}); "
            f"this apply used {used!r}, so on rows the run also predicted the calibrated values and intervals differ "
            f"by the Monte-Carlo error (largest where the epistemic part is large)"
            + (f"; {how} reproduces the run's predictions.csv." if how else "."))


def _reference_unit_note(data, cal) -> str | None:
    """Why the recording's reference columns are not scored, or None: with a declared ``--field-unit`` both the
    readings and the reference are converted, and a reference logged in another unit (uT beside nT readings) would
    be scored 1000x off (before: RMSE 22 uT, coverage 10 %, no word). Checked against the training field
    (:func:`train_max_ut`); the wording is :func:`~bayesmag._src.app.apply_io.reference_unit_note`'s."""
    if data.field_unit is None:
        return None                         # undeclared: the unit check refused a reference in another unit
    ok = np.isfinite(data.b_ref).all(axis=1)
    if not ok.any():
        return None
    meas = np.isfinite(data.b_meas).all(axis=1)
    return reference_unit_note(float(np.percentile(np.abs(data.b_ref[ok]), 99)),
                               float(np.percentile(np.abs(data.b_meas[meas]), 99)) if meas.any() else float("nan"),
                               train_max_ut(cal), data.field_unit)


def training_rows_note(model_dir, data_path, digest: str, *, field: bool = False) -> str | None:
    """A note when the recording is the one the calibration was trained on (its sha256 ``digest`` is the run
    certificate's ``data_sha256``): apply calibrates every recording as a new session, so these rows got the
    new-session intervals (transfer part added) although they come from the training sessions."""
    trained = training_data_sha256(model_dir)
    if trained is None or digest != trained:
        return None
    how = ("`FieldCalibration.predict(u, t, new_session=False)` (bayesmag.load_field(RUN)) gives their same-session "
           "intervals; the run's predictions.csv has them for its held-out rows" if field else
           "`Calibration.predict(..., new_session=False)` (bayesmag.load(RUN)) gives their same-session intervals; "
           "the run's predictions.csv has them for its held-out rows")
    return (f"{data_path} is the recording this calibration was trained on (its sha256 is the certificate's "
            f"data_sha256): its rows are the training sessions' rows, but apply treats every recording as a new "
            f"session, so their intervals include the between-session (transfer) part. {how}. The rows the fit used "
            f"are in-sample: their errors understate a new recording's.")


def _uses_temperature(cal) -> bool:
    """True when the calibration's output depends on each row's temperature (thermal terms, a network, a transform):
    one row at the middle of the training field predicted at the training temperature range's two ends differs.
    True when that cannot be told."""
    if getattr(cal, "network", None) is not None:
        return True
    try:
        from bayesmag._src.core.data import CalibrationData
        lo, hi = np.asarray(cal.domain.low, float), np.asarray(cal.domain.high, float)
        u = (lo[:3] + hi[:3]) / 2
        t_lo, t_hi = lo[3], (hi[3] if hi[3] > lo[3] else lo[3] + 10.0)
        a, b = (cal.predict(CalibrationData(u[None], np.array([t]), None), check_units=False, check_rates=False,
                            warn=False, new_session=False)["calibrated"] for t in (t_lo, t_hi))
        return not np.allclose(a, b, rtol=0, atol=1e-12 * max(1.0, float(np.abs(a).max())))
    except Exception:  # noqa: BLE001 -- an error message is being built: assume the calibration needs it
        return True


def _apply_field(model_dir, data_path, out_path, conversions: dict, *, level, method, n_params, n_qmc,
                 force) -> dict:
    """A field calibration's apply (:func:`~bayesmag._src.app.field_apply.apply_field_calibration`) and its unit
    file: the field columns' meaning, the magnitude's Gaussian interval, relative units for ``field = "free"``."""
    from bayesmag._src.app.artifact import load_field
    from bayesmag._src.app.field_apply import apply_field_calibration
    from bayesmag._src.core.datasets import sha256_of
    cu = {k: conversions[k] for k in ("field_unit", "temperature_unit", "time_unit", "columns")}
    try:
        summary = apply_field_calibration(model_dir, data_path, out_path, level=level, force=force, method=method,
                                          n_params=n_params, n_qmc=n_qmc, **cu)
    except DataError as e:
        try:
            fc = load_field(model_dir)
            trained = (fc.ranges or {}).get("temperature")
            better = missing_temperature_error(e, cu["columns"], thermal=bool(fc.fit.model.temperature),
                                               trained=None if trained is None else tuple(map(float, trained)),
                                               field=True)
        except Exception:  # noqa: BLE001 -- the calibration's own error is said by the apply itself
            better = None
        if better is None:
            raise
        raise better from None
    fc = load_field(model_dir)
    relative = bool(summary.get("relative", getattr(fc.fit.model.measurement, "scale_gauge", False)))
    digest = sha256_of(Path(data_path))
    side = write_apply_sidecar(out_path, apply_about(model_dir, data_path, summary["level"],
                                                     intervals=field_intervals(summary), conversions=conversions,
                                                     data_sha256=digest, relative=relative))
    note = training_rows_note(model_dir, data_path, digest, field=True)
    if note:
        summary = {**summary, "notes": [*summary.get("notes", []), note]}
    return {**summary, "units_file": str(side)}
