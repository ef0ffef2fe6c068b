"""What every apply shares (vector, field, archive): the option and ``--out`` checks, the unit check against a
training range, the output CSV written atomically, and its unit file.

The unit file (:func:`sidecar_path`: ``<out>.json`` beside a CSV, :data:`DATASET_SIDECAR` inside a Dask apply's
folder) states what the CSV's bare numbers are: the unit of every column (:func:`column_units`), the level of the
intervals, the calibration they come from (folder, certificate ID, sha256 of its calibration file), the recording,
the bayesmag version and the CSV's own sha256 and row count (so a unit file that does not belong to the CSV beside
it can be told). The CSV itself is unchanged: ``pandas.read_csv`` reads it as before."""

from __future__ import annotations

import datetime
import json
import os
from pathlib import Path

import numpy as np

from bayesmag._src.core.data import DataError, check_values
from bayesmag._src.core.data import check_units as _check_units
from bayesmag._src.core.domain import REASON_CODES

__all__ = ["check_apply_options", "check_apply_paths", "check_units_against", "is_apply_output",
           "refuse_training_recording", "write_apply_csv", "APPLY_HEADER_END", "sidecar_path", "is_apply_sidecar",
           "column_units", "apply_about", "sidecar_doc", "write_apply_sidecar", "DATASET_SIDECAR", "SIDECAR_KIND"]


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


#: The ``kind`` of an apply's unit file (with ``tool`` = bayesmag): what :func:`is_apply_sidecar` recognises.
SIDECAR_KIND = "apply-output"
#: The unit file inside a Dask apply's Parquet folder (a leading underscore: Parquet readers skip it).
DATASET_SIDECAR = "_bayesmag_apply.json"

#: Units of the columns that are not field values (every other output column is a field value or sd, in uT).
_UNITS = {"time": "s", "run": "1", "in_domain_reason": "1", "in_domain": "1", "valid": "1"}
_MEANING = {
    "time": "seconds, as in the recording (nan when it had no time column)",
    "run": "session id, as in the recording",
    "in_domain_reason": "bit code, the sum of " + ", ".join(f"{v} {k}" for k, v in REASON_CODES.items())
                        + "; 0 inside the training domain or invalid",
    "in_domain": "1 inside the calibration's training domain, else 0",
    "valid": "1 calibrated (finite inputs and outputs), 0 not calibrated (NaN outputs)",
}


def sidecar_path(out) -> Path:
    """The unit file of apply output ``out``: ``<out>.json`` beside a CSV (``calibrated.csv.json``)."""
    out = Path(out)
    return out.with_name(out.name + ".json")


def is_apply_sidecar(path) -> bool:
    """True if ``path`` is a unit file ``bayesmag apply`` wrote (a JSON object, ``tool`` bayesmag, ``kind``
    :data:`SIDECAR_KIND`)."""
    path = Path(path)
    if path.is_symlink() or not path.is_file() or path.stat().st_size > 1 << 20:
        return False
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(doc, dict) and doc.get("tool") == "bayesmag" and doc.get("kind") == SIDECAR_KIND


def column_units(names) -> dict[str, str]:
    """The unit of every apply output column: ``time`` s; ``run`` and the flags 1 (a number without unit); every
    field value, sd and interval bound (``x_calibrated``, ``x_total``, ``magnitude_lower``, ...) uT. A name of no
    known kind raises ``ValueError`` (a new column must say its unit)."""
    out = {}
    for n in names:
        if n in _UNITS:
            out[n] = _UNITS[n]
        elif n.startswith(("x_", "y_", "z_", "magnitude")):
            out[n] = "uT"
        else:
            raise ValueError(f"apply output column {n!r} has no known unit; add it to apply_io.column_units.")
    return out


def apply_about(model_dir, data, level: float) -> dict:
    """What an apply's unit file says about where its numbers come from: the calibration (folder, kind, certificate
    ID where the run has one, sha256 of its calibration file), the recording, the intervals' level."""
    from bayesmag._src.core.datasets import sha256_of
    model = Path(model_dir).resolve()
    main = next((model / f for f in ("calibration.json", "field_params.json") if (model / f).is_file()), None)
    cid = None
    try:
        cert = json.loads((model / "metrics.json").read_text()).get("certificate") or {}
        cid = cert.get("calibration_id") if isinstance(cert, dict) else None
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        pass
    return {"calibration": {"folder": str(model), "kind": "field" if main and main.name == "field_params.json"
                            else "vector", "calibration_id": cid,
                            "file": main.name if main else None, "sha256": sha256_of(main) if main else None},
            "data": str(Path(data).resolve()) if not any(c in str(data) for c in "*?[") else str(data),
            "level": float(level)}


