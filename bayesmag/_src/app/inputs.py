"""The recording a job's config names: a CSV or Parquet path, a named dataset, or the built-in simulator."""

from __future__ import annotations

from bayesmag._src.app.config import Config, ConfigError
from bayesmag._src.core.data import CalibrationData
from bayesmag._src.core.datasets import find_dataset, load_dataset

__all__ = ["load_data", "recording_paths"]


def load_data(cfg: Config) -> CalibrationData:
    """The recording a config names (CSV path, named dataset, or the built-in simulator)."""
    d = cfg.data
    if d.path is not None:                  # CSV, or Parquet by its suffix (as `apply` reads)
        from bayesmag._src.core.frames import load_table
        return load_table(d.path, columns=d.columns or None, temperature_unit=d.temperature_unit,
                          field_unit=d.field_unit)
    if d.source == "simulated":
        from bayesmag._src.core.simulate import simulate_from_config
        try:
            return simulate_from_config(dict(d.simulate))
        except (ValueError, TypeError) as e:
            raise ConfigError(f"[data.simulate] {e}") from None
    return load_dataset(d.source)


def recording_paths(data, run_dir=None) -> list:
    """The files on this machine that a job's ``[data]`` table (a dict, as saved in a calibration) read: its
    ``path``, or the file of its named dataset (``source``) where it is found. A command's ``--out`` never
    replaces them (``apply``, ``export``). A relative ``path`` is taken both from here and from the folder the run
    was started in (``run_dir``'s marker records it): the command may run elsewhere."""
    from pathlib import Path
    d = data if isinstance(data, dict) else {}
    if d.get("path"):
        p = Path(d["path"])
        out = [p]
        if not p.is_absolute() and run_dir is not None:
            from bayesmag._src.app.outdir import marker_status
            cwd = (marker_status(run_dir) or {}).get("cwd")
            if isinstance(cwd, str) and cwd:
                out.append(Path(cwd) / p)
        return out
    src = d.get("source")
    if src and src != "simulated":
        try:
            return [find_dataset(src)]
        except Exception:  # noqa: BLE001 -- not on this machine: nothing to protect here
            return []
    return []
