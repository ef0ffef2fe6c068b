"""The ``bayesmag discover`` command: its argument parsing and the ``[discover]`` config table."""

from __future__ import annotations

import argparse
import dataclasses
import re
import sys
import time
from pathlib import Path
from typing import Sequence

from bayesmag._src.pipeline.discover.options import DiscoverOptions
from bayesmag._src.pipeline.discover.pipeline import discover

__all__ = ["load_discover_config", "build_parser", "main"]


def load_discover_config(path: str | Path, overrides: Sequence[str] = ()):
    """(Config, DiscoverOptions) from a TOML file whose optional ``[discover]`` table holds
    :class:`DiscoverOptions` fields (validated; unknown keys are errors naming the valid set)."""
    from bayesmag._src.app.config import read_config_dict

    return discover_config_from_dict(read_config_dict(path, overrides))


def discover_config_from_dict(raw: dict):
    """(Config, DiscoverOptions) from a raw config dict (:func:`load_discover_config`'s checks)."""
    from bayesmag._src.app.config import ConfigError, config_from_dict

    raw = dict(raw)
    disc = raw.pop("discover", {})
    cfg = config_from_dict(raw)
    if cfg.measurement.kind != "vector" or cfg.data.source == "field_simulated":
        raise ConfigError(f"`bayesmag discover` compares the calibrated field with a vector reference, row by row; this "
                          f"config is a field calibration (measurement.kind = {cfg.measurement.kind!r}{', data.source = ' + repr(cfg.data.source) if cfg.data.source == 'field_simulated' else ''}), "
                          f"whose recordings have none (or withhold it). Give discover a config with a vector "
                          f"reference (bx_ref, by_ref, bz_ref; e.g. discover_belsten), or set measurement.kind = "
                          f"\"vector\" if the recording holds one.")
    valid = [f.name for f in dataclasses.fields(DiscoverOptions)]
    unknown = sorted(set(disc) - set(valid))
    if unknown:
        raise ConfigError(f"Unknown config key(s) {['discover.' + k for k in unknown]}. Valid keys in [discover]: {valid}.")
    try:
        opts = DiscoverOptions(**disc)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"[discover]: {e}") from None
    if "t0" not in disc:                # [physics] t0 (itself defaulting to the one default, "mean") applies
        opts = dataclasses.replace(opts, t0=cfg.physics.t0)
    return cfg, opts



def _columns_of(path: Path) -> list[str]:
    """The column names of a CSV's header (BOM-safe, any delimiter) or of a Parquet file's schema."""
    if path.suffix.lower() in (".parquet", ".pq"):
        import pyarrow.parquet as pq
        return list(pq.read_schema(path).names)
    with open(path, encoding="utf-8-sig", errors="replace") as f:
        header = f.readline()
    return [c.strip().strip('"') for c in re.split(r"[,;\t]", header)]


def resolve_config(name: str) -> Path:
    """A config path, or the name of a packaged config (``discover_belsten``), as ``bayesmag run`` accepts."""
    from bayesmag._src.app.config import resolve_config_path
    return resolve_config_path(name)


def default_out(name: str) -> Path:
    """``runs/discover_<name>``; a name that already starts with ``discover`` is not prefixed twice."""
    return Path("runs") / (name if name.startswith("discover") else f"discover_{name}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bayesmag discover", description=(
        "Find physics missing from the calibration model: fit the thermo-affine model, search the catalogue of "
        "candidate physics terms on the residuals, check the findings and name what is left unexplained "
        "(docs/discovery.md)."))
    p.add_argument("config", nargs="?", help="config file with [data] and optional [discover], or the name of a "
                                             "packaged config (e.g. discover_belsten)")
    p.add_argument("--data", help="a canonical CSV instead of a config (defaults for everything else)")
    p.add_argument("--out", help="output folder (default runs/discover_<name>, or runs/<name> when the config's "
                                 "name starts with discover)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config key")
    p.add_argument("--field-unit", choices=["uT", "nT", "mT", "G"], default=None,
                   help="declare the field unit of the data (converted to uT and trusted)")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--no-progress", action="store_true", help="no stage lines on stderr")
    return p


def _progress_printer():
    t0 = time.perf_counter()

    def show(msg: str) -> None:
        print(f"  [{time.perf_counter() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)
    return show


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from bayesmag._src.app.config import ConfigError
    from bayesmag._src.core.data import DataError
    from bayesmag._src.app.job import load_data

    try:
        if args.data and args.config:
            raise ConfigError("give a CONFIG or --data FILE.csv, not both.")
        if args.data:                       # the defaults for everything else; --set overrides them as for a config
            from bayesmag._src.app.config import apply_overrides
            units = [f'data.field_unit="{args.field_unit}"'] if args.field_unit else []
            raw = apply_overrides({"name": Path(args.data).stem, "data": {"path": str(args.data)}},
                                  (args.set or []) + units)
            cfg, opts = discover_config_from_dict(raw)
            data = load_data(cfg)
            if opts.time_available is None and "time" not in _columns_of(Path(cfg.data.path)):
                opts = dataclasses.replace(opts, time_available=False)
            name = cfg.name
        elif args.config:
            units = [f'data.field_unit="{args.field_unit}"'] if args.field_unit else []
            cfg, opts = load_discover_config(resolve_config(args.config), (args.set or []) + units)
            data = load_data(cfg)
            name = cfg.name
        else:
            raise ConfigError("give a CONFIG or --data FILE.csv.")
        if args.no_figures:
            opts = dataclasses.replace(opts, figures=False)
        out = Path(args.out) if args.out else default_out(name)
        res = discover(data, opts, progress=None if args.no_progress else _progress_printer())
        from bayesmag._src.app.discover_outputs import write_discovery
        write_discovery(res, out)
    except (ConfigError, DataError, FileNotFoundError, ValueError) as e:
        print(f"bayesmag discover: error: {e}", file=sys.stderr)
        return 2
    print(f"bayesmag discover: wrote {out}/ in {res.seconds:.1f} s")
    if res.no_missing_physics:
        print("  no missing physics found")
    for f in res.findings:
        ps = ", ".join(f"{k}={p['value']:.4g}+-{p['se']:.2g}"
                       + (f" [95 %: {p['interval95'][0]:.4g}, {p['interval95'][1]:.4g}]" if p.get("interval95") else "")
                       for k, p in f["parameters"].items())
        loc = f.get("location")
        if loc:
            ps += f"; at {loc['value']:.6g} s [95 %: {loc['interval95'][0]:.6g}, {loc['interval95'][1]:.6g}]"
        ev = f["evidence"]
        ps += f"; {ev['decided_by']} = {ev['z_decisive']:.2f}"
        where = f"{f['channel']} channel" if f["frame"] == "sensor" else (
            "whole sensor" if f["frame"] == "whole" else f"{f['axis']} output")
        print(f"  {where}: {f['effect']} ({ps})")
    for u in res.unexplained:
        where = f"{u['axis']} output" if u.get("frame") == "output" else f"{u['channel']} channel"
        scale = (f"{u['time_scale_s']:.3g} s" if u.get("time_scale_s") is not None
                 else f"{u['time_scale_rows']:.3g} rows (no time column)")
        print(f"  {where}: unexplained, time scale {scale} ({u['basis']})")
    for n in res.notes:
        print(f"  note: {n}")
    return 0