def sidecar_doc(about: dict, columns, *, rows: int, files: dict) -> dict:
    """The unit file's JSON: ``about`` (:func:`apply_about`), the unit and meaning of each of ``columns``, ``rows``,
    ``files`` (the files it describes: name -> ``{"rows": n}``, with ``"sha256"`` for a CSV), the bayesmag version
    and the time it was written."""
    from bayesmag._src.core.version import __version__
    units = column_units(columns)
    return {"tool": "bayesmag", "kind": SIDECAR_KIND, "bayesmag_version": __version__,
            "written_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "files": files, "rows": int(rows), **about, "units": units,
            "meaning": {"uT columns": "calibrated field values, their standard deviations (aleatoric, epistemic, "
                                      "residual, transfer: their parts; total) and the central interval of "
                                      "probability 'level' (lower, upper)",
                        **{n: _MEANING[n] for n in units if n in _MEANING}}}


def write_apply_sidecar(out_path, about: dict) -> Path:
    """Write the unit file of the apply CSV ``out_path`` (:func:`sidecar_path`) atomically, after the CSV: it names
    the CSV's columns (its header), rows and sha256."""
    from bayesmag._src.app.outdir import atomic_write_text
    from bayesmag._src.core.datasets import sha256_of
    out_path = Path(out_path)
    with open(out_path) as f:
        header = f.readline().strip().split(",")
        rows = sum(1 for _ in f)
    doc = sidecar_doc(about, header, rows=rows, files={out_path.name: {"rows": rows, "sha256": sha256_of(out_path)}})
    return atomic_write_text(sidecar_path(out_path), json.dumps(doc, indent=2) + "\n")


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
    (:func:`is_apply_output`). The unit file ``<out>.json`` (:func:`sidecar_path`) is checked by the same rules.
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
    _check_sidecar(sidecar_path(out), out, data, protected, force)
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


def _check_sidecar(side: Path, out: Path, data: Path, protected, force: bool) -> None:
    """:func:`check_apply_paths`'s rules for the unit file ``side`` of ``--out out``."""
    from bayesmag._src.app.outdir import read_only, run_file_owner
    fix = "Give a new output file name."
    what = f"--out {out}: its unit file {side}"
    if side.is_dir() or side.is_symlink():
        raise DataError(f"{what} is a {'folder' if side.is_dir() else 'symbolic link'}; bayesmag does not replace it. "
                        f"{fix}")
    if not side.exists():
        return
    if data.exists() and side.resolve() == data.resolve():
        raise DataError(f"{what} is the input recording --data {data}; it would be overwritten. {fix}")
    refuse_training_recording(side, protected)
    if read_only(side):
        raise DataError(f"{what} is read-only (no write permission); bayesmag never replaces a protected file. {fix}")
    ours = is_apply_sidecar(side)
    owner = None if ours else run_file_owner(side)
    if owner is not None:
        raise DataError(f"{what} is a file of the bayesmag run folder {owner}; it is never overwritten. {fix}")
    if not force and not ours:
        raise DataError(f"{what} exists and was not written by `bayesmag apply`; bayesmag does not replace it. {fix} "
                        f"Or add --force to replace it.")


def write_apply_csv(out_path: Path, data, columns, pred) -> None:
    """The apply output: ``time,run``, the ``(name, (n,) values)`` columns, then ``in_domain_reason`` (bit code, sum
    of :data:`REASON_CODES`; 0 inside or invalid), ``in_domain``, ``valid``; written to a temporary sibling and
    renamed into place, so a killed process never leaves a half-written file under the name. Rows read without a time
    column get ``nan`` times (the row index they are numbered by inside is not a time). An earlier apply's unit file
    beside it (:func:`sidecar_path`) is removed before the rename, so none describes another result; the caller
    writes the new one (:func:`write_apply_sidecar`)."""
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
        side = sidecar_path(out_path)
        if is_apply_sidecar(side):                  # an earlier apply's: it would describe another result
            side.unlink()
        tmp.replace(out_path)
    finally:
        tmp.unlink(missing_ok=True)


def _check_magnitudes(data) -> None:
    """Absurd magnitudes (|B| > 1 T, |T| > 1e4 C) are corrupt data, refused naming the row (NaN rows stay allowed)."""
    check_values(data, origin=data.source, allow_nonfinite=True)
