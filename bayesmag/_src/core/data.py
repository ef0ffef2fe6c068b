"""Calibration data: one immutable container, CSV loaders, validation and splits.

Units throughout: magnetic field in microtesla (uT), temperature in degrees Celsius,
time in seconds. Every loader validates at the boundary and raises
:class:`DataError` naming the row, column and the fix.
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

__all__ = [
    "CalibrationData",
    "DataError",
    "CANONICAL_COLUMNS",
    "load_csv",
    "load_belsten",
    "load_column",
    "write_csv",
    "validate",
    "validate_for_discover",
    "check_field_unit",
    "check_values",
    "check_units",
    "spread_duplicate_times",
    "DataNote",
    "FIELD_UNITS",
    "ARRAY_COLUMNS",
    "split_random",
    "split_by_run",
    "split_time_blocks",
    "make_split",
    "Split",
]

AXES = ("x", "y", "z")
CANONICAL_COLUMNS = (
    "time",
    "run",
    "bx_meas",
    "by_meas",
    "bz_meas",
    "temperature",
    "bx_ref",
    "by_ref",
    "bz_ref",
)
_REQUIRED = ("bx_meas", "by_meas", "bz_meas", "temperature")
_REF = ("bx_ref", "by_ref", "bz_ref")
#: Column order of a NumPy array given to the library's entry points (``fit_physics``, ``Calibration.predict``,
#: ``Calibrator``, ``discover``): (n, 4) = the first four (no reference), (n, 7) = all seven.
ARRAY_COLUMNS = ("bx_meas", "by_meas", "bz_meas", "temperature", "bx_ref", "by_ref", "bz_ref")
#: Absolute zero in degrees Celsius: no temperature is below it.
ABSOLUTE_ZERO_C = -273.15
#: Run ids are stored as int64 and read as float64: above 2**53 distinct ids could merge.
_MAX_RUN_ID = 2**53
#: A temperature column whose median is above this is almost surely kelvin.
_KELVIN_THRESHOLD_C = 150.0
#: A column declared kelvin whose median lies below this after conversion (C; 93 K) held Celsius already.
_CELSIUS_AS_KELVIN_C = -180.0
#: Field units ``load_csv`` converts from, as the factor to microtesla.
FIELD_UNITS = {"uT": 1.0, "nT": 1e-3, "mT": 1e3, "G": 100.0}
#: Time units a file may declare, and their factor to seconds (loggers often stamp ms or us since boot).
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "min": 60.0, "h": 3600.0}


#: A median time step within runs outside this range (s) is named (:func:`time_step_warning`): a time column in ms or
#: us read as seconds is the likelier cause than a logger at 10 kHz or one row in 100 s.
PLAUSIBLE_STEP_S = (1e-4, 100.0)


def median_step(time, run=None) -> float | None:
    """The median positive sampling step (s) of ``time`` (with ``run``: between rows of the same run); None without
    one."""
    steps = np.diff(np.asarray(time, np.float64))
    if run is not None:
        run = np.asarray(run).reshape(-1)
        steps = steps[run[1:] == run[:-1]]
    steps = steps[np.isfinite(steps) & (steps > 0)]
    return float(np.median(steps)) if steps.size else None


def time_step_warning(data: "CalibrationData", declare: str = "[data] time_unit") -> str | None:
    """A warning when the rows' median time step within runs lies outside :data:`PLAUSIBLE_STEP_S` (the time column is
    read in seconds: a logger's ms or us stamps make every rate, lag time constant and correlation time 1000x off);
    None otherwise, or for rows without times. ``declare``: how the caller declares the unit."""
    if not getattr(data, "time_given", True):
        return None
    step = median_step(data.time, data.run)
    if not step or PLAUSIBLE_STEP_S[0] <= step <= PLAUSIBLE_STEP_S[1]:
        return None
    return (f"The rows' median time step within runs is {step:.4g} s ({1 / step:.3g} rows per second): the time column "
            f"is read in seconds, so if it holds ms or us (as many loggers stamp), every rate, lag time constant and "
            f"correlation time is off by 1000x or more. Declare its unit ({declare} = \"ms\" or \"us\"), or ignore "
            f"this if the rows really are that far apart.")


def time_in_seconds(time, time_unit: str = "s"):
    """``time`` (or None) in seconds from the declared ``time_unit`` (one of :data:`TIME_UNITS`; else DataError)."""
    if time_unit not in TIME_UNITS:
        raise DataError(f"time_unit is {time_unit!r}; it must be one of {list(TIME_UNITS)}.")
    return None if time is None else np.asarray(time, dtype=np.float64) * TIME_UNITS[time_unit]
#: Without a training domain, a field whose 99th percentile |component| lies outside this range (uT) is in
#: the wrong unit: the Earth's field is 25-65 uT and calibration coils reach a few hundred uT, i.e.
#: 25 000-65 000 in nT (above the range) but 0.025-0.065 in mT and 0.25-0.65 in gauss (below it).
_PLAUSIBLE_P99_UT = (1.0, 2000.0)
#: No magnetometer reading (uT) or temperature (C) has a magnitude above these; larger values are corrupt.
_MAX_ABS = {"field": 1e6, "temperature": 1e4}


class DataError(ValueError):
    """Bad input data: the message names the row/column and the fix."""


class DataNote(UserWarning):
    """Something bayesmag did to the input on the user's behalf (e.g. ignored an unused text column)."""


class CalibrationWarning(UserWarning):
    """A calibration was computed but should not be trusted without reading this (too few rows for its
    parameters, a temperature span too small for the thermal terms, no between-session term). The command line
    prints each as a WARNING line and keeps it in ``metrics.json``; the library raises it once per run."""


def user_stacklevel() -> int:
    """``stacklevel`` for :func:`warnings.warn`, called from the function that warns: the first frame outside the
    bayesmag package, so the warning names the user's line, not the library's."""
    import os
    import sys
    pkg = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))   # .../bayesmag
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(pkg + os.sep):
        frame, level = frame.f_back, level + 1
    return level


