"""The recording a job's config names: a CSV or Parquet path, a named dataset, or the built-in simulator."""

from __future__ import annotations

from bayesmag._src.app.config import Config, ConfigError
from bayesmag._src.core.data import CalibrationData, load_csv
from bayesmag._src.core.datasets import find_dataset, load_dataset

__all__ = ["load_data", "recording_paths"]


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


def recording_paths(data) -> list:
    """The files on this machine that a job's ``[data]`` table (a dict, as saved in a calibration) read: its
    ``path``, or the file of its named dataset (``source``) where it is found. A command's ``--out`` never
    replaces them (``apply``, ``export``)."""
    from pathlib import Path
    d = data if isinstance(data, dict) else {}
    if d.get("path"):
        return [Path(d["path"])]
    src = d.get("source")
    if src and src != "simulated":
        try:
            return [find_dataset(src)]
        except Exception:  # noqa: BLE001 -- not on this machine: nothing to protect here
            return []
    return []
