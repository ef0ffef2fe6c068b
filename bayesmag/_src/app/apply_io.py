"""What every apply shares (vector, field, archive): the option and ``--out`` checks, the unit check against a
training range, the output CSV written atomically, and its unit file.

The unit file (:func:`sidecar_path`: ``<out>.json`` beside a CSV, :data:`DATASET_SIDECAR` inside a Dask apply's
folder) states what the CSV's bare numbers are: the unit of every column (:func:`column_units`), the level of the
intervals, the calibration they come from (folder, certificate ID, sha256 of its calibration file), the recording,
the bayesmag version and the CSV's own sha256 and row count (so a unit file that does not belong to the CSV beside
it can be told), the predictive family of the intervals (:func:`interval_family`, :func:`field_intervals`: a Laplace
hybrid's interval is not 1.96 x total), the conversions declared at load (:func:`declared_conversions`) and the
input recording's sha256 (a single file; an archive's folder or glob has none, and the file says so). The CSV itself
is unchanged: ``pandas.read_csv`` reads it as before."""

from __future__ import annotations

import dataclasses
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
           "column_units", "apply_about", "sidecar_doc", "write_apply_sidecar", "DATASET_SIDECAR", "SIDECAR_KIND",
           "training_recordings", "training_data_sha256", "reference_unit_note", "interval_family", "field_intervals",
           "declared_conversions", "missing_temperature_error"]


def check_units_against(data, train_max: float, *, small_ok: bool = False,
                        train_noise_ut: float | None = None) -> list[str]:
    """The unit check of :func:`~bayesmag._src.core.data.check_units` (errors for units that cannot be right,
    warnings for suspicious ones) on the finite rows, against a training domain reaching ``train_max`` uT."""
    finite = np.isfinite(data.b_meas).all(axis=1) & np.isfinite(data.temperature)
    if not finite.any():
        raise DataError("No row of the recording has finite bx_meas, by_meas, bz_meas and temperature: no row can be "
                        "calibrated. Check the column mapping (--columns) and the file.")
    rows = data.subset(finite)
    if rows.field_unit is not None and rows.b_ref is not None:
        # a declared unit converts the reference too; one logged in another unit than the readings is said by the
        # caller (reference_unit_note: not scored, the calibrated values unaffected), not here as "the calibrated
        # values are wrong by that factor" (seventh outside pass: two overlapping warnings, the first one wrong)
        rows = dataclasses.replace(rows, b_ref=None)
    return _check_units(rows, train_max_ut=train_max, fix="Use --field-unit nT",
                        temperature_fix="Use --temperature-unit K", small_ok=small_ok, train_noise_ut=train_noise_ut)


def reference_unit_note(p99_ref: float, p99_meas: float, train_max: float, field_unit: str | None) -> str | None:
    """Why an apply does not score the recording's reference columns, or None: with a declared ``--field-unit`` the
    readings and the reference are both converted, and a reference still logged in another unit (uT beside nT
    readings) is far (over 50x) from the training field ``train_max`` (uT) after the conversion. ``p99_ref`` /
    ``p99_meas``: 99th percentiles of |component| of the reference and the readings (uT, after the conversion). Only
    the scores are affected: the calibrated values come from the readings (said as such when the readings look
    right; when they do not, the readings' own warning says what that does)."""
    if field_unit is None or not np.isfinite(p99_ref) or not train_max > 0:
        return None
    odd = lambda v: not train_max / 50 <= v <= 50 * train_max      # noqa: E731
    if not odd(p99_ref):
        return None
    head = (f"the reference columns (bx_ref, by_ref, bz_ref) reach {p99_ref:.4g} uT (99th percentile) after the "
            f"declared --field-unit {field_unit} conversion, while the calibration's training field reached "
            f"{train_max:.4g} uT")
    if np.isfinite(p99_meas) and not odd(p99_meas) and p99_ref > 0:
        r = p99_ref / p99_meas
        size = f"about {10 ** round(abs(np.log10(r))):g}x {'smaller' if r < 1 else 'larger'} than theirs"
        return (f"{head} and the readings {p99_meas:.4g} uT: the reference columns look like another unit than the "
                f"readings ({size}; uT already?), so no RMSE or coverage against them is "
                f"given (it would not be meaningful). The calibrated values are unaffected: they come from the "
                f"readings and are in uT. To score them, give the reference columns in {field_unit} like the readings.")
    return (f"{head}: no RMSE or coverage against them is given (it would not be meaningful); see the warning on "
            f"the readings for the calibrated values.")


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