@dataclasses.dataclass(frozen=True)
class CalibrationData:
    """One calibration recording (or a subset of one).

    Attributes:
      b_meas: (n, 3) measured field of the device under test, uT.
      temperature: (n,) sensor temperature, degrees C.
      b_ref: (n, 3) reference field, uT, or ``None`` when the recording has no
        reference (the normal case when applying a calibration in the field).
      time: (n,) seconds.
      run: (n,) integer run (campaign) id (|id| < 2**53).
      source: a short description of where the rows came from.
      field_unit: the field unit the user declared at load (values are converted to uT), or ``None``
        when none was declared: entry points then check that the values look like uT
        (:func:`check_units`); a declared unit is trusted (e.g. a genuine low-field session).
      time_given: whether the rows came with times (default: ``time`` was given); without, ``time`` is the row
        index and nothing that needs seconds (the rate checks of the training domain) reads it.

    Example:
      >>> d = CalibrationData(np.zeros((2, 3)), np.array([20.0, 21.0]), np.zeros((2, 3)))
      >>> d.n
      2
    """

    b_meas: np.ndarray
    temperature: np.ndarray
    b_ref: np.ndarray | None
    time: np.ndarray | None = None
    run: np.ndarray | None = None
    source: str = ""
    field_unit: str | None = None
    time_given: bool | None = None

    def __post_init__(self):
        b = np.asarray(self.b_meas, dtype=np.float64)
        n = b.shape[0] if b.ndim == 2 else -1
        if b.ndim != 2 or b.shape[1] != 3:
            raise DataError(f"b_meas must have shape (n, 3); got {b.shape}.")
        t = np.asarray(self.temperature, dtype=np.float64).reshape(-1)
        if t.shape[0] != n:
            raise DataError(f"temperature has {t.shape[0]} rows but b_meas has {n}.")
        ref = None
        if self.b_ref is not None:
            ref = np.asarray(self.b_ref, dtype=np.float64)
            if ref.shape != (n, 3):
                raise DataError(f"b_ref must have shape ({n}, 3); got {ref.shape}.")
        time = (
            np.arange(n, dtype=np.float64)
            if self.time is None
            else np.asarray(self.time, dtype=np.float64).reshape(-1)
        )
        object.__setattr__(self, "time_given", self.time is not None if self.time_given is None
                           else bool(self.time_given))
        run = np.zeros(n, dtype=np.int64) if self.run is None else _run_ids(self.run)
        if time.shape[0] != n or run.shape[0] != n:
            raise DataError(f"time and run must have {n} rows.")
        for name, arr in (("b_meas", b), ("temperature", t), ("b_ref", ref), ("time", time), ("run", run)):
            if arr is not None:
                arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def n(self) -> int:
        return int(self.b_meas.shape[0])

    @property
    def has_reference(self) -> bool:
        return self.b_ref is not None

    @property
    def runs(self) -> np.ndarray:
        return np.unique(self.run)

    def subset(self, idx: np.ndarray) -> "CalibrationData":
        """Rows ``idx`` (a boolean mask or integer indices), in that order."""
        idx = np.asarray(idx)
        return CalibrationData(
            self.b_meas[idx],
            self.temperature[idx],
            None if self.b_ref is None else self.b_ref[idx],
            self.time[idx],
            self.run[idx],
            self.source,
            self.field_unit,
            self.time_given,
        )

    def __repr__(self) -> str:
        ref = "with reference" if self.b_ref is not None else "no reference"
        src = f", source={self.source!r}" if self.source else ""
        return f"CalibrationData(n={self.n}, runs={self.runs.size}, {ref}{src})"


def _run_ids(run) -> np.ndarray:
    """(n,) int64 run ids; ids that are not integers or beyond 2**53 are refused (they would merge)."""
    r = np.asarray(run).reshape(-1)
    if r.dtype.kind in "iu":
        big = np.abs(r.astype(np.float64)) >= _MAX_RUN_ID
    elif r.dtype.kind in "fb":
        rf = r.astype(np.float64)
        if not np.isfinite(rf).all():
            raise DataError(f"Column 'run' has non-finite values at {_bad_rows(~np.isfinite(rf))}.")
        if np.any(rf != np.round(rf)):
            raise DataError(f"Column 'run' must hold integers; {_bad_rows(rf != np.round(rf))} do not.")
        big = np.abs(rf) >= _MAX_RUN_ID
    else:
        raise DataError(f"Column 'run' must hold integers; got {r.dtype} values.")
    if big.any():
        i = int(np.flatnonzero(big)[0])
        raise DataError(f"Column 'run' holds {r[i]} at {_bad_rows(big)}: run ids must lie within +-2**53 "
                        f"({_MAX_RUN_ID}), beyond which distinct ids merge into one run. Renumber the runs "
                        f"(e.g. 1, 2, 3, ...).")
    return r.astype(np.int64)


# --------------------------------------------------------------------------- validation


def _bad_rows(mask: np.ndarray, limit: int = 5) -> str:
    rows = np.flatnonzero(mask)
    shown = ", ".join(str(int(r) + 1) for r in rows[:limit])
    more = f" and {rows.size - limit} more" if rows.size > limit else ""
    return f"data row(s) {shown}{more}"


def _columns(data: CalibrationData) -> dict[str, np.ndarray]:
    cols = {"bx_meas": data.b_meas[:, 0], "by_meas": data.b_meas[:, 1], "bz_meas": data.b_meas[:, 2],
            "temperature": data.temperature, "time": data.time}
    if data.b_ref is not None:
        cols.update({c: data.b_ref[:, i] for i, c in enumerate(_REF)})
    return cols


def check_values(data: CalibrationData, *, origin: str = "", allow_nonfinite: bool = False) -> None:
    """Refuse non-finite values (unless ``allow_nonfinite``) and absurd magnitudes, naming the column and rows.

    Absurd: |field| > 1e6 uT (1 T) or |temperature| > 1e4 C; such a value is corrupt, not a reading.
    """
    where = f" in {origin}" if origin else ""
    for name, col in _columns(data).items():
        bad = ~np.isfinite(col)
        if bad.any() and not allow_nonfinite:
            raise DataError(
                f"Column '{name}'{where} has {int(bad.sum())} non-finite value(s) (NaN or inf) at "
                f"{_bad_rows(bad)}. Remove or repair those rows before calibrating."
            )
        limit = _MAX_ABS["temperature"] if name == "temperature" else _MAX_ABS["field"] if name != "time" else None
        if limit is not None:
            huge = np.isfinite(col) & (np.abs(np.where(np.isfinite(col), col, 0.0)) > limit)
            if huge.any():
                r = int(np.flatnonzero(huge)[0])
                raise DataError(
                    f"Column '{name}'{where} holds {col[r]:.6g} at {_bad_rows(huge)}: no "
                    f"{'temperature (C)' if name == 'temperature' else 'field (uT)'} is that large "
                    f"(|value| > {limit:.0e}). The value is corrupt; repair or remove those rows."
                )
        if name == "temperature":
            cold = np.isfinite(col) & (np.where(np.isfinite(col), col, 0.0) < ABSOLUTE_ZERO_C)
            if cold.any():
                r = int(np.flatnonzero(cold)[0])
                raise DataError(
                    f"Column 'temperature'{where} holds {col[r]:.6g} C at {_bad_rows(cold)}, below absolute zero "
                    f"({ABSOLUTE_ZERO_C} C): the value is corrupt or in another unit. Repair or remove those rows "
                    f"(temperatures are read in Celsius, or kelvin with temperature_unit = \"K\")."
                )


