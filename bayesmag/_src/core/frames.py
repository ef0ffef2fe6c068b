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

from bayesmag._src.core.data import AXES, CANONICAL_COLUMNS, FIELD_UNITS, CalibrationData, DataError, column_mapping

__all__ = ["FIELD_UNITS", "frame_io", "load_table", "from_frame", "to_frame", "prediction_frame", "read_parquet", "as_data",
           "is_frame"]

_FIELD = ("bx_meas", "by_meas", "bz_meas", "bx_ref", "by_ref", "bz_ref")


def is_frame(obj) -> bool:
    """True for a pandas DataFrame (without importing pandas when it is not loaded)."""
    import sys
    pd = sys.modules.get("pandas")
    return pd is not None and isinstance(obj, pd.DataFrame)


def from_frame(df, *, columns: Mapping[str, str] | None = None, temperature_unit: str = "C",
               field_unit: str = "uT", require_reference: bool = False, source: str = "DataFrame") -> CalibrationData:
    """A :class:`~bayesmag.CalibrationData` from a DataFrame with canonical (or mapped) columns.

    ``time`` and ``run`` are optional (row index / one run); the three ``*_ref`` columns are
    all present or all absent (absent is fine unless ``require_reference``).
    """
    if not is_frame(df):
        raise DataError(f"expected a pandas DataFrame; got {type(df).__name__}.")
    mapping = column_mapping(columns, field_unit=field_unit, temperature_unit=temperature_unit)

    def col(name, required):
        src = mapping[name]
        if src not in df.columns:
            if required:
                raise DataError(f"the DataFrame has no column {src!r}" + (f" (for {name!r})" if src != name else "")
                                + f". Columns found: {list(df.columns)}; expected {list(CANONICAL_COLUMNS)} "
                                "or a columns= mapping.")
            return None
        try:
            v = df[src].to_numpy(dtype=np.float64, na_value=np.nan)
        except (TypeError, ValueError):
            raise DataError(f"column {src!r} of the DataFrame is not numeric (dtype {df[src].dtype}).") from None
        return v * FIELD_UNITS[field_unit] if name in _FIELD else v

    b = np.stack([col(c, True) for c in ("bx_meas", "by_meas", "bz_meas")], axis=1)
    t = col("temperature", True)
    if temperature_unit == "K":
        t = t - 273.15
    refs = [col(c, require_reference) for c in ("bx_ref", "by_ref", "bz_ref")]
    if any(r is None for r in refs) and not all(r is None for r in refs):
        missing = [mapping[c] for c, r in zip(("bx_ref", "by_ref", "bz_ref"), refs) if r is None]
        raise DataError(f"the DataFrame has some reference columns but not {missing}; give all three or none.")
    ref = None if refs[0] is None else np.stack(refs, axis=1)
    run = col("run", False)
    if run is not None and (not np.isfinite(run).all() or np.any(run != np.round(run))):
        raise DataError("column 'run' of the DataFrame must hold finite integers.")
    return CalibrationData(b, t, ref, col("time", False), run, source=source)


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
               field_unit: str = "uT", require_reference: bool = True) -> CalibrationData:
    """A recording from CSV (``data.load_csv``) or Parquet (by suffix), with column mapping and units."""
    if Path(path).suffix.lower() in (".parquet", ".pq"):
        return read_parquet(path, columns=columns, temperature_unit=temperature_unit, field_unit=field_unit,
                            require_reference=require_reference)
    from bayesmag._src.core.data import load_csv
    return load_csv(path, columns=columns, temperature_unit=temperature_unit, field_unit=field_unit,
                    require_reference=require_reference)
