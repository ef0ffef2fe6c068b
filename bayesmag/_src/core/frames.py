"""pandas at the edges: DataFrame <-> :class:`~bayesmag.CalibrationData`, predictions as a DataFrame, Parquet.

Inside bayesmag everything stays NumPy/JAX; these functions convert at the boundary only.
Column names are the canonical CSV header (``time, run, bx_meas, by_meas, bz_meas,
temperature, bx_ref, by_ref, bz_ref``); ``columns`` maps canonical names to other ones, and
``field_unit`` converts a field given in nT, mT or gauss to the uT bayesmag works in.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from bayesmag._src.core.data import (ARRAY_COLUMNS, AXES, CANONICAL_COLUMNS, FIELD_UNITS, CalibrationData, DataError,
                                     check_units, column_mapping, kelvin_to_celsius, spread_duplicate_times,
                                     time_in_seconds)

__all__ = ["FIELD_UNITS", "frame_io", "load_table", "from_frame", "to_frame", "prediction_frame", "read_parquet", "as_data",
           "is_frame", "as_calibration_data", "DUPLICATE_TIMES"]

#: What the library's entry points do with repeated timestamps within a run: ``"ignore"`` (time not used),
#: ``"refuse"`` (name the rows) or ``"spread"`` (spread the rows that share a stamp evenly over the
#: interval to the next stamp, as the Belsten loader does for its whole-second stamps).
DUPLICATE_TIMES = ("ignore", "refuse", "spread")

_FIELD = ("bx_meas", "by_meas", "bz_meas", "bx_ref", "by_ref", "bz_ref")


def is_frame(obj) -> bool:
    """True for a pandas DataFrame (without importing pandas when it is not loaded)."""
    import sys
    pd = sys.modules.get("pandas")
    return pd is not None and isinstance(obj, pd.DataFrame)


def from_frame(df, *, columns: Mapping[str, str] | None = None, temperature_unit: str = "C",
               field_unit: str | None = None, require_reference: bool = False,
               source: str = "DataFrame", time_unit: str = "s") -> CalibrationData:
    """A :class:`~bayesmag.CalibrationData` from a DataFrame with canonical (or mapped) columns.

    ``time`` and ``run`` are optional (row index / one run); the three ``*_ref`` columns are
    all present or all absent (absent is fine unless ``require_reference``). ``time_unit``: the
    ``time`` column's (one of ``data.TIME_UNITS``, converted to seconds).
    """
    if not is_frame(df):
        raise DataError(f"expected a pandas DataFrame; got {type(df).__name__}.")
    declared, field_unit = field_unit, field_unit or "uT"
    mapping = column_mapping(columns, field_unit=field_unit, temperature_unit=temperature_unit)
    dup = [c for c in set(df.columns) if list(df.columns).count(c) > 1]
    if dup:
        pos = [i + 1 for i, c in enumerate(df.columns) if c == dup[0]]
        raise DataError(f"the DataFrame has two columns named {dup[0]!r} (positions {pos}); bayesmag cannot tell "
                        f"which one holds the data. Rename or drop one.")

    def col(name, required):
        src = mapping[name]
        if src not in df.columns:
            if required:
                who = "the DataFrame" if source == "DataFrame" else source      # a Parquet file: its path
                raise DataError(f"{who} has no column {src!r}" + (f" (for {name!r})" if src != name else "")
                                + f". Columns found: {list(df.columns)}; expected {list(CANONICAL_COLUMNS)} "
                                "or a column mapping (columns= in Python, --columns / [data.columns] on the "
                                "command line).")
            return None
        try:
            v = df[src].to_numpy(dtype=np.float64, na_value=np.nan)
        except (TypeError, ValueError):
            raise DataError(f"column {src!r} of the DataFrame is not numeric (dtype {df[src].dtype}).") from None
        return v * FIELD_UNITS[field_unit] if name in _FIELD else v

    b = np.stack([col(c, True) for c in ("bx_meas", "by_meas", "bz_meas")], axis=1)
    t = col("temperature", True)
    if temperature_unit == "K":
        t = kelvin_to_celsius(t, f" of {source}" if source else "")
    refs = [col(c, require_reference) for c in ("bx_ref", "by_ref", "bz_ref")]
    if any(r is None for r in refs) and not all(r is None for r in refs):
        missing = [mapping[c] for c, r in zip(("bx_ref", "by_ref", "bz_ref"), refs) if r is None]
        raise DataError(f"the DataFrame has some reference columns but not {missing}; give all three or none.")
    ref = None if refs[0] is None else np.stack(refs, axis=1)
    run = col("run", False)
    if run is not None and (not np.isfinite(run).all() or np.any(run != np.round(run))):
        raise DataError("column 'run' of the DataFrame must hold finite integers.")
    return CalibrationData(b, t, ref, time_in_seconds(col("time", False), time_unit), run, source=source,
                           field_unit=declared)


def _from_array(x, *, field_unit: str | None, temperature_unit: str, source: str) -> CalibrationData:
    """A (n, 4) or (n, 7) array in the order :data:`~bayesmag._src.data.ARRAY_COLUMNS`."""
    x = np.asarray(x)
    if x.ndim != 2 or x.shape[1] not in (4, 7) or not np.issubdtype(x.dtype, np.number):
        raise DataError(f"a NumPy array must be numeric with shape (n, 4) or (n, 7), columns "
                        f"{list(ARRAY_COLUMNS[:4])} (+ {list(ARRAY_COLUMNS[4:])} for a fit); got shape {x.shape} "
                        f"of {x.dtype}. Or pass a DataFrame with named columns.")
    x = x.astype(np.float64)
    f = FIELD_UNITS[field_unit or "uT"]
    t = kelvin_to_celsius(x[:, 3], f" of {source}" if source else "") if temperature_unit == "K" else x[:, 3]
    return CalibrationData(x[:, :3] * f, t, x[:, 4:7] * f if x.shape[1] == 7 else None, source=source,
                           field_unit=field_unit)


def as_calibration_data(obj, *, columns: Mapping[str, str] | None = None, field_unit: str | None = None,
                        temperature_unit: str = "C", require_reference: bool = False,
                        duplicate_times: str = "ignore", train_max_ut: float | None = None,
                        what: str = "data", train_noise_ut: float | None = None) -> CalibrationData:
    """The library's boundary: a :class:`~bayesmag.CalibrationData`, DataFrame or NumPy array as checked
    CalibrationData in uT and Celsius (the command line's checks, :func:`~bayesmag._src.data.check_units`).

    Args:
      obj: CalibrationData, a pandas DataFrame (canonical or ``columns``-mapped names), or a NumPy
        array (n, 4) / (n, 7) in the order :data:`~bayesmag._src.data.ARRAY_COLUMNS`
        (``bx_meas, by_meas, bz_meas, temperature[, bx_ref, by_ref, bz_ref]``).
      columns: canonical name -> the DataFrame's column name.
      field_unit: ``None`` (uT, checked: nT, mT and gauss refused), or a declared unit of
        :data:`FIELD_UNITS` (converted to uT and trusted).
      temperature_unit: ``"C"`` or ``"K"`` (converted); kelvin given as Celsius is refused.
      require_reference: refuse data without the reference field, or with a non-finite value (a fit's rows).
      duplicate_times: one of :data:`DUPLICATE_TIMES`.
      train_max_ut: the calibration's largest training |B| (``predict``: the field is checked against it).
      train_noise_ut: its input-noise sd (uT): a weak field whose row noise matches it is uT, not mT.
      what: how messages name ``obj`` (e.g. ``"the data given to fit_physics"``).

    Example:
      >>> as_calibration_data(np.array([[20.0, 5.0, -40.0, 21.0]] * 3)).n
      3
    """
    if duplicate_times not in DUPLICATE_TIMES:
        raise DataError(f"duplicate_times is {duplicate_times!r}; it must be one of {list(DUPLICATE_TIMES)}.")
    column_mapping(columns, field_unit=field_unit or "uT", temperature_unit=temperature_unit)   # units known
    if isinstance(obj, CalibrationData):
        data = obj                          # columns= maps DataFrame names: nothing to map here
        if field_unit is not None or temperature_unit != "C":
            f = FIELD_UNITS[field_unit or "uT"]
            t = kelvin_to_celsius(data.temperature, f" of {what}") if temperature_unit == "K" else data.temperature
            data = CalibrationData(data.b_meas * f, t,
                                   None if data.b_ref is None else data.b_ref * f, data.time, data.run, data.source,
                                   field_unit or data.field_unit, data.time_given)
    elif is_frame(obj):
        data = from_frame(obj, columns=columns, temperature_unit=temperature_unit, field_unit=field_unit,
                          require_reference=require_reference, source=what)
    elif isinstance(obj, np.ndarray):
        if columns:
            raise DataError(f"columns= maps DataFrame columns; a NumPy array has the fixed order {list(ARRAY_COLUMNS)}.")
        data = _from_array(obj, field_unit=field_unit, temperature_unit=temperature_unit, source=what)
    else:
        raise DataError(f"{what} must be a CalibrationData, a pandas DataFrame or a NumPy array (n, 4) / (n, 7) "
                        f"in the order {list(ARRAY_COLUMNS)}; got {type(obj).__name__}.")
    if require_reference and data.b_ref is None:
        raise DataError(f"{what} has no reference field (bx_ref, by_ref, bz_ref); a fit needs it.")
    if require_reference:                   # a fit: every row counts (a NaN would end in a LinAlgError)
        from bayesmag._src.core.data import check_values
        check_values(data, origin=what)
    arg_fix = "Convert the field to uT or pass field_unit='nT' (or 'mT', 'G')"
    finite = np.isfinite(data.b_meas).all(axis=1) & np.isfinite(data.temperature)
    if finite.any():
        import warnings

        from bayesmag._src.core.data import DataNote
        for w in check_units(data.subset(finite), train_max_ut=train_max_ut, origin=what, fix=arg_fix,
                             train_noise_ut=train_noise_ut,
                             declare="field_unit='uT'",
                             temperature_fix="Pass temperature_unit='K' (or subtract 273.15)"):
            warnings.warn(DataNote(w), stacklevel=3)
    if duplicate_times != "ignore":
        from bayesmag._src.core.data import _check_time
        if duplicate_times == "spread":
            data = spread_duplicate_times(data)
        try:
            _check_time(data, f" in {what}", duplicates=True, order=False)
        except DataError as e:
            raise DataError(f"{e} Or pass duplicate_times='spread' to spread rows that share a timestamp evenly "
                            f"up to the next one.") from None
    return data


def to_frame(data: CalibrationData):
    """The canonical columns of ``data`` as a DataFrame (reference columns only when present)."""
    import pandas as pd

    cols = {"time": data.time, "run": data.run}
    cols.update({f"b{a}_meas": data.b_meas[:, i] for i, a in enumerate(AXES)})
    cols["temperature"] = data.temperature
    if data.b_ref is not None:
        cols.update({f"b{a}_ref": data.b_ref[:, i] for i, a in enumerate(AXES)})
    return pd.DataFrame(cols)


def prediction_frame(pred: Mapping[str, np.ndarray], index=None):
    """A prediction dict (``(n, 3)`` arrays and ``(n,)`` flags) as a DataFrame.

    Columns ``{axis}_{name}`` (``x_calibrated``, ``x_lower``, ...; the names of ``bayesmag apply``'s
    CSV) then the per-row flags; ``index`` is kept (e.g. the input DataFrame's index).
    """
    import pandas as pd

    cols = {}
    per_axis = [k for k, v in pred.items() if np.ndim(v) == 2]
    for a, ax in enumerate(AXES):
        for k in per_axis:
            cols[f"{ax}_{k}"] = np.asarray(pred[k])[:, a]
    for k, v in pred.items():
        if np.ndim(v) == 1:
            cols[k] = np.asarray(v)
    return pd.DataFrame(cols, index=index)


def as_data(obj, **kwargs) -> tuple[CalibrationData, object]:
    """``(CalibrationData, index)`` from a CalibrationData (index None) or a DataFrame (its index)."""
    if isinstance(obj, CalibrationData):
        return obj, None
    if is_frame(obj):
        return from_frame(obj, **kwargs), obj.index
    raise DataError(f"expected a CalibrationData or a pandas DataFrame; got {type(obj).__name__}.")


def read_parquet(path: str | Path, **kwargs) -> CalibrationData:
    """Load a Parquet file with canonical (or mapped) columns; needs pyarrow (``pip install bayesmag[parquet]``)."""
    import pandas as pd

    path = Path(path)
    if not path.exists():
        raise DataError(f"Data file {path} does not exist.")
    try:
        df = pd.read_parquet(path)
    except ImportError as e:
        raise DataError(f"reading {path} needs pyarrow (pip install 'bayesmag[parquet]' or pip install pyarrow): "
                        f"{e}") from None
    return from_frame(df, source=str(path), **kwargs)


def frame_io(method=None, *, physics_inputs: bool = False):
    """Decorate a ``predict(self, data, ...)`` so that a DataFrame in gives a DataFrame out.

    The DataFrame is converted with :func:`from_frame` (reference columns optional) and the result
    (a dict of arrays, or one (n, 3) array named ``calibrated``) with :func:`prediction_frame`,
    keeping the input's index. Anything else passes through unchanged; with ``physics_inputs``
    a :class:`~bayesmag.CalibrationData` is also accepted and turned into model inputs.
    """
    import functools

    def deco(fn):
        @functools.wraps(fn)
        def wrapper(self, data, *args, **kwargs):
            index = None
            frame = is_frame(data)
            if frame:
                data, index = as_data(data)
            if physics_inputs and isinstance(data, CalibrationData):
                from bayesmag._src.core.physics import inputs_from_data
                data = inputs_from_data(data)
            out = fn(self, data, *args, **kwargs)
            if not frame:
                return out
            return prediction_frame(out if isinstance(out, Mapping) else {"calibrated": np.asarray(out)}, index)
        return wrapper
    return deco if method is None else deco(method)


def load_table(path: str | Path, *, columns: Mapping[str, str] | None = None, temperature_unit: str = "C",
               field_unit: str | None = None, require_reference: bool = True, time_unit: str = "s",
               mapping_hint: str = "a [data.columns] mapping") -> CalibrationData:
    """A recording from CSV (``data.load_csv``) or Parquet (by suffix), with column mapping and units."""
    if Path(path).suffix.lower() in (".parquet", ".pq"):
        return read_parquet(path, columns=columns, temperature_unit=temperature_unit, field_unit=field_unit,
                            require_reference=require_reference, time_unit=time_unit)
    from bayesmag._src.core.data import load_csv
    return load_csv(path, columns=columns, temperature_unit=temperature_unit, field_unit=field_unit,
                    require_reference=require_reference, time_unit=time_unit, mapping_hint=mapping_hint)