def kelvin_to_celsius(t, where: str = "") -> np.ndarray:
    """``t`` (kelvin, as declared) in Celsius; a declared kelvin column whose median is below
    :data:`_CELSIUS_AS_KELVIN_C` after conversion held Celsius already (read as -250 C before: every row out of domain,
    nothing naming the cause), refused naming the column and the fix."""
    c = np.asarray(t, dtype=np.float64) - 273.15
    f = c[np.isfinite(c)]
    if f.size and float(np.median(f)) < _CELSIUS_AS_KELVIN_C:
        m = float(np.median(f))
        raise DataError(f"Column 'temperature'{where} was declared kelvin (temperature_unit K), but its median "
                        f"{m + 273.15:.4g} K would be {m:.4g} C: the values look like Celsius already. Drop the kelvin "
                        f"declaration (--temperature-unit, [data] temperature_unit, temperature_unit=).")
    return c


def check_field_unit(data: CalibrationData, *, train_max_ut: float | None = None, origin: str = "",
                     fix: str = "Convert the field columns to uT", declare: str = "--field-unit uT",
                     extra_fields: Sequence[tuple[str, np.ndarray]] = (), small_ok: bool = False,
                     train_noise_ut: float | None = None) -> list[str]:
    """Refuse a field that is not in microtesla; return warnings for a suspicious one.

    With ``train_max_ut`` (the largest |B| a calibration was trained on, ``apply``): a 99th
    percentile |component| above 50x that is nT, below 1/50 of it mT or gauss (both refused; a genuinely
    weak field, e.g. a shielded recording, is declared with ``field_unit="uT"``). Without it (``run``, ``discover``): the 99th percentile must lie in
    :data:`_PLAUSIBLE_P99_UT`; above is nT, below is mT or gauss (both refused). Measured and
    reference columns are checked alike (the reference against the training range too). A field that is
    zero in every row is refused as such. A unit the user declared at load (``data.field_unit``, e.g.
    ``--field-unit uT`` for a genuine low-field session) is trusted: only the all-zero check runs.
    ``extra_fields``: more ``(label, (n, k) array)`` groups in the same unit, checked alike (a field
    calibration's scalar reference column). ``small_ok``: skip the mT / gauss test against ``train_max_ut`` (a part
    of a recording, e.g. one Dask partition of a near-zero-field run, says nothing about the whole's unit; the
    caller checks the whole). ``train_noise_ut``: the calibration's input-noise sd (uT); rows whose own
    row-to-row noise is within 30x of it are in uT whatever their size (in mT or gauss the noise shrinks with the
    field, 1000x or 100x), so a genuinely weak field (Belsten run 1: 0.69 uT) is not refused as mT.
    """
    where = f" in {origin}" if origin else ""
    weak_ut = train_noise_ut is not None and _row_noise(data) > train_noise_ut / 30
    groups = [("measured field (bx_meas, by_meas, bz_meas)", data.b_meas)]
    if data.b_ref is not None:
        groups.append(("reference field (bx_ref, by_ref, bz_ref)", data.b_ref))
    groups += list(extra_fields)
    warn = []
    for label, b in groups:
        ok = np.isfinite(b).all(axis=1)
        if not ok.any():
            if label.startswith("reference") and train_max_ut is not None:
                continue                    # apply: reference columns are optional extras
            raise DataError(f"No row{where} has a finite {label}.")
        p99 = float(np.percentile(np.abs(b[ok]), 99))
        if p99 == 0.0 and not np.any(b[ok]):
            raise DataError(f"The {label}{where} is zero in every row: the sensor recorded no field (or the "
                            f"columns are mapped wrongly). Check the file and the column mapping.")
        if data.field_unit is not None:     # declared by the user: trusted, but said when training disagrees
            if train_max_ut is not None and train_max_ut > 10 and not small_ok and (
                    p99 < train_max_ut / 50 or p99 > 50 * train_max_ut):
                warn.append(f"The {label}{where}, read as {data.field_unit!r} as declared, reaches {p99:.4g} uT "
                            f"(99th percentile) while the calibration was trained on |B| up to {train_max_ut:.3g} "
                            f"uT: if the file is in another unit (uT already?), the calibrated values are wrong by "
                            f"that factor. Check the declared field unit.")
            continue
        if train_max_ut is not None:
            if p99 > 50 * train_max_ut:
                raise DataError(f"The {label}{where} reaches {p99:.4g} (99th percentile) but the calibration was "
                                f"trained on |B| up to {train_max_ut:.3g} uT: the file looks like nT (x1000). {fix}.")
            if train_max_ut > 10 and p99 < train_max_ut / 50 and not small_ok and not weak_ut:
                what = ("its RMSE would be meaningless" if label.startswith("reference") else
                        "every calibrated value would be wrong")
                raise DataError(f"The {label}{where} is at most {p99:.3g} (99th percentile) while the calibration "
                                f"was trained on |B| up to {train_max_ut:.3g} uT: the file looks like mT "
                                f"(/1000) or gauss (/100); {what}. Convert it to uT, or {declare} if it really is "
                                f"(e.g. a magnetically shielded recording).")
            continue
        lo, hi = _PLAUSIBLE_P99_UT
        if p99 > hi and b.shape[1] == 3:
            per = np.percentile(np.abs(b[ok]), 99, axis=0)
            names = [c.strip() for c in label[label.index("(") + 1:label.index(")")].split(",")] if "(" in label \
                else ["x", "y", "z"]
            if int((per > hi).sum()) == 1 and (per[per <= hi] >= lo).all():     # one column alone out of range
                k = int(np.argmax(per))
                rest = " and ".join(f"{n} {v:.3g}" for n, v in zip(names, per) if v <= hi)
                raise DataError(f"In the {label}{where}, {names[k]} reaches {per[k]:.4g} (99th percentile of |value|) "
                                f"while {rest} look like microtesla: either that one column is corrupt, offset or "
                                f"mapped to the wrong column (check it), or the whole file is in nT with the field "
                                f"held along that axis ({fix} (divide by 1000), or declare {declare.replace('uT', 'nT')}).")
        if p99 > hi:
            raise DataError(f"The {label}{where} reaches {p99:.4g} (99th percentile of |component|), but bayesmag "
                            f"expects microtesla and a calibration field is at most a few hundred uT: the file looks "
                            f"like nT (x1000). {fix} (divide by 1000).")
        if p99 < lo:
            raise DataError(f"The {label}{where} stays below {p99:.3g} (99th percentile of |component|), but "
                            f"bayesmag expects microtesla (the Earth's field is 25-65 uT): the file looks like mT "
                            f"(x1000) or gauss (x100). {fix}; or, for a genuine low-field recording in uT, "
                            f"declare the unit with {declare}.")
    return warn