#: The unit of a field calibration's field columns fitted with ``measurement.field = "free"`` (trace(S) = 3).
RELATIVE_UNIT = "1 (relative)"

#: What each column of a field-calibration apply means (the field columns: ``field_apply.FIELD_OUTPUT_COLUMNS``).
_FIELD_MEANING = {
    "x_calibrated": "calibrated field, x, in the calibration's gauge frame (x along the sensor's x axis, y in its x-y "
                    "plane), not the vehicle's body frame: a magnitude fit cannot see that rotation (docs/field.md)",
    "y_calibrated": "calibrated field, y, in the gauge frame (as x_calibrated)",
    "z_calibrated": "calibrated field, z, in the gauge frame (as x_calibrated)",
    "magnitude": "calibrated field magnitude |B|, the quantity the intervals are for",
    "magnitude_epistemic": "sd of the magnitude from the calibration's parameter uncertainty",
    "magnitude_noise": "sd of the magnitude from the sensor's noise (the fit's residual scale)",
    "magnitude_transfer": "between-session sd added for this recording, a new session (0 when the calibration holds "
                          "none)",
    "magnitude_total": "total sd: sqrt((interval_scale x sqrt(magnitude_epistemic^2 + magnitude_noise^2))^2 + "
                       "magnitude_transfer^2)",
    "magnitude_lower": "lower end of the central interval of probability 'level': magnitude - interval_factor x "
                       "magnitude_total, clipped at 0 (a magnitude is >= 0)",
    "magnitude_upper": "upper end of that interval: magnitude + interval_factor x magnitude_total",
}
_FIELD_REASONS = ("field_range", "temperature", "magnitude")


def column_units(names, *, relative: bool = False) -> dict[str, str]:
    """The unit of every apply output column: ``time`` s; ``run`` and the flags 1 (a number without unit); every
    field value, sd and interval bound (``x_calibrated``, ``x_total``, ``magnitude_lower``, ...) uT, or
    :data:`RELATIVE_UNIT` with ``relative`` (a field calibration fitted with ``field = "free"``). A name of no
    known kind raises ``ValueError`` (a new column must say its unit)."""
    out = {}
    for n in names:
        if n in _UNITS:
            out[n] = _UNITS[n]
        elif n.startswith(("x_", "y_", "z_", "magnitude")):
            out[n] = RELATIVE_UNIT if relative else "uT"
        else:
            raise ValueError(f"apply output column {n!r} has no known unit; add it to apply_io.column_units.")
    return out


def training_recordings(model_dir) -> list:
    """The recordings the calibration in ``model_dir`` was trained on (and, for a fleet sensor, its fleet's:
    :func:`~bayesmag._src.app.inputs.protected_recordings`), read from the calibration's saved config
    (``calibration.json``, or a field run's ``config.resolved.toml``) before the calibration is loaded, so that
    ``--out`` is checked against them first. [] when neither can be read (loading then names what is wrong)."""
    from bayesmag._src.app.inputs import protected_recordings
    model = Path(model_dir)
    data_cfg = None
    try:
        if (model / "calibration.json").is_file():
            cfg = json.loads((model / "calibration.json").read_text()).get("config")
            data_cfg = cfg.get("data") if isinstance(cfg, dict) else None
        elif (model / "config.resolved.toml").is_file():
            import tomllib
            data_cfg = tomllib.loads((model / "config.resolved.toml").read_text()).get("data")
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        data_cfg = None
    try:
        return protected_recordings(data_cfg if isinstance(data_cfg, dict) else None, model)
    except (OSError, ValueError, AttributeError):
        return []


def training_data_sha256(model_dir) -> str | None:
    """The sha256 of the data the calibration in ``model_dir`` was trained on, as its certificate recorded it
    (``metrics.json``: ``certificate.data_sha256``; the file's sha256 for a recording), or None."""
    try:
        cert = json.loads((Path(model_dir) / "metrics.json").read_text()).get("certificate") or {}
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        return None
    digest = cert.get("data_sha256") if isinstance(cert, dict) else None
    return digest if isinstance(digest, str) and digest else None


