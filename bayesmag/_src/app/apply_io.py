"""What every apply shares (vector, field, archive): the option and ``--out`` checks, the unit check against a
training range, and the output CSV written atomically."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from bayesmag._src.core.data import DataError, check_values
from bayesmag._src.core.data import check_units as _check_units
from bayesmag._src.core.domain import REASON_CODES

__all__ = ["check_apply_options", "check_apply_paths", "check_units_against", "is_apply_output",
           "refuse_training_recording", "write_apply_csv", "APPLY_HEADER_END"]


def check_units_against(data, train_max: float, *, small_ok: bool = False,
                        train_noise_ut: float | None = None) -> list[str]:
    """The unit check of :func:`~bayesmag._src.core.data.check_units` (errors for units that cannot be right,
    warnings for suspicious ones) on the finite rows, against a training domain reaching ``train_max`` uT."""
    finite = np.isfinite(data.b_meas).all(axis=1) & np.isfinite(data.temperature)
    if not finite.any():
        raise DataError("No row of the recording has finite bx_meas, by_meas, bz_meas and temperature: no row can be "
                        "calibrated. Check the column mapping (--columns) and the file.")
    return _check_units(data.subset(finite), train_max_ut=train_max, fix="Use --field-unit nT",
                       temperature_fix="Use --temperature-unit K", small_ok=small_ok, train_noise_ut=train_noise_ut)


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
    """:class:`DataError` when ``out`` is one of ``protected`` (the training recordings: :func:`recording_paths`)."""
    from bayesmag._src.app.outdir import same_file
    for p in protected:
        if same_file(out, p):
            raise DataError(f"--out {out} is a recording ({p}) this calibration, or another sensor of its fleet, "
                            f"was trained on; it is never overwritten. Give a new output file name.")


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


def write_apply_csv(out_path: Path, data, columns, pred) -> None:
    """The apply output: ``time,run``, the ``(name, (n,) values)`` columns, then ``in_domain_reason`` (bit code, sum
    of :data:`REASON_CODES`; 0 inside or invalid), ``in_domain``, ``valid``; written to a temporary sibling and
    renamed into place, so a killed process never leaves a half-written file under the name. Rows read without a time
    column get ``nan`` times (the row index they are numbered by inside is not a time)."""
    header = ["time", "run"] + [c for c, _ in columns] + ["in_domain_reason", "in_domain", "valid"]
    code = np.array([sum(REASON_CODES[k] for k in w.split(";") if k in REASON_CODES) for w in pred["in_domain_reason"]])
    time = data.time if getattr(data, "time_given", True) else np.full(data.n, np.nan)
    mat = np.column_stack([time, data.run.astype(np.float64)] + [np.asarray(v, np.float64) for _, v in columns]
                          + [code.astype(np.float64), pred["in_domain"].astype(np.float64),
                             pred["valid"].astype(np.float64)])
    fmt = ["%.6f", "%d"] + ["%.8g"] * len(columns) + ["%d", "%d", "%d"]
    tmp = out_path.with_name(f".{out_path.name}.partial-{os.getpid()}")
    try:
        with open(tmp, "w") as f:
            f.write(",".join(header) + "\n")
            for lo in range(0, data.n, 200_000):
                np.savetxt(f, mat[lo:lo + 200_000], delimiter=",", fmt=fmt)
        tmp.replace(out_path)
    finally:
        tmp.unlink(missing_ok=True)


def _check_magnitudes(data) -> None:
    """Absurd magnitudes (|B| > 1 T, |T| > 1e4 C) are corrupt data, refused naming the row (NaN rows stay allowed)."""
    check_values(data, origin=data.source, allow_nonfinite=True)