def second_difference_sd(x, run, min_rows: int = 1, time=None) -> np.ndarray | None:
    """Per column of ``x`` (n, k), the white-noise sd from second differences of consecutive rows of one run:
    ``1.4826 * MAD(d2) / sqrt(6)`` (``Var(x[t+1] - 2x[t] + x[t-1]) = 6 s^2`` for white noise); rows with a non-finite
    value are left out. None with fewer than ``min_rows`` differences.

    With ``time`` (n,), the rows are taken in time order within each run and only triples of rows *adjacent in the
    recording* count: both steps positive and at most 1.5x the run's median step. A subset of a recording (the
    training rows of a random split) otherwise differences across the rows it lacks, where a sweep's slope no longer
    cancels (``x[t+1] - 2x[t] + x[t-1]`` is ``slope * (h2 - h1)`` for unequal steps): Belsten's random 90/10 split read
    0.0056 / 0.0140 / 0.0060 uT against 0.0046 / 0.0119 / 0.0051 from all rows. Where fewer than 20 such triples
    remain, all consecutive triples are used, as without ``time``.

    Example:
      >>> rng = np.random.default_rng(0); t = np.arange(4000.0); x = (0.05 * t + rng.normal(0, 0.01, t.size))[:, None]
      >>> keep = np.sort(rng.choice(t.size, 3600, replace=False))            # a random 90 % of the rows
      >>> bool(second_difference_sd(x[keep], np.zeros(3600), time=t[keep])[0] < 0.0105)
      True
      >>> bool(second_difference_sd(x[keep], np.zeros(3600))[0] > 0.0115)  # differenced across the gaps: +24 %
      True
    """
    x, run = np.asarray(x, np.float64), np.asarray(run).reshape(-1)
    if x.shape[0] < 3:
        return None
    adjacent = None
    if time is not None:
        t = np.asarray(time, np.float64).reshape(-1)
        order = np.lexsort((t, run))
        x, run, t = x[order], run[order], t[order]
        h = np.diff(t)
        within = run[1:] == run[:-1]
        step = np.full(h.size, np.nan)
        for r in np.unique(run[1:][within]):
            m = within & (run[1:] == r)
            pos = h[m][h[m] > 0]
            if pos.size:
                step[m] = np.median(pos)
        ok = within & (h > 0) & (h <= 1.5 * step)
        adjacent = ok[1:] & ok[:-1]
    same = (run[2:] == run[1:-1]) & (run[1:-1] == run[:-2])
    if adjacent is not None and np.sum(adjacent & same) >= 20:
        same = same & adjacent
    d2 = (x[2:] - 2 * x[1:-1] + x[:-2])[same]
    d2 = d2[np.isfinite(d2).all(axis=1)]
    if d2.shape[0] < max(min_rows, 1):
        return None
    med = np.median(d2, axis=0)
    return 1.4826 * np.median(np.abs(d2 - med), axis=0) / np.sqrt(6.0)


def _row_noise(data: CalibrationData) -> float:
    """The measured field's row-to-row noise sd (uT as read), median over the axes (:func:`second_difference_sd`);
    0 with fewer than 20 second differences."""
    sd = second_difference_sd(data.b_meas, data.run, min_rows=20)
    return 0.0 if sd is None else float(np.median(sd))


def check_units(data: CalibrationData, *, train_max_ut: float | None = None, origin: str = "",
                fix: str = "Convert the field columns to uT", declare: str = "--field-unit uT",
                temperature_fix: str = "Set [data] temperature_unit = \"K\" (or subtract 273.15)",
                extra_fields: Sequence[tuple[str, np.ndarray]] = (), small_ok: bool = False,
                train_noise_ut: float | None = None) -> list[str]:
    """The one unit check of every entry point (``run``, ``apply``, ``discover`` and the library's
    ``fit_physics``, ``Calibration.predict``, ``Calibrator``, ``discover``).

    Field in uT (:func:`check_field_unit`; nT, mT and gauss refused unless declared), temperature in
    Celsius (a median above 150 C is kelvin: refused), nothing below absolute zero. Returns
    warnings (suspicious, not refused); raises :class:`DataError` naming the column and the fix.
    ``fix``/``declare``/``temperature_fix`` word the remedy for the caller (a CLI flag or an argument).
    """
    where = f" in {origin}" if origin else ""
    warn = check_field_unit(data, train_max_ut=train_max_ut, origin=origin, fix=fix, declare=declare,
                            extra_fields=extra_fields, small_ok=small_ok, train_noise_ut=train_noise_ut)
    t = data.temperature[np.isfinite(data.temperature)]
    if t.size:
        med = float(np.median(t))
        if med > _KELVIN_THRESHOLD_C:
            raise DataError(f"Column 'temperature'{where} has median {med:.2f}, which looks like kelvin, but "
                            f"Celsius is expected. {temperature_fix}.")
        if t.min() < ABSOLUTE_ZERO_C:
            bad = np.isfinite(data.temperature) & (np.nan_to_num(data.temperature) < ABSOLUTE_ZERO_C)
            raise DataError(f"Column 'temperature'{where} is below absolute zero ({ABSOLUTE_ZERO_C} C) at "
                            f"{_bad_rows(bad)}: the value is corrupt or in another unit. Repair those rows.")
    return warn