def missing_temperature_error(error: Exception, columns, *, thermal: bool, trained=None,
                              field: bool = False) -> "DataError | None":
    """``apply``'s message for a recording without the temperature column (``error``: the loader's DataError), or
    None when ``error`` is about something else. The loader's advice was for training (``temperature_terms =
    false``), a key that does nothing for applying a calibration already fitted: say what applies. ``thermal``:
    the calibration's output depends on the temperature; ``trained``: its training temperature range (C);
    ``field``: a field calibration (its config key is ``[measurement] temperature_terms``)."""
    import re
    src = dict(columns or {}).get("temperature", "temperature")
    text = " ".join(str(error).split())
    if f"has no column {src!r}" not in text:
        return None
    m = re.match(r"(.*?Columns found: \[.*?\])", text)
    head = (m.group(1) if m else text.split(". ")[0]) + "."
    span = (f" (trained at {trained[0]:.4g} to {trained[1]:.4g} C)" if trained is not None
            and all(np.isfinite(trained)) else "")
    how = ("give it as a 'temperature' column, or name the file's column with --columns temperature=NAME "
           "(--temperature-unit K for kelvin)")
    if thermal:
        return DataError(f"{head} This calibration needs each row's temperature: its thermal terms correct the field "
                         f"with it{span}; {how}. A recording without a temperature sensor cannot be calibrated "
                         f"with it: recalibrate without thermal terms ({'[measurement]' if field else '[physics]'} "
                         f"temperature_terms = false in the run's config) and apply that calibration.")
    mid = f" holding one value inside that range, e.g. {(trained[0] + trained[1]) / 2:.3g}" if span else ""
    return DataError(f"{head} This calibration has no thermal terms, but its training-domain check reads the "
                     f"temperature{span}: {how}; a recording without a temperature sensor can be given a constant "
                     f"temperature column{mid}.")


def interval_family(cal, level: float) -> dict:
    """The predictive family of a vector calibration's intervals, for the unit file: Gaussian for the physics model
    (and the paper's fusion), the hybrid's likelihood (``hybrid_family``, as in the run's ``predictions.csv``) with
    its fixed shape (a Student-t's ``df``) or the names of the shape fields its network learned per row, and the
    factor ``interval_factor`` (half-width over ``total``, where it is the same in every row): 1.96 for a Gaussian at
    95 %, 2.12 for a Laplace (a Laplace hybrid's interval rebuilt as 1.96 x total is 8 % too narrow)."""
    from bayesmag._src.core.likelihoods import get_likelihood, moment_match
    net = getattr(cal, "network", None)
    fusion, fixed, learned, family, hybrid = None, {}, [], "gaussian", None
    if net is not None:
        from bayesmag._src.core.network import NetworkSpec
        meta = net["meta"]
        spec = NetworkSpec.from_dict(meta["spec"])
        fusion, hybrid = meta.get("fusion", "moment_match"), spec.likelihood
        if fusion != "paper":
            family = spec.likelihood
            fixed = {k: float(v) for k, v in spec.fixed_shape.items()}
            learned = [f for f in get_likelihood(family).shape_names() if f not in fixed]
    factor = None
    if not learned:
        factor = float(np.asarray(moment_match(family, np.zeros(1), np.ones(1), **fixed).interval(level)[1])[0])
    out = {"family": family, "of": "each axis (x, y, z) separately", "level": float(level),
           "source": "physics model" if net is None else f"hybrid (physics + residual network, fusion {fusion!r})"}
    if hybrid is not None:
        out["hybrid_family"] = hybrid
        if fusion == "paper":
            out["note"] = ("the paper's fusion combines the parts as a Gaussian whatever the network's likelihood "
                           f"({hybrid!r})")
    if fixed:
        out["shape"] = fixed
    if learned:
        out["shape_learned_per_row"] = learned
    out["interval_factor"] = factor
    out["rule"] = ("lower, upper = calibrated -/+ interval_factor x total (the family's central interval of "
                   "probability 'level' with sd total)" if factor is not None else
                   f"the family's central interval of probability 'level' with sd total and each row's own "
                   f"{', '.join(learned)} (learned by the network, not in this file): the half-width over total "
                   f"differs between rows, so use lower and upper as written")
    return out


