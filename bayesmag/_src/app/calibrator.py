"""A scikit-learn-style front door for notebooks: ``bayesmag.Calibrator(config).fit(data).predict(df)``.

``fit`` runs the same job as ``bayesmag run`` (split, physics fit, physics uncertainty, and the
network / NUTS stages the config enables) on the rows it is given, into a run folder, and keeps
the saved calibration; ``predict`` applies it. Without a config it fits the physics stage on all
rows (``[split] kind = "none"``) with the exact analytic uncertainty.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from bayesmag._src.app.config import Config, ConfigError, config_from_dict, read_config_dict
from bayesmag._src.core.data import DataError, write_csv

__all__ = ["Calibrator", "DEFAULT_CONFIG"]

DEFAULT_CONFIG = {"name": "calibrator", "split": {"kind": "none"}, "physics": {"t0": "mean"},
                  "uq": {"method": "analytic"}, "output": {"figures": False, "progress": False}}


def _drop_none(d):
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    return d


class Calibrator:
    """Fit a calibration on a DataFrame or :class:`~bayesmag.CalibrationData`, then predict.

    Args:
      config: None (physics stage on all rows), a TOML path or packaged config name, a
        :class:`~bayesmag.Config`, or a plain dict as parsed from TOML. Its ``[data]`` table is
        replaced by the rows given to :meth:`fit`.
      overrides: ``--set``-style ``key=value`` strings applied to the config.
      out: run folder to write (default: a temporary folder kept as long as the object).
      columns, temperature_unit, field_unit: how to read the data (``frames.as_calibration_data``: a
        DataFrame, a NumPy array (n, 7) in the order ``data.ARRAY_COLUMNS``, or CalibrationData;
        the field is checked to be in uT and the temperature in C unless a unit is declared).
      duplicate_times: ``"refuse"`` (default: rows of a run that share a timestamp are named) or
        ``"spread"`` (spread them evenly up to the next stamp, as for the whole-second Belsten stamps).

    Attributes after :meth:`fit`: ``calibration_`` (:class:`~bayesmag.Calibration`),
    ``metrics_`` (the run's metrics.json), ``physics_fit_``, ``run_dir_``.

    Example:
      >>> import bayesmag
      >>> d = bayesmag.simulate.simulate(400, design="campaign", seed=0)
      >>> cal = bayesmag.Calibrator().fit(d)
      >>> cal.predict(d)["calibrated"].shape
      (400, 3)
    """

    def __init__(self, config=None, overrides=(), *, out: str | Path | None = None, columns: dict | None = None,
                 temperature_unit: str = "C", field_unit: str | None = None, duplicate_times: str = "refuse"):
        self.config = config
        self.overrides = list(overrides)
        self.out = out
        self.duplicate_times = duplicate_times
        self.frame_options = {"columns": columns, "temperature_unit": temperature_unit, "field_unit": field_unit}

    def _raw_config(self) -> dict:
        c = self.config
        if c is None:
            raw = {k: dict(v) if isinstance(v, dict) else v for k, v in DEFAULT_CONFIG.items()}
        elif isinstance(c, Config):
            raw = _drop_none(c.to_dict())
        elif isinstance(c, dict):
            raw = _drop_none(dict(c))
        elif isinstance(c, (str, Path)):
            from bayesmag._src.app.cli import _resolve_config
            raw = read_config_dict(_resolve_config(str(c)))
        else:
            raise ConfigError(f"config must be None, a path, a Config or a dict; got {type(c).__name__}.")
        if self.overrides:
            from bayesmag._src.app.config import apply_overrides
            raw = apply_overrides(raw, self.overrides)
        return raw

    def fit(self, data, y=None) -> "Calibrator":
        """Run the job on ``data`` (with reference columns); ``y`` is ignored (sklearn signature)."""
        del y
        from bayesmag._src.app.artifact import load
        from bayesmag._src.core.frames import as_calibration_data
        from bayesmag._src.app.job import run_job

        what = "the data given to Calibrator.fit"
        rows = as_calibration_data(data, **self.frame_options, require_reference=True,
                                   duplicate_times=self.duplicate_times, what=what)
        if self.out is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="bayesmag-calibrator-")
            base = Path(self._tmp.name)
        else:
            base = Path(self.out)
            base.mkdir(parents=True, exist_ok=True)
        csv = base / "fit_data.csv"
        write_csv(rows, csv)
        raw = self._raw_config()
        raw["data"] = {"path": str(csv), **({"field_unit": "uT"} if rows.field_unit is not None else {})}
        cfg = config_from_dict(raw)
        self.run_dir_ = base / "run"
        try:
            result = run_job(cfg, self.run_dir_, progress=cfg.output.progress)
        except DataError as e:          # name the user's data, never the temporary CSV it was handed over in
            raise DataError(str(e).replace(f" in {csv}", f" in {what}").replace(str(csv), what)) from None
        self.metrics_ = result["metrics"]
        self.physics_fit_ = result["fit"]
        self.calibration_ = load(self.run_dir_)
        return self

    def _check_fitted(self):
        if not hasattr(self, "calibration_"):
            raise RuntimeError("this Calibrator is not fitted yet: call fit(data) first.")

    def predict(self, data, **kwargs):
        """Calibrated field and uncertainty: a DataFrame for a DataFrame, the dict of arrays for CalibrationData."""
        self._check_fitted()
        return self.calibration_.predict(data, **{**self.frame_options, **kwargs})

    def __repr__(self) -> str:
        state = f"fitted, {self.run_dir_}" if hasattr(self, "calibration_") else "not fitted"
        return f"Calibrator(config={self.config!r}) [{state}]"