def _check_time(data: CalibrationData, where: str, *, duplicates: bool, order: bool) -> None:
    """Within each run: rows in time order (if ``order``), no repeated timestamp after sorting (if ``duplicates``)."""
    for r in np.unique(data.run):
        sel = np.flatnonzero(data.run == r)
        t = data.time[sel]
        if order:
            back = np.flatnonzero(np.diff(t) < 0)
            if back.size:
                i = sel[back[0] + 1]
                raise DataError(
                    f"Column 'time'{where} is not sorted within run {int(r)}: data row {i + 1} (time {data.time[i]:.6g}) "
                    f"comes after data row {i} (time {data.time[i - 1]:.6g}). Sort the file by run, then time."
                )
        if duplicates:
            o = np.argsort(t, kind="stable")
            same = np.diff(t[o]) == 0
            if same.any():
                dup = np.zeros(data.n, dtype=bool)
                dup[sel[o[1:][same]]] = True
                first = np.zeros(data.n, dtype=bool)
                first[sel[o[:-1][same]]] = True
                raise DataError(
                    f"Column 'time'{where} has duplicated timestamps within run {int(r)} at {_bad_rows(dup)} "
                    f"(same time as {_bad_rows(first)}). Give each row a distinct time (or distinct 'run' ids "
                    f"for separate recordings)."
                )


def spread_duplicate_times(data: CalibrationData) -> CalibrationData:
    """Rows of a run that share a timestamp spread evenly up to the run's next distinct stamp.

    A stamp held by k rows becomes ``t, t + d/k, ..., t + (k-1) d/k`` with d the gap to the next
    stamp (the median gap after the last one): e.g. whole-second stamps at 4 Hz become quarter
    seconds, as :func:`load_belsten` does. Row order is kept; other rows are unchanged.

    Example:
      >>> d = CalibrationData(np.ones((4, 3)) * 40, np.full(4, 20.0), None, time=[0, 0, 1, 1])
      >>> spread_duplicate_times(d).time.tolist()
      [0.0, 0.5, 1.0, 1.5]
    """
    time = np.array(data.time, dtype=np.float64)
    for r in np.unique(data.run):
        sel = np.flatnonzero(data.run == r)
        o = np.argsort(time[sel], kind="stable")
        ts = time[sel][o]
        uniq, start, counts = np.unique(ts, return_index=True, return_counts=True)
        if counts.max(initial=1) == 1:
            continue
        last_gap = float(np.median(np.diff(uniq))) if uniq.size > 1 else 1.0
        step = (np.append(uniq[1:], uniq[-1] + last_gap) - uniq) / counts
        rank = np.arange(ts.size) - np.repeat(start, counts)
        new = np.empty_like(ts)
        new[o] = ts + rank * np.repeat(step, counts)
        time[sel] = new
    return dataclasses.replace(data, time=time)


def validate(
    data: CalibrationData,
    *,
    n_params: int = 8,
    need_reference: bool = True,
    need_temperature_variation: bool = True,
    allow_duplicate_times: bool = False,
    origin: str = "",
    extra_fields: Sequence[tuple[str, np.ndarray]] = (),
) -> None:
    """Check a recording before fitting; raise :class:`DataError` naming what is wrong.

    Checks: non-finite or absurdly large values (row and column), missing reference, field
    units (:func:`check_field_unit`), enough rows for ``n_params`` parameters, temperature in
    kelvin, constant temperature (temperature terms not identifiable), duplicated timestamps
    within a run (after sorting by time). ``extra_fields``: more field groups in the readings' unit
    (:func:`check_field_unit`).
    Row numbers in messages count data rows from 1 (the header is not counted).
    """
    where = f" in {origin}" if origin else ""
    check_values(data, origin=origin)
    if need_reference and data.b_ref is None:
        raise DataError(f"The recording{where} has no reference columns {_REF}; a calibration needs them.")
    check_units(data, origin=origin, declare="[data] field_unit = \"uT\" (or --field-unit uT)",
                extra_fields=extra_fields)
    if data.n < n_params + 1:
        raise DataError(
            f"The recording{where} has {data.n} rows but the physics model has {n_params} parameters per axis; "
            f"at least {n_params + 1} rows are needed (many more for a useful calibration)."
        )
    if need_temperature_variation and float(np.ptp(data.temperature)) < 1e-6:
        raise DataError(
            f"Column 'temperature'{where} does not vary (all rows {data.temperature[0]:.3f} C): the temperature "
            f"terms Ks and Ko are not identifiable. Set [physics] temperature_terms = false to fit S and O only."
        )
    if not allow_duplicate_times:
        _check_time(data, where, duplicates=True, order=False)


def check_time_order(data: CalibrationData, reasons, *, origin: str = "") -> None:
    """Rows in time order within each run, where something takes them so (``reasons``: what, e.g. "the time-block
    split"); nothing to check without a reason. Raises :class:`DataError` naming the first row out of order."""
    reasons = [r for r in reasons if r]
    if not reasons:
        return
    where = f" in {origin}" if origin else ""
    try:
        _check_time(data, where, duplicates=False, order=True)
    except DataError as e:
        raise DataError(f"{e} (Needed in time order by: {'; '.join(reasons)}.)") from None


def validate_for_discover(data: CalibrationData, *, origin: str = "", time_available: bool | None = None) -> None:
    """The checks ``discover`` needs before it starts: finite, plausible values in uT and Celsius, rows sorted
    by time within each run and, unless ``time_available`` is False, no timestamp repeated within a run (the
    time-domain candidates -- lags, steps, drifts, periodicity -- read the stamps; ``run`` refuses repeats too).
    Raises :class:`DataError` naming the row and column."""
    origin = origin or data.source
    where = f" in {origin}" if origin else ""
    check_values(data, origin=origin)
    check_units(data, origin=origin, declare="[data] field_unit = \"uT\" (or --field-unit uT)")
    _check_time(data, where, duplicates=time_available is not False, order=True)


# --------------------------------------------------------------------------- loaders


_DELIMITERS = {",": "comma", ";": "semicolon", "\t": "tab"}