def field_intervals(summary: dict) -> dict:
    """The predictive family of a field-calibration apply's intervals (of the magnitude), from the summary
    ``field_apply.apply_field_calibration`` returns: Gaussian, ``interval_factor`` z of the level, the run's interval
    scale and between-session sd."""
    import scipy.stats
    level = float(summary["level"])
    out = {"family": "gaussian", "of": "the field magnitude (magnitude)", "level": level,
           "interval_factor": float(scipy.stats.norm.ppf(0.5 + level / 2)),
           "rule": "magnitude_lower, magnitude_upper = magnitude -/+ interval_factor x magnitude_total (the lower end "
                   "clipped at 0)"}
    for k in ("measurement", "interval_scale", "transfer_sd", "transfer_method"):
        if k in summary:
            out[k] = summary[k]
    return out


def declared_conversions(*, field_unit=None, temperature_unit="C", time_unit="s", columns=None) -> dict:
    """What the command declared about the recording's units and columns (``--field-unit``, ``--temperature-unit``,
    ``--time-unit``, ``--columns``), converted at load, for the unit file."""
    return {"field_unit": field_unit, "temperature_unit": temperature_unit, "time_unit": time_unit,
            "columns": dict(columns) if columns else None,
            "meaning": "the recording's units and column names as declared at load (--field-unit, --temperature-unit, "
                       "--time-unit, --columns), converted to uT, C and s before calibrating; field_unit null: none "
                       "declared, the field read as uT and checked against the training field; columns null: the "
                       "canonical names. The output columns are in the units under 'units' whatever was declared"}


def apply_about(model_dir, data, level: float, *, intervals: dict | None = None, conversions: dict | None = None,
                data_sha256: str | None = None, relative: bool = False) -> dict:
    """What an apply's unit file says about where its numbers come from: the calibration (folder, kind, certificate
    ID where the run has one, sha256 of its calibration file), the recording and its sha256 (``data_sha256``, or of
    ``data`` when it is one file; an archive's folder or glob is said to have none), the intervals' level and
    family (``intervals``: :func:`interval_family`, :func:`field_intervals`), the declared ``conversions``
    (:func:`declared_conversions`) and, for a field calibration fitted with ``field = "free"``, ``relative``."""
    from bayesmag._src.core.datasets import sha256_of
    model = Path(model_dir).resolve()
    main = next((model / f for f in ("calibration.json", "field_params.json") if (model / f).is_file()), None)
    cid = None
    try:
        cert = json.loads((model / "metrics.json").read_text()).get("certificate") or {}
        cid = cert.get("calibration_id") if isinstance(cert, dict) else None
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        pass
    glob = any(c in str(data) for c in "*?[")
    out = {"calibration": {"folder": str(model), "kind": "field" if main and main.name == "field_params.json"
                           else "vector", "calibration_id": cid,
                           "file": main.name if main else None, "sha256": sha256_of(main) if main else None},
           "data": str(Path(data).resolve()) if not glob else str(data)}
    if data_sha256 is None and not glob and Path(data).is_file():
        data_sha256 = sha256_of(Path(data))
    if data_sha256 is not None:
        out["data_sha256"] = data_sha256
    else:
        out["data_sha256_not_recorded"] = ("the recording is an archive (a folder or a glob of files), not one file: "
                                           "no single sha256 describes it")
    out["level"] = float(level)
    if intervals is not None:
        out["intervals"] = intervals
    if conversions is not None:
        out["conversions"] = conversions
    if relative:
        out["relative"] = ("the calibration fitted the field magnitude itself (measurement field = \"free\"): the "
                           "calibrated field, its magnitude, their sds and bounds are relative (trace(S) = 3), not uT")
    return out


