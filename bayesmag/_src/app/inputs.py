"""The recording a job's config names: a CSV or Parquet path, a named dataset, or the built-in simulator."""

from __future__ import annotations

from bayesmag._src.app.config import Config, ConfigError
from bayesmag._src.core.data import CalibrationData, load_csv
from bayesmag._src.core.datasets import load_dataset

__all__ = ["load_data"]


def load_data(cfg: Config) -> CalibrationData:
    """The recording a config names (CSV path, named dataset, or the built-in simulator)."""
    d = cfg.data
    if d.path is not None:
        return load_csv(d.path, columns=d.columns or None, temperature_unit=d.temperature_unit,
                        field_unit=d.field_unit)
    if d.source == "simulated":
        from bayesmag._src.core.simulate import simulate_from_config
        try:
            return simulate_from_config(dict(d.simulate))
        except (ValueError, TypeError) as e:
            raise ConfigError(f"[data.simulate] {e}") from None
    return load_dataset(d.source)