def _sniff_delimiter(path: Path, header_line: str, data_line: str) -> str:
    """The one of ``, ; tab`` that splits the header and the first data row into the same number of fields.

    A single-column file reads as comma-separated. When two candidates fit, the error names both.
    """
    fits = [d for d in _DELIMITERS if header_line.count(d) > 0
            and (not data_line.strip() or data_line.count(d) == header_line.count(d))]
    if len(fits) == 1:
        return fits[0]
    if not fits:
        if not any(d in header_line for d in _DELIMITERS):
            return ","
        used = [_DELIMITERS[d] for d in _DELIMITERS if d in header_line]
        raise DataError(f"{path}: the header and the first data row split into different numbers of fields with "
                        f"every delimiter bayesmag reads ({', '.join(used)} found in the header). Write the file "
                        f"with one delimiter: comma, semicolon or tab.")
    names = " and ".join(_DELIMITERS[d] for d in fits)
    raise DataError(f"{path}: cannot tell the delimiter: both {names} split the header and the first data row "
                    f"consistently. Write the file comma-separated (with '.' as the decimal point).")


def _decode(path: Path, raw: bytes, *, note: bool = True) -> str:
    """``raw`` as text: UTF-8 (a byte-order mark removed); else Latin-1 with a :class:`DataNote` naming the
    line of the first non-UTF-8 byte. A NUL byte means a binary file: refused."""
    if b"\x00" in raw[:65536]:
        if raw[:4] == b"PAR1":
            raise DataError(f"{path} is a Parquet file without the .parquet suffix; rename it to .parquet (Parquet is "
                            f"read by its suffix) or write it as a CSV with a header row.")
        raise DataError(f"{path} is not a text file (it holds NUL bytes); expected a CSV with a header row.")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw[:e.start].count(b"\n") + 1
        import warnings
        if note:
            warnings.warn(DataNote(f"{path}: line {line} holds the byte 0x{raw[e.start]:02x}, which is not UTF-8; "
                                   f"the file was read as Latin-1 (save it as UTF-8 to silence this note)."),
                          stacklevel=4)
        return raw.decode("latin-1")


def _header(path: Path, first: str, delim: str) -> list[str]:
    """The header row's names (quotes and blanks removed); two columns of one name are refused, naming both."""
    try:
        header = [h.strip().strip('"').strip() for h in next(csv.reader([first], delimiter=delim))]
    except (csv.Error, StopIteration) as e:
        raise DataError(f"{path}: the header row cannot be read ({e}); write one header line of column names.") \
            from None
    seen: dict[str, int] = {}
    for j, h in enumerate(header):
        if h and h in seen:
            raise DataError(f"{path}: the header names column '{h}' twice (column {seen[h] + 1} and column {j + 1}); "
                            f"bayesmag cannot tell which one holds the data. Rename or remove one of them.")
        seen[h] = j
    return header


def _read_table(path: Path, wanted: set[str] | None = None) -> tuple[list[str], np.ndarray]:
    """Read a delimited file (comma, semicolon or tab; sniffed) with a header row into (header, float array).

    A UTF-8 byte-order mark is removed; a file that is not UTF-8 is read as Latin-1 (a note says so).
    Fast path: ``numpy.loadtxt``; on any irregularity the row-by-row reader below names the row and
    column at fault. Columns outside ``wanted`` (all wanted when None) that hold text are ignored
    (NaN) with a :class:`DataNote`; a wanted one is refused naming the row.
    """
    if path.is_dir():
        raise DataError(f"{path} is a folder; expected a CSV file.")
    with open(path, "rb") as f:
        head = f.readline() + f.readline()
    head_text = _decode(path, head, note=False) if head else ""     # the whole file's decode below notes it
    lines = head_text.split("\n")
    first = lines[0].rstrip("\r")
    second = lines[1].rstrip("\r") if len(lines) > 1 else ""
    delim = _sniff_delimiter(path, first, second)
    header = _header(path, first, delim) if first.strip() else []
    if not header:
        raise DataError(f"{path} is empty; expected a header row and data rows.")
    try:
        import warnings
        with warnings.catch_warnings():     # a header without rows: our own one-line error below, not numpy's warning
            warnings.filterwarnings("ignore", message="loadtxt: input contained no data")
            arr = np.loadtxt(path, delimiter=delim, skiprows=1, ndmin=2, dtype=np.float64, encoding="utf-8-sig")
        if arr.shape[0] > 0 and arr.shape[1] == len(header):
            return header, arr
    except (ValueError, UnicodeDecodeError):
        pass
    import io

    text = _decode(path, path.read_bytes())
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delim)
    rows: list[list[str]] = []
    try:
        next(reader)
        for i, row in enumerate(reader, start=1):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise DataError(
                    f"{path}: data row {i} has {len(row)} fields but the header has {len(header)} "
                    f"({_DELIMITERS[delim]}-separated)."
                )
            rows.append(row)
    except csv.Error as e:
        raise DataError(f"{path}: line {reader.line_num} cannot be read as CSV ({e}): a field that long usually "
                        f"means an unbalanced quote (\") joined many lines into one field. Repair the quotes on or "
                        f"before that line.") from None
    if not rows:
        raise DataError(f"{path} has a header but no data rows.")
    cols = []
    for j, name in enumerate(header):
        col = np.empty(len(rows))
        for k, row in enumerate(rows):
            c = row[j].strip()
            try:
                col[k] = float(c) if c else np.nan
            except ValueError:
                if wanted is not None and name not in wanted:
                    import warnings
                    warnings.warn(DataNote(f"{path}: column '{name}' holds text (data row {k + 1}: {c[:40]!r}); "
                                           f"bayesmag does not use it and ignored it."), stacklevel=3)
                    col[:] = np.nan
                    break
                hint = (" Decimal commas are not read: use '.' as the decimal point."
                        if "," in c and delim != "," else
                        " An unbalanced quote (\") joined lines into this field; repair the quotes."
                        if '"' in row[j] or "\n" in row[j] else "")
                raise DataError(
                    f"{path}: data row {k + 1}, column '{name}' holds {c[:60]!r}, which is not a number.{hint}"
                ) from None
        cols.append(col)
    return header, np.column_stack(cols)