def sidecar_doc(about: dict, columns, *, rows: int, files: dict) -> dict:
    """The unit file's JSON: ``about`` (:func:`apply_about`), the unit and meaning of each of ``columns`` (a field
    calibration's field columns described as such, relative with ``about["relative"]``), ``rows``, ``files`` (the
    files it describes: name -> ``{"rows": n}``, with ``"sha256"`` for a CSV), the bayesmag version and the time it
    was written."""
    from bayesmag._src.core.version import __version__
    field = (about.get("calibration") or {}).get("kind") == "field"
    units = column_units(columns, relative=bool(about.get("relative")))
    if field:
        unit = RELATIVE_UNIT if about.get("relative") else "uT"
        meaning = {n: f"{_FIELD_MEANING[n]} ({unit})" for n in units if n in _FIELD_MEANING}
        reason = ("bit code, the sum of " + ", ".join(f"{REASON_CODES[k]} {k}" for k in _FIELD_REASONS)
                  + " (field_range: a reading outside training's; magnitude: the calibrated magnitude outside the "
                    "training reference magnitudes); 0 inside the training domain or invalid")
    else:
        meaning = {"uT columns": "calibrated field values, their standard deviations (aleatoric, epistemic, "
                                 "residual, transfer: their parts; total) and the central interval of "
                                 "probability 'level' (lower, upper; see 'intervals' for its family)"}
        reason = _MEANING["in_domain_reason"]
    meaning.update({n: (reason if n == "in_domain_reason" else _MEANING[n]) for n in units if n in _MEANING})
    return {"tool": "bayesmag", "kind": SIDECAR_KIND, "bayesmag_version": __version__,
            "written_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "files": files, "rows": int(rows), **about, "units": units, "meaning": meaning}


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


def check_apply_paths(model_dir, data_path, out_path, *, force: bool = False, protected=None) -> Path:
    """Refuse an ``--out`` that would overwrite the recording, a file of the calibration, or a folder.

    Never (even with ``force``): a folder, a symbolic link, the input recording, one of ``protected`` (the
    calibration's training recordings; None, the default: :func:`training_recordings` of ``model_dir``), a read-only
    file, a file of a bayesmag run folder (other than an earlier apply output). Without ``force``: an existing file
    that ``bayesmag apply`` did not write (:func:`is_apply_output`). What ``force`` cannot override is checked first,
    so a refusal never suggests --force for a file --force would not replace (a training recording was refused with
    "Or add --force to replace it", then with --force as a training recording). The unit file ``<out>.json``
    (:func:`sidecar_path`) is checked by the same rules.
    """
    from bayesmag._src.app.outdir import read_only, run_file_owner

    out, data, model = Path(out_path), Path(data_path), Path(model_dir)
    if protected is None:
        protected = training_recordings(model)
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
    needs_force = [_check_sidecar(sidecar_path(out), out, data, protected)]
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
        if not ours:
            needs_force.insert(0, f"--out {out} exists and is not a file `bayesmag apply` wrote; bayesmag does not "
                                  f"replace it. {fix} Or add --force to replace it.")
    needs_force = [m for m in needs_force if m]
    if needs_force and not force:          # only now: every refusal --force cannot override came first
        raise DataError(needs_force[0])
    parent = out.parent
    if not parent.is_dir():
        raise DataError(f"--out {out}: the folder {parent} does not exist; create it or give another path.")
    from bayesmag._src.app.outdir import partial_name, recover
    recover(parent, files_only=True)        # partial output files of killed processes (never a live pid's)
    probe = partial_name(out)
    probe.touch()                           # unwritable, read-only or over-long: OSError now, not after the work
    probe.unlink()
    return out


def _check_sidecar(side: Path, out: Path, data: Path, protected) -> str | None:
    """:func:`check_apply_paths`'s rules for the unit file ``side`` of ``--out out``: raises what ``--force`` cannot
    override; returns the refusal ``--force`` overrides (a file apply did not write), or None."""
    from bayesmag._src.app.outdir import read_only, run_file_owner
    fix = "Give a new output file name."
    what = f"--out {out}: its unit file {side}"
    if side.is_dir() or side.is_symlink():
        raise DataError(f"{what} is a {'folder' if side.is_dir() else 'symbolic link'}; bayesmag does not replace it. "
                        f"{fix}")
    if not side.exists():
        return None
    if data.exists() and side.resolve() == data.resolve():
        raise DataError(f"{what} is the input recording --data {data}; it would be overwritten. {fix}")
    refuse_training_recording(side, protected)
    if read_only(side):
        raise DataError(f"{what} is read-only (no write permission); bayesmag never replaces a protected file. {fix}")
    ours = is_apply_sidecar(side)
    owner = None if ours else run_file_owner(side)
    if owner is not None:
        raise DataError(f"{what} is a file of the bayesmag run folder {owner}; it is never overwritten. {fix}")
    if not ours:
        return (f"{what} exists and was not written by `bayesmag apply`; bayesmag does not replace it. {fix} "
                f"Or add --force to replace it.")
    return None


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
