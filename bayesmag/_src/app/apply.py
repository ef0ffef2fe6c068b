"""Apply a saved calibration to a new recording: checks, chunked prediction, CSV out, optional metrics."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from bayesmag._src.app.artifact import load
from bayesmag._src.core.data import AXES, DataError, check_values
from bayesmag._src.core.data import check_units as _check_units
from bayesmag._src.core.domain import REASON_CODES

__all__ = ["apply_calibration", "check_units", "check_apply_paths"]

OUTPUT_COLUMNS = ("calibrated", "aleatoric_physics", "epistemic_physics", "residual_physics", "aleatoric_nn",
                  "epistemic_nn", "transfer", "total", "lower", "upper")


def check_units(cal, data) -> list[str]:
    """Errors for units that cannot be right; warnings for suspicious ones (vs the training domain).

    The check is :func:`~bayesmag._src.core.data.check_units`, shared with ``run``, ``discover`` and the library;
    measured and reference columns are both checked against the training range.
    """
    finite = np.isfinite(data.b_meas).all(axis=1) & np.isfinite(data.temperature)
    if not finite.any():
        raise DataError("No row of the recording has finite bx_meas, by_meas, bz_meas and temperature: no row can be "
                        "calibrated. Check the column mapping (--columns) and the file.")
    return _check_units(data.subset(finite), train_max_ut=train_max_ut(cal), fix="Use --field-unit nT",
                       temperature_fix="Use --temperature-unit K")


def new_session_notes(cal) -> list[str]:
    """What a new recording does not get from the calibration: its terms bound to training runs (``run_offset``,
    ``run_step``: :func:`~bayesmag._src.core.physics.new_session_runs`)."""
    bound = [t.name for t in cal.model.terms if t.bound_runs()]
    if not bound:
        return []
    it = "it" if len(bound) == 1 else "them"
    return [f"the calibration's {', '.join(bound)} describe{'s' if len(bound) == 1 else ''} training runs "
            f"{list(cal.model.bound_runs)} only: this recording is calibrated without {it} (as a run with no offset "
            f"of its own and no step; run ids are not matched), and the spread between runs is in the transfer part."]


def train_max_ut(cal) -> float:
    """The largest |field component| (uT) a calibration's training domain reaches."""
    return float(np.maximum(np.abs(np.asarray(cal.domain.low[:3])), np.abs(np.asarray(cal.domain.high[:3]))).max())