def column_mapping(columns: Mapping[str, str] | None, *, field_unit: str = "uT", temperature_unit: str = "C",
                   what: str = "columns") -> dict[str, str]:
    """Check the units and return the canonical -> source column mapping (unmapped names map to themselves).

    Raises :class:`DataError` naming an unknown unit or canonical name (``what``: how the caller
    calls the mapping, e.g. ``[data.columns]``) and the valid set.
    """
    if temperature_unit not in ("C", "K"):
        raise DataError(f"temperature_unit is {temperature_unit!r}; it must be one of ['C', 'K'].")
    if field_unit not in FIELD_UNITS:
        raise DataError(f"field_unit is {field_unit!r}; it must be one of {list(FIELD_UNITS)}.")
    mapping = {c: c for c in CANONICAL_COLUMNS}
    if columns:
        unknown = set(columns) - set(CANONICAL_COLUMNS)
        if unknown:
            raise DataError(f"{what} names unknown canonical column(s) {sorted(unknown)}; "
                            f"valid: {list(CANONICAL_COLUMNS)}.")
        mapping.update(columns)
    return mapping


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def load_csv(
    path: str | Path,
    *,
    columns: Mapping[str, str] | None = None,
    temperature_unit: str = "C",
    field_unit: str | None = None,
    require_reference: bool = True,
    time_unit: str = "s",
    mapping_hint: str = "a [data.columns] mapping",
) -> CalibrationData:
    """Load a canonical CSV (``time,run,bx_meas,by_meas,bz_meas,temperature,bx_ref,by_ref,bz_ref``).

    Args:
      path: the file.
      columns: optional mapping canonical name -> the file's column name, for other layouts.
      temperature_unit: ``"C"`` or ``"K"`` (kelvin is converted to Celsius).
      field_unit: one of :data:`FIELD_UNITS` (``uT``, ``nT``, ``mT``, ``G``), converted to uT and trusted
        (recorded as ``data.field_unit``); ``None`` (default): uT, checked by :func:`check_units`.
      require_reference: if False, the ``*_ref`` columns may be absent.
      time_unit: the ``time`` column's unit, one of :data:`TIME_UNITS` (converted to seconds).
      mapping_hint: how the caller maps columns, for the missing-column message (``apply``: its ``--columns``).

    ``run`` is optional (all rows one run); ``time`` is optional (row index). The delimiter
    (comma, semicolon or tab) is sniffed from the header and first row; a quoted header is read.
    Two columns of one name are refused; a text column the mapping does not use is ignored with
    a :class:`DataNote` warning.
    """
    path = Path(path)
    if not path.exists():
        where = ("" if path.is_absolute() else f" (looked for {path.resolve()}; a config's relative [data] path is "
                                               f"read from the current folder, then from the config file's folder)")
        raise DataError(f"Data file {path} does not exist{where}.")
    declared = field_unit
    field_unit = field_unit or "uT"
    mapping = column_mapping(columns, field_unit=field_unit, temperature_unit=temperature_unit,
                             what="[data.columns]")
    if path.is_dir():
        raise DataError(f"Data file {path} is a folder; expected a CSV file.")
    header, arr = _read_table(path, wanted=set(mapping.values()))
    idx = {h: i for i, h in enumerate(header)}

    def col(name: str, required: bool) -> np.ndarray | None:
        src = mapping[name]
        if src not in idx:
            if required:
                hint = f" (mapped from '{name}')" if src != name else ""
                if header and all(_is_number(h) for h in header):
                    raise DataError(f"{path} has no header row: its first line holds numbers ({', '.join(header[:4])}"
                                    f"{', ...' if len(header) > 4 else ''}). Add the header line "
                                    f"{','.join(CANONICAL_COLUMNS)} (in the file's own column order), or name "
                                    f"the columns with {mapping_hint} after adding a header.")
                extra = (". A recording without a temperature sensor: add a temperature column holding one constant "
                         "value (e.g. 25) and turn the temperature terms off (physics.temperature_terms = false; "
                         "measurement.temperature_terms = false for a field calibration)") if name == "temperature" else ""
                raise DataError(
                    f"{path} has no column '{src}'{hint}. Columns found: {header}. Expected the canonical header "
                    f"{','.join(CANONICAL_COLUMNS)} or {mapping_hint}{extra}."
                )
            return None
        return arr[:, idx[src]]

    b = np.stack([col(c, True) for c in _REQUIRED[:3]], axis=1) * FIELD_UNITS[field_unit]
    t = col("temperature", True)
    if temperature_unit == "K":
        t = kelvin_to_celsius(t, f" of {path}")
    refs = [col(c, require_reference) for c in _REF]
    if any(r is None for r in refs) and not all(r is None for r in refs):
        missing = [c for c, r in zip(_REF, refs) if r is None]
        raise DataError(f"{path} has some reference columns but not {missing}; give all three or none.")
    ref = None if refs[0] is None else np.stack(refs, axis=1) * FIELD_UNITS[field_unit]
    time = time_in_seconds(col("time", False), time_unit)
    run = col("run", False)
    try:
        run = None if run is None else _run_ids(run)
    except DataError as e:
        raise DataError(f"{path}: {e}") from None
    return CalibrationData(b, t, ref, time, run, source=str(path), field_unit=declared)


def load_column(path: str | Path, name: str, *, key: str = "the column", positive: bool = False,
                allow_nonfinite: bool = False) -> np.ndarray:
    """One extra numeric column of a CSV (e.g. a scalar magnetometer's magnitude), validated at load.

    Args:
      path: the file. name: the column's header. key: what named the column (for the message, e.g.
        ``"[measurement] scalar_column"``). positive: every value must be > 0 (a magnitude).
        allow_nonfinite: empty or non-finite cells come back as NaN (and are not checked) instead of an error.
    Raises :class:`DataError` naming the column, the row and the fix.
    """
    path = Path(path)
    if not path.exists():
        raise DataError(f"Data file {path} does not exist.")
    header, arr = _read_table(path)
    if name not in header:
        raise DataError(f"{path} has no column '{name}' (named by {key}); columns found: {header}. "
                        f"Set {key} to one of them.")
    v = arr[:, header.index(name)]
    bad = ~np.isfinite(v)
    if allow_nonfinite:
        v, bad = np.where(bad, np.nan, v), np.zeros_like(bad)
    if bad.any():
        raise DataError(f"{path}: column '{name}' (named by {key}) is empty or not finite at {_bad_rows(bad)}; "
                        "drop those rows or fill them.")
    if positive and np.any(v <= 0):         # NaN compares False: only finite values are checked
        i = int(np.flatnonzero(v <= 0)[0])
        raise DataError(f"{path}: column '{name}' (named by {key}) holds {v[i]:g} at data row {i + 1}: a field "
                        f"magnitude must be positive (uT); check the column and its unit.")
    return v


