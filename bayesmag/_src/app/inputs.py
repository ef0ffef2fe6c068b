"""The recording a job's config names: a CSV or Parquet path, a named dataset, or the built-in simulator."""

from __future__ import annotations

from bayesmag._src.app.config import Config, ConfigError
from bayesmag._src.core.data import CalibrationData
from bayesmag._src.core.datasets import find_dataset, load_dataset

__all__ = ["load_data", "recording_paths", "fleet_verdict", "failed_sensor_warning"]


def load_data(cfg: Config) -> CalibrationData:
    """The recording a config names (CSV path, named dataset, or the built-in simulator)."""
    d = cfg.data
    if d.path is not None:                  # CSV, or Parquet by its suffix (as `apply` reads)
        from bayesmag._src.core.frames import load_table
        return load_table(d.path, columns=d.columns or None, temperature_unit=d.temperature_unit,
                          field_unit=d.field_unit, time_unit=d.time_unit)
    if d.source == "simulated":
        from bayesmag._src.core.simulate import simulate_from_config
        try:
            return simulate_from_config(dict(d.simulate))
        except (ValueError, TypeError) as e:
            raise ConfigError(f"[data.simulate] {e}") from None
    return load_dataset(d.source)


def _sensor_metrics(run_dir) -> dict | None:
    """metrics.json of a ``bayesmag fleet`` sensor folder (it has a ``fleet`` block), else None."""
    import json
    from pathlib import Path
    try:
        m = json.loads((Path(run_dir) / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    return m if isinstance(m, dict) and isinstance(m.get("fleet"), dict) else None


def fleet_verdict(run_dir) -> dict | None:
    """The fleet's verdict on a sensor folder (``metrics.json: fleet``: ``verdict``, ``fails_limits``, ...), or
    None for any other folder."""
    m = _sensor_metrics(run_dir)
    return None if m is None else m["fleet"]


def failed_sensor_warning(run_dir) -> str | None:
    """A warning when ``run_dir`` is a fleet sensor folder whose sensor failed the fleet's sign-off, else None."""
    v = fleet_verdict(run_dir)
    if not v or v.get("verdict") != "fail":
        return None
    why = [*(v.get("fails_limits") or []), *(["outlier"] if v.get("outlier") else [])]
    msg = (f"sensor {v.get('id', '?')} FAILED the fleet's sign-off ({', '.join(why) or 'see fleet_report.md'}; "
           f"its metrics.json 'fleet' block and the fleet's fleet_report.md say why)")
    if "unidentifiable" in why:
        return msg + (": its data cannot inform every parameter, so its parameters are meaningless; recalibrate "
                      "it on a recording with every field axis and the temperature varied.")
    return msg + ": its calibration is not signed off; use it only if you accept those reasons."


def protected_recordings(data, run_dir=None) -> list:
    """The files a command's ``--out`` never replaces: :func:`recording_paths`, and for a fleet sensor folder the
    recordings of every other sensor of its fleet (``--force`` replaced another sensor's raw recording: sixth
    outside pass)."""
    return recording_paths(data, run_dir) + (_fleet_recordings(run_dir) if run_dir is not None else [])


def _fleet_recordings(run_dir) -> list:
    """The recordings the other sensor folders of ``run_dir``'s fleet were calibrated on ([] for any other folder)."""
    import json
    from pathlib import Path
    run_dir = Path(run_dir)
    if _sensor_metrics(run_dir) is None or run_dir.parent.name != "sensors":
        return []
    out = []
    for sib in sorted(run_dir.parent.iterdir()):
        if sib == run_dir or not (sib / "calibration.json").is_file():
            continue
        try:
            data = (json.loads((sib / "calibration.json").read_text()).get("config") or {}).get("data")
        except (OSError, ValueError, AttributeError):
            continue
        out += recording_paths(data, sib)
    return out


def recording_paths(data, run_dir=None) -> list:
    """The files on this machine that a job's ``[data]`` table (a dict, as saved in a calibration) read: its
    ``path``, or the file of its named dataset (``source``) where it is found. A command's ``--out`` never
    replaces them (``apply``, ``export``). A relative ``path`` is taken both from here and from the folder the run
    was started in (``run_dir``'s marker records it): the command may run elsewhere.

    A fleet sensor folder (``run_dir``) saved before its config held ``[data] path``: the recording its
    metrics.json names."""
    from pathlib import Path
    d = data if isinstance(data, dict) else {}
    sensor = _sensor_metrics(run_dir) if run_dir is not None else None
    if sensor is not None and not d.get("path"):
        src = Path(str((sensor.get("data") or {}).get("source", "")))
        return [src] if src.suffix and src.is_file() else []
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