def check_apply_options(level, n_params: int, n_qmc: int) -> None:
    """``--level`` in (0, 1) (or None: the run's), ``--n-params`` and ``--n-qmc`` at least 2; else :class:`DataError`."""
    if level is not None and not (isinstance(level, (int, float)) and 0 < level < 1):
        raise DataError(f"--level {level} must be a number in (0, 1), e.g. --level 0.95 for 95 % intervals.")
    for flag, v in (("--n-params", n_params), ("--n-qmc", n_qmc)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 2:
            raise DataError(f"{flag} {v} must be an integer of at least 2 (the PS-QMC draws), e.g. {flag} "
                            f"{100 if flag == '--n-params' else 256}.")


APPLY_HEADER_END = ",in_domain_reason,in_domain,valid"


def is_apply_output(path) -> bool:
    """True if ``path`` is a CSV that ``bayesmag apply`` wrote (its header: ``time,run,...,in_domain,valid``)."""
    path = Path(path)
    if path.is_symlink() or not path.is_file():
        return False
    try:
        with open(path, "rb") as f:
            head = f.readline(65536).decode("utf-8", "replace").strip()
    except OSError:
        return False
    return head.startswith("time,run,x_") and head.endswith(APPLY_HEADER_END)


def refuse_training_recording(out, protected) -> None:
    """:class:`DataError` when ``out`` is one of ``protected`` (the calibration's training recording)."""
    from bayesmag._src.app.outdir import same_file
    for p in protected:
        if same_file(out, p):
            raise DataError(f"--out {out} is the recording the calibration was trained on ({p}); it is never "
                            f"overwritten. Give a new output file name.")


def check_apply_paths(model_dir, data_path, out_path, *, force: bool = False, protected=()) -> Path:
    """Refuse an ``--out`` that would overwrite the recording, a file of the calibration, or a folder.

    Never (even with ``force``): a folder, a symbolic link, the input recording, one of ``protected`` (the
    calibration's training recording), a read-only file, a file of a bayesmag run folder (other than an earlier
    apply output). Without ``force``: an existing file that ``bayesmag apply`` did not write
    (:func:`is_apply_output`).
    """
    from bayesmag._src.app.outdir import read_only, run_file_owner

    out, data, model = Path(out_path), Path(data_path), Path(model_dir)
    fix = "Give a new output file name."
    if out.is_dir():
        raise DataError(f"--out {out} is a folder; give the path of the output CSV file, e.g. {out / 'calibrated.csv'}.")
    if out.is_symlink():
        raise DataError(f"--out {out} is a symbolic link; bayesmag does not write through links. {fix}")
    if out.exists() and data.exists() and out.resolve() == data.resolve():
        raise DataError(f"--out {out} is the input recording --data {data}; it would be overwritten. {fix}")
    try:
        out.resolve().relative_to(model.resolve())
        inside = True
    except ValueError:
        inside = False
    if inside:
        raise DataError(f"--out {out} lies inside the calibration folder --model {model}; writing there could "
                        f"overwrite the calibration. Give an output file outside it.")
    if out.exists():
        refuse_training_recording(out, protected)
        if read_only(out):
            raise DataError(f"--out {out} is read-only (no write permission); bayesmag never replaces a protected "
                            f"file. {fix}")
        ours = is_apply_output(out)
        owner = None if ours else run_file_owner(out)
        if owner is not None:
            raise DataError(f"--out {out} is a file of the bayesmag run folder {owner}; replacing it would break that "
                            f"run, so it is never overwritten. {fix}")
        if not force and not ours:
            raise DataError(f"--out {out} exists and is not a file `bayesmag apply` wrote; bayesmag does not replace "
                            f"it. {fix} Or add --force to replace it.")
    parent = out.parent
    if not parent.is_dir():
        raise DataError(f"--out {out}: the folder {parent} does not exist; create it or give another path.")
    from bayesmag._src.app.outdir import partial_name, recover
    recover(parent, files_only=True)        # partial output files of killed processes (never a live pid's)
    probe = partial_name(out)
    probe.touch()                           # unwritable, read-only or over-long: OSError now, not after the work
    probe.unlink()
    return out


def _check_magnitudes(data) -> None:
    """Absurd magnitudes (|B| > 1 T, |T| > 1e4 C) are corrupt data, refused naming the row (NaN rows stay allowed)."""
    check_values(data, origin=data.source, allow_nonfinite=True)


def apply_calibration(model_dir, data_path, out_path, *, level=None, method="auto", n_params=100, n_qmc=256,
                      temperature_unit="C", field_unit=None, columns=None, chunk_size=100_000,
                      progress=False, force: bool = False) -> dict:
    """Calibrate every row of ``data_path`` with the calibration in ``model_dir``; write ``out_path``.

    ``columns`` maps canonical names to the file's columns; ``field_unit`` and ``temperature_unit``
    are converted at load. The output never replaces the recording, the calibration's training recording, a
    file of a run folder or a read-only file, nor (without ``force``) a file ``apply`` did not write
    (:func:`check_apply_paths`); it is written to a temporary sibling first, then renamed into place.
    """
    from bayesmag._src.app.inputs import recording_paths

    t0 = time.perf_counter()
    check_apply_options(level, n_params, n_qmc)
    out_path = check_apply_paths(model_dir, data_path, out_path, force=force)      # before loading anything
    cal = load(model_dir)
    refuse_training_recording(out_path, recording_paths((cal.config or {}).get("data")
                                                        if isinstance(cal.config, dict) else None))
    from bayesmag._src.core.frames import load_table      # CSV, or Parquet by suffix
    data = load_table(data_path, columns=columns, temperature_unit=temperature_unit, field_unit=field_unit,
                      require_reference=False)
    _check_magnitudes(data)
    warnings = check_units(cal, data) + new_session_notes(cal)
    note = cal.domain.step_note(data)
    if note:
        warnings.append(note)
    pred = cal.predict(data, level=level, method=method, n_params=n_params, n_qmc=n_qmc, chunk_size=chunk_size,
                       progress=progress, check_units=False)      # checked above, with the CLI's wording
    level = cal.level if level is None else level
    if not pred["valid"].any():
        raise DataError(f"No row of {data_path} could be calibrated ({data.n} rows, every one with a non-finite "
                        f"input or output); nothing was written. Check the file's values and column mapping.")
    bad = np.flatnonzero(~pred["valid"])
    if bad.size:
        shown = ", ".join(str(int(r) + 1) for r in bad[:10]) + (f" and {bad.size - 10} more" if bad.size > 10 else "")
        warnings.append(f"{bad.size} row(s) have non-finite inputs or outputs and were not calibrated "
                        f"(marked valid=false): data row(s) {shown}.")
    n_out = int((~pred["in_domain"] & pred["valid"]).sum())
    if n_out:
        warnings.append(f"{n_out} of {data.n} rows lie outside the calibration's training domain (in_domain=false): "
                        f"their values are extrapolation and their intervals may be far too narrow.")
    cols = [c for c in OUTPUT_COLUMNS if c in pred]
    header = ["time", "run"] + [f"{a}_{c}" for a in AXES for c in cols] + ["in_domain_reason", "in_domain", "valid"]
    mats = [data.time[:, None], data.run[:, None].astype(np.float64)]
    for a in range(3):
        mats += [pred[c][:, a:a + 1] for c in cols]
    # the reason as a bit code (the file stays all-numeric): sum of REASON_CODES, 0 inside or invalid
    code = np.array([sum(REASON_CODES[k] for k in w.split(";") if k in REASON_CODES) for w in pred["in_domain_reason"]])
    mats += [code[:, None].astype(np.float64), pred["in_domain"][:, None].astype(np.float64),
             pred["valid"][:, None].astype(np.float64)]
    mat = np.concatenate(mats, axis=1)
    fmt = ["%.6f", "%d"] + ["%.8g"] * (mat.shape[1] - 5) + ["%d", "%d", "%d"]
    tmp = out_path.with_name(f".{out_path.name}.partial-{os.getpid()}")
    try:
        with open(tmp, "w") as f:
            f.write(",".join(header) + "\n")
            for lo in range(0, data.n, 200_000):
                np.savetxt(f, mat[lo:lo + 200_000], delimiter=",", fmt=fmt)
        tmp.replace(out_path)
    finally:
        tmp.unlink(missing_ok=True)
    summary = {"n_rows": data.n, "n_valid": int(pred["valid"].sum()), "n_outside_domain": n_out,
               "outside_domain_by_reason": {k: int(np.sum(pred["in_domain_reason"][pred["valid"]] == k))
                                            for k in sorted(set(pred["in_domain_reason"][pred["valid"]])) if k},
               "transfer_sd": (None if cal.transfer_sd is None
                               else dict(zip(AXES, np.asarray(cal.transfer_sd, float).tolist()))),
               "warnings": warnings, "level": level, "seconds": time.perf_counter() - t0}
    if data.b_ref is not None:
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