def _runs_from_gaps(time: np.ndarray, gap_s: float) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(np.diff(time) > gap_s)]).astype(np.int64) + 1


def _spread_quantised_times(time: np.ndarray) -> np.ndarray:
    """Spread rows that share an integer-second timestamp evenly inside that second."""
    out = time.astype(np.float64).copy()
    start = 0
    n = time.size
    while start < n:
        stop = start + 1
        while stop < n and time[stop] == time[start]:
            stop += 1
        k = stop - start
        out[start:stop] = time[start] + np.arange(k) / k
        start = stop
    return out


def load_belsten(path: str | Path, *, gap_s: float = 5.0) -> CalibrationData:
    """Load Belsten et al. (2023) ``full_data.csv`` (no header).

    Columns ``Time, refX, refY, refZ, testX, testY, testZ, Temp`` (Temp in kelvin,
    converted to C). Runs start at time gaps > ``gap_s`` seconds. Timestamps are whole
    seconds in the file (about four rows share each), so rows sharing a second are
    spread evenly inside it; ``time`` is then seconds since the first row.
    """
    path = Path(path)
    try:
        arr = np.loadtxt(path, delimiter=",", dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise DataError(f"{path} is not the Belsten 8-column numeric CSV: {e}") from None
    if arr.shape[1] != 8:
        raise DataError(f"{path} has {arr.shape[1]} columns; the Belsten file has 8 (Time, refX..Z, testX..Z, Temp).")
    t_raw = arr[:, 0]
    run = _runs_from_gaps(t_raw, gap_s)
    time = _spread_quantised_times(t_raw) - t_raw[0]
    return CalibrationData(
        b_meas=arr[:, 4:7],
        temperature=arr[:, 7] - 273.15,
        b_ref=arr[:, 1:4],
        time=time,
        run=run,
        source=f"belsten2023 ({path})",
    )


def write_csv(data: CalibrationData, path: str | Path) -> None:
    """Write ``data`` in the canonical CSV layout (reference columns only if present)."""
    cols = ["time", "run", "bx_meas", "by_meas", "bz_meas", "temperature"]
    parts = [data.time[:, None], data.run[:, None].astype(np.float64), data.b_meas, data.temperature[:, None]]
    if data.b_ref is not None:
        cols += list(_REF)
        parts.append(data.b_ref)
    mat = np.concatenate(parts, axis=1)
    fmt = ["%.6f", "%d"] + ["%.10g"] * (mat.shape[1] - 2)
    np.savetxt(path, mat, delimiter=",", header=",".join(cols), comments="", fmt=fmt)


# --------------------------------------------------------------------------- splits


@dataclasses.dataclass(frozen=True)
class Split:
    """Row indices of a train/test split and how it was made."""

    train: np.ndarray
    test: np.ndarray
    kind: str
    description: str

    def as_dict(self) -> dict:
        return {"kind": self.kind, "n_train": int(self.train.size), "n_test": int(self.test.size),
                "description": self.description}


def split_random(n: int, *, test_fraction: float, seed: int) -> Split:
    """Seeded random row split (the paper's protocol; flatters models on autocorrelated data)."""
    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"test_fraction is {test_fraction}; it must be in (0, 1).")
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n)
    n_test = max(1, int(round(test_fraction * n)))
    test, train = np.sort(perm[:n_test]), np.sort(perm[n_test:])
    return Split(train, test, "random", f"random {1 - test_fraction:.0%}/{test_fraction:.0%} row split, seed {seed}")


def split_by_run(run: np.ndarray, *, test_runs: Sequence[int]) -> Split:
    """Leave whole runs out: rows of ``test_runs`` are the test set."""
    runs = np.unique(run)
    if runs.size < 2:
        raise ValueError("split 'by_run' needs at least two runs; the data has one. Use 'random' or 'time_blocks'.")
    missing = [r for r in test_runs if r not in runs]
    if missing:
        raise ValueError(f"test_runs {missing} are not in the data; runs present: {runs.tolist()}.")
    test_mask = np.isin(run, list(test_runs))
    if test_mask.all():
        raise ValueError("split 'by_run' would leave no training rows; name fewer test_runs.")
    return Split(np.flatnonzero(~test_mask), np.flatnonzero(test_mask), "by_run",
                 f"leave-runs-out, test runs {list(test_runs)}")


def split_time_blocks(run: np.ndarray, *, test_fraction: float, n_blocks: int = 1, seed: int = 0) -> Split:
    """Hold out contiguous time blocks inside every run (interpolation without neighbour leak).

    In each run, ``n_blocks`` blocks covering ``test_fraction`` of its rows are held out,
    at seeded positions.
    """
    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"test_fraction is {test_fraction}; it must be in (0, 1).")
    rng = np.random.default_rng(seed)
    test = np.zeros(run.size, dtype=bool)
    for r in np.unique(run):
        rows = np.flatnonzero(run == r)
        m = rows.size
        block = max(1, int(round(test_fraction * m / n_blocks)))
        # Non-overlapping: choose block start slots on a grid of len m // n_blocks.
        slot = m // n_blocks
        for b in range(n_blocks):
            lo = b * slot
            hi = max(lo, lo + slot - block)
            s = int(rng.integers(lo, hi + 1))
            test[rows[s:s + block]] = True
    return Split(np.flatnonzero(~test), np.flatnonzero(test), "time_blocks",
                 f"{n_blocks} contiguous block(s) per run, {test_fraction:.0%} of rows held out, seed {seed}")


def make_split(data: CalibrationData, *, kind: str, test_fraction: float = 0.1, seed: int = 0,
               test_runs: Sequence[int] = (), n_blocks: int = 1) -> Split:
    """Dispatch on split ``kind`` in {'random', 'by_run', 'time_blocks', 'none'}."""
    if kind == "random":
        return split_random(data.n, test_fraction=test_fraction, seed=seed)
    if kind == "by_run":
        runs = list(test_runs) if test_runs else [int(data.runs[-1])]
        return split_by_run(data.run, test_runs=runs)
    if kind == "time_blocks":
        return split_time_blocks(data.run, test_fraction=test_fraction, n_blocks=n_blocks, seed=seed)
    if kind == "none":
        idx = np.arange(data.n)
        return Split(idx, idx, "none", "no split: fit and evaluate on all rows (in-sample)")
    raise ValueError(f"split kind {kind!r} is not known; it must be one of ['random', 'by_run', 'time_blocks', 'none'].")
