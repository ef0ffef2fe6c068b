"""The ``bayesmag`` command line: thin wrappers around the Python API.

Commands::

    bayesmag run CONFIG [--out DIR] [--set key=value]...
    bayesmag apply --model RUN_DIR --data FILE.csv --out OUT.csv [--level 0.95] [--uq analytic|psqmc]
                   [--columns time=t,bx_meas=X,...] [--field-unit uT|nT|mT|G] [--temperature-unit C|K]
    bayesmag report RUN_DIR
    bayesmag export RUN_DIR --format {json,c-header,ardupilot,px4,magcal} [--out FILE] [--temperature T]
    bayesmag study CONFIG [--out DIR] [--set key=value]...
    bayesmag discover CONFIG | --data FILE.csv --out DIR
    bayesmag data fetch NAME [--force]
    bayesmag data list

Expected errors (bad config, data, calibration or output path; any OSError) print one line on
stderr and exit with status 2; output folders follow the rules in ``outdir`` (never replace a
folder bayesmag did not write, lock, two-phase swap).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["main"]


def _cmd_run(args) -> int:
    from bayesmag._src.app.config import load_config
    from bayesmag._src.app.job import run_job
    from bayesmag._src.app.outdir import reserve

    cfg_path = _resolve_config(args.config)
    cfg = load_config(cfg_path, args.set or [])
    out = Path(args.out) if args.out else Path("runs") / Path(args.config).stem
    with reserve(out, inputs=[cfg_path, cfg.data.path]):       # refused before any computation
        result = run_job(cfg, out, progress=not args.no_progress)
    m = result["metrics"]
    print(f"bayesmag: wrote {out}/ ({m['split']['description']}; {m['split']['n_train']} train, "
          f"{m['split']['n_test']} test rows)")
    print("  test RMSE (uT)      " + "  ".join(f"{ax}: {m['raw']['rmse'][ax]:.4g} raw -> {m['physics']['rmse'][ax]:.4g} physics"
                                            for ax in "xyz"))
    cov = m["physics"]["coverage"]
    print(f"  physics {m['uq']['level']:.0%} coverage  " + "  ".join(f"{ax}: {cov[ax]:.1%}" for ax in "xyz"))
    for name, block in m.get("hybrid", {}).items():
        print(f"  hybrid[{name}] RMSE    " + "  ".join(f"{ax}: {block['rmse'][ax]:.4g}" for ax in "xyz")
              + "   coverage " + "  ".join(f"{ax}: {block['coverage'][ax]:.1%}" for ax in "xyz"))
    for ax, block in m.get("nuts", {}).get("axes", {}).items():
        if "verdict" in block:
            print(f"  NUTS {ax}: {block['verdict']}")
    for note in result["fit"].design_notes:
        print(f"  note: {note}")
    for w in m.get("warnings", []):
        print(f"  WARNING: {w}", file=sys.stderr)
    return 0


def packaged_configs_dir() -> Path:
    """The shipped configs (:func:`bayesmag._src.app.config.packaged_configs_dir`)."""
    from bayesmag._src.app.config import packaged_configs_dir as where
    return where()


def _resolve_config(name: str) -> Path:
    from bayesmag._src.app.config import resolve_config_path
    return resolve_config_path(name)


def _cmd_data(args) -> int:
    from bayesmag._src.core.datasets import DATASETS, fetch_dataset, find_dataset

    if args.action == "list":
        for name, ds in DATASETS.items():
            try:
                where = str(find_dataset(name))
            except Exception:
                where = "not downloaded (bayesmag data fetch " + name + ")"
            print(f"{name}: {ds.description}\n  {where}")
        return 0
    if not args.name:
        print("bayesmag data fetch: name a dataset, e.g. `bayesmag data fetch belsten2023`", file=sys.stderr)
        return 2
    path = fetch_dataset(args.name, force=args.force)
    print(f"bayesmag: {args.name} is at {path} (sha256 verified)")
    return 0


def _cmd_apply(args) -> int:

    from bayesmag._src.app.apply import apply_calibration

    summary = apply_calibration(args.model, args.data, args.out, level=args.level, method=args.uq,
                                n_params=args.n_params, n_qmc=args.n_qmc, temperature_unit=args.temperature_unit,
                                field_unit=args.field_unit, columns=_parse_columns(args.columns),
                                progress=not args.no_progress)
    print(f"bayesmag: calibrated {summary['n_valid']} of {summary['n_rows']} rows -> {args.out} "
          f"({summary['seconds']:.2f} s)")
    for w in summary["warnings"]:
        print(f"  WARNING: {w}", file=sys.stderr)
    if summary.get("metrics"):
        m = summary["metrics"]
        print("  reference columns found: RMSE (uT) " + "  ".join(f"{a}: {m['rmse'][a]:.4g}" for a in "xyz")
              + f"   {summary['level']:.0%} coverage " + "  ".join(f"{a}: {m['coverage'][a]:.1%}" for a in "xyz"))
    return 0


def _parse_columns(text: str | None) -> dict[str, str] | None:
    """``time=t,bx_meas=X`` -> {"time": "t", "bx_meas": "X"} (names checked by ``load_csv``)."""
    from bayesmag._src.core.data import DataError

    if not text:
        return None
    mapping = {}
    for item in text.split(","):
        if item.count("=") != 1 or not all(part.strip() for part in item.split("=")):
            raise DataError(f"--columns item {item!r} must look like CANONICAL=FILE_COLUMN, e.g. "
                            f"--columns time=t,bx_meas=X.")
        k, v = (part.strip() for part in item.split("="))
        mapping[k] = v
    return mapping


def _cmd_study(args) -> int:
    from bayesmag._src.app.config import load_config
    from bayesmag._src.app.outdir import reserve
    from bayesmag._src.app.study import run_study

    cfg_path = _resolve_config(args.config)
    cfg = load_config(cfg_path, args.set or [])
    out = Path(args.out) if args.out else Path("runs") / Path(args.config).stem
    with reserve(out, inputs=[cfg_path, cfg.data.path]):
        res = run_study(cfg, out, progress=not args.no_progress)
    print(f"bayesmag: wrote {out}/ ({res['seconds_total']:.0f} s, peak memory {res['peak_rss_gb']:.2f} GB)")
    print((out / "simulation_study.md").read_text())
    return 0


def _cmd_export(args) -> int:
    from bayesmag._src.app.export import ExportError, export_run, limitations

    try:
        path, ex = export_run(args.run_dir, args.format, args.out, t_ref=args.temperature)
    except ExportError as e:
        print(f"bayesmag: error: {e}", file=sys.stderr)
        return 2
    print(f"bayesmag: wrote {path}")
    for line in limitations(args.format, ex):
        print(f"  {line}")
    return 0


def _cmd_report(args) -> int:
    from bayesmag._src.app.report import write_report

    print(f"bayesmag: wrote {write_report(args.run_dir)}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from bayesmag._src.core.version import __version__
    p = argparse.ArgumentParser(prog="bayesmag", description="Magnetometer calibration with trustworthy uncertainty.")
    p.add_argument("--version", action="version", version=f"bayesmag {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run a calibration job from a TOML config")
    r.add_argument("config", help="config file (or the name of a packaged config, e.g. quickstart)")
    r.add_argument("--out", help="output folder (default runs/<config name>)")
    r.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a config key, e.g. --set uq.n_params=100 or --set data.path=my.csv")
    r.add_argument("--no-progress", action="store_true", help="no progress bars")
    r.set_defaults(func=_cmd_run)

    a = sub.add_parser("apply", help="apply a saved calibration to a recording (reference columns optional)")
    a.add_argument("--model", required=True, help="run folder written by `bayesmag run`")
    a.add_argument("--data", required=True, help="canonical CSV (time,run,bx_meas,by_meas,bz_meas,temperature[,*_ref])")
    a.add_argument("--out", required=True, help="output CSV")
    a.add_argument("--level", type=float, default=None, help="central interval level (default: the run's)")
    a.add_argument("--uq", choices=["auto", "analytic", "psqmc"], default="auto",
                   help="physics uncertainty method (auto, the default everywhere: analytic -- exact moments, "
                        "fastest -- where the model allows it, else psqmc)")
    a.add_argument("--n-params", type=int, default=100, help="Np for --uq psqmc")
    a.add_argument("--n-qmc", type=int, default=256, help="Nq for --uq psqmc")
    a.add_argument("--temperature-unit", choices=["C", "K"], default="C", help="temperature unit of --data")
    a.add_argument("--field-unit", choices=["uT", "nT", "mT", "G"], default="uT",
                   help="field unit of --data (converted to uT at load)")
    a.add_argument("--columns", metavar="NAME=COL,...",
                   help="map canonical columns to the file's, e.g. time=t,bx_meas=X,by_meas=Y,bz_meas=Z,temperature=T")
    a.add_argument("--no-progress", action="store_true")
    a.set_defaults(func=_cmd_apply)

    st = sub.add_parser("study", help="the paper's simulation study over sample sizes")
    st.add_argument("config")
    st.add_argument("--out")
    st.add_argument("--set", action="append", metavar="KEY=VALUE")
    st.add_argument("--no-progress", action="store_true")
    st.set_defaults(func=_cmd_study)

    rp = sub.add_parser("report", help="(re)write report.md in a run folder")
    rp.add_argument("run_dir")
    rp.set_defaults(func=_cmd_report)

    ex = sub.add_parser("export", help="write a run's calibration for firmware/other tools")
    ex.add_argument("run_dir", help="run folder written by `bayesmag run`")
    ex.add_argument("--format", required=True, choices=["json", "c-header", "ardupilot", "px4", "magcal"])
    ex.add_argument("--out", help="output file (default RUN_DIR/calibration.<ext>)")
    ex.add_argument("--temperature", type=float, default=None,
                    help="reference temperature (C) of the hard/soft-iron and PX4 forms (default: median training temperature)")
    ex.set_defaults(func=_cmd_export)

    dc = sub.add_parser("discover", help="find physics missing from the calibration model", add_help=False)
    dc.add_argument("rest", nargs=argparse.REMAINDER)
    dc.set_defaults(func=lambda a: __import__("bayesmag._src.app.discover_cli", fromlist=["main"]).main(a.rest))

    d = sub.add_parser("data", help="named datasets: list, fetch")
    d.add_argument("action", choices=["fetch", "list"])
    d.add_argument("name", nargs="?")
    d.add_argument("--force", action="store_true", help="download again even if present")
    d.set_defaults(func=_cmd_data)
    return p


def _cmd_discover(argv: list[str]) -> int:
    """``bayesmag discover``: check and lock --out before the search, then run discover's own CLI."""
    from bayesmag._src.app.config import read_config_dict
    from bayesmag._src.app.discover_cli import build_parser as discover_parser, main as discover_main
    from bayesmag._src.app.outdir import reserve

    args = discover_parser().parse_args(argv)
    if bool(args.data) == bool(args.config):
        return discover_main(argv)          # discover names the usage error
    raw = read_config_dict(args.config, args.set or []) if args.config else {}
    name = Path(args.data).stem if args.data else raw.get("name", "bayesmag")
    out = Path(args.out) if args.out else Path("runs") / f"discover_{name}"
    data_table = raw.get("data") if isinstance(raw.get("data"), dict) else {}
    with reserve(out, inputs=[args.data, args.config, data_table.get("path")]):
        return discover_main(argv)


def _one_line(e: BaseException) -> str:
    if isinstance(e, OSError) and e.strerror and not type(e).__module__.startswith("bayesmag"):
        where = f" {e.filename}" if e.filename else ""
        return f"cannot use{where}: {e.strerror}" + (f" (errno {e.errno})" if e.errno else "")
    return " ".join(str(e).split())


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    from bayesmag._src.core.cache import ensure_compile_cache
    ensure_compile_cache()                  # before the first compilation (off: BAYESMAG_COMPILE_CACHE=0)
    from bayesmag._src.app.artifact import ArtifactError
    from bayesmag._src.app.config import ConfigError
    from bayesmag._src.core.data import DataError
    from bayesmag._src.app.job import JobError
    from bayesmag._src.app.outdir import OutputError

    expected = (ConfigError, DataError, JobError, ArtifactError, OutputError, OSError)
    try:
        if argv[:1] == ["discover"]:        # discover parses its own options (argparse REMAINDER drops --flags)
            return _cmd_discover(argv[1:])
        args = build_parser().parse_args(argv)
        return args.func(args)
    except expected as e:
        print(f"bayesmag: error: {_one_line(e)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
