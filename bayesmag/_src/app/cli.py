"""The ``bayesmag`` command line: thin wrappers around the Python API.

Commands::

    bayesmag run CONFIG [--out DIR] [--set key=value]...
    bayesmag apply --model RUN_DIR --data FILE.csv --out OUT.csv [--level 0.95] [--uq analytic|psqmc]
                   [--columns time=t,bx_meas=X,...] [--field-unit uT|nT|mT|G] [--temperature-unit C|K]
    bayesmag report RUN_DIR
    bayesmag export RUN_DIR --format {json,c-header,ardupilot,px4,magcal} [--out FILE] [--temperature T] [--force]
    bayesmag study CONFIG [--out DIR] [--set key=value]...
    bayesmag fleet CONFIG [--out DIR] [--set key=value]...
    bayesmag discover CONFIG | --data FILE.csv --out DIR
    bayesmag data fetch NAME [--force]
    bayesmag data list
    bayesmag config list | show NAME

Progress bars are drawn only when stderr is a terminal (a log file gets none).

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
    import contextlib

    from bayesmag._src.app.figure_worker import JOB_BARE, JOB_MODULES, FigureWorker
    # the figure process starts first: its imports (matplotlib, the plot modules) overlap ours and the job's
    with (FigureWorker(preload=JOB_MODULES, bare=JOB_BARE) if _figure_worker()
          else contextlib.nullcontext(False)) as worker:
        if worker:
            worker.warm()
        return _run(args, worker)


def _run(args, worker) -> int:
    from bayesmag._src.app.config import load_config
    from bayesmag._src.app.job import run_job
    from bayesmag._src.app.outdir import reserve

    cfg_path = _resolve_config(args.config)
    _refuse_fleet_config(cfg_path, "run")
    cfg = load_config(cfg_path, (args.set or []) + _unit_overrides(args))
    out = Path(args.out) if args.out else Path("runs") / Path(args.config).stem
    import gc
    gc.freeze()                     # the imports so far live to the end: the collector need not walk them again
    with reserve(out, inputs=[cfg_path, cfg.data.path], kind="run"):       # refused before any computation
        result = run_job(cfg, out, progress=None if _progress(args) else False,   # None: [output] progress
                         figure_worker=worker)
    m = result["metrics"]
    print(f"bayesmag: wrote {out}/ ({m['split']['description']}; {m['split']['n_train']} train, "
          f"{m['split']['n_test']} test rows)")
    if "scores" in m.get("field", {}):              # a field calibration (app/field_job.py); vector runs have field metrics
        from bayesmag._src.app.field_job import print_summary
        return print_summary(m)
    print("  test RMSE (uT)      " + "  ".join(f"{ax}: {m['raw']['rmse'][ax]:.4g} raw -> {m['physics']['rmse'][ax]:.4g} physics"
                                            for ax in "xyz"))
    cov = m["physics"]["coverage"]
    print(f"  physics {m['uq']['level']:.0%} coverage  " + "  ".join(f"{ax}: {cov[ax]:.1%}" for ax in "xyz"))
    for name, block in m.get("hybrid", {}).items():
        print(f"  hybrid[{name}] RMSE    " + "  ".join(f"{ax}: {block['rmse'][ax]:.4g}" for ax in "xyz")
              + "   coverage " + "  ".join(f"{ax}: {block['coverage'][ax]:.1%}" for ax in "xyz"))
    for stage, fm in m.get("field", {}).items():      # the field metrics (issue 26 item 12), test rows
        if stage != "raw" and "magnitude" in fm:
            h = fm.get("heading", {})
            head = (f"heading error RMS {h['rms']:.3g} deg (max {h['max_abs']:.3g})" if h.get("n_rows")
                    else "no heading (horizontal field below 5 uT on every row)")
            print(f"  {stage}: {head}, |B| residual RMS {fm['magnitude']['rms']:.3g} uT")
    for ax, block in m.get("nuts", {}).get("axes", {}).items():
        if "verdict" in block:
            print(f"  NUTS {ax}: {block['verdict']}")
    for note in result["fit"].design_notes:
        print(f"  note: {note}")
    for w in m.get("warnings", []):
        print(f"  WARNING: {w}", file=sys.stderr)
    return 0


def _refuse_fleet_config(cfg_path: Path, command: str) -> None:
    """A config with a [fleet] table is for ``bayesmag fleet`` (issue 27): say so instead of an unknown-key error."""
    import tomllib
    try:
        raw = tomllib.loads(Path(cfg_path).read_text(encoding="utf-8-sig"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return                              # load_config names the problem
    if isinstance(raw.get("fleet"), dict):
        from bayesmag._src.app.config import ConfigError
        raise ConfigError(f"{cfg_path} is a fleet config (it has a [fleet] table): use `bayesmag fleet {cfg_path}`, "
                          f"not `bayesmag {command}`.")


def _cmd_fleet(args) -> int:
    from bayesmag._src.app.fleet import load_fleet_config, run_fleet

    cfg_path = _resolve_config(args.config)
    cfg = load_fleet_config(cfg_path, args.set or [])
    out = Path(args.out) if args.out else Path("runs") / Path(args.config).stem
    s = run_fleet(cfg, out, progress=not args.no_progress)
    print(f"bayesmag: wrote {out}/ ({s['n_sensors']} sensors: {s['n_pass']} pass, {s['n_fail']} flagged; "
          f"{s['timings']['total']:.1f} s)")
    for sid in s["flagged"][:20]:
        why = s["failed_limits"].get(sid, []) + (["outlier"] if sid in s["outliers"] else [])
        print(f"  flagged {sid}: {', '.join(why)}")
    if len(s["flagged"]) > 20:
        print(f"  ... and {len(s['flagged']) - 20} more (fleet_report.md)")
    if not s["outlier_test"]["computed"]:
        print(f"  note: outlier test not computed: {s['outlier_test']['reason']}")
    gt = s.get("ground_truth")
    if gt:
        print(f"  ground truth: planted {sorted(gt['defective'])}; flagged exactly: {gt['exact']}")
    return 0


def _figure_worker() -> bool:
    """Share the figures with a worker process? Yes unless ``BAYESMAG_FIGURE_WORKER=0``: it starts while this
    process computes and draws half the figures after the training (docs/benchmarks.md, "Cold start")."""
    import os
    return os.environ.get("BAYESMAG_FIGURE_WORKER", "1").strip().lower() not in ("0", "false", "no", "off")


def _unit_overrides(args) -> list[str]:
    """``--field-unit U`` as the ``--set data.field_unit="U"`` it means."""
    return [f'data.field_unit="{args.field_unit}"'] if getattr(args, "field_unit", None) else []


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
    from bayesmag._src.app.apply_dask import is_archive
    if args.scheduler or is_archive(args.data):      # a Parquet dataset, a glob of CSVs or a cluster: Dask
        return _cmd_apply_dask(args)

    from bayesmag._src.app.apply import apply_calibration

    summary = apply_calibration(args.model, args.data, args.out, level=args.level, method=args.uq,
                                n_params=args.n_params, n_qmc=args.n_qmc, temperature_unit=args.temperature_unit,
                                field_unit=args.field_unit, columns=_parse_columns(args.columns),
                                progress=_progress(args), force=args.force, time_unit=args.time_unit)
    print(f"bayesmag: calibrated {summary['n_valid']} of {summary['n_rows']} rows -> {args.out} "
          f"({summary['seconds']:.2f} s)")
    return _report_apply(summary)


def _cmd_apply_dask(args) -> int:
    from bayesmag._src.app.apply_dask import apply_dask

    s = apply_dask(args.model, args.data, args.out, scheduler=args.scheduler, n_workers=args.workers,
                   threads_per_worker=args.threads_per_worker, memory_limit=args.memory_limit,
                   blocksize=int(args.blocksize_mb * 2**20), level=args.level, method=args.uq, n_params=args.n_params,
                   n_qmc=args.n_qmc, temperature_unit=args.temperature_unit, field_unit=args.field_unit,
                   columns=_parse_columns(args.columns), progress=_progress(args), time_unit=args.time_unit)
    print(f"bayesmag: calibrated {s['n_valid']} of {s['n_rows']} rows in {s['n_partitions']} partitions -> {args.out}/ "
          f"({s['seconds']:.2f} s, {s['n_rows'] / max(s['seconds'], 1e-9):,.0f} rows/s)")
    return _report_apply(s)


def _report_apply(summary: dict) -> int:
    """The lines after an apply's summary line: its warnings, and RMSE / coverage when the rows had a reference."""
    for w in summary["warnings"]:
        print(f"  WARNING: {w}", file=sys.stderr)
    if summary.get("metrics"):
        m = summary["metrics"]
        print("  reference columns found: RMSE (uT) " + "  ".join(f"{a}: {m['rmse'][a]:.4g}" for a in "xyz")
              + f"   {summary['level']:.0%} coverage " + "  ".join(f"{a}: {m['coverage'][a]:.1%}" for a in "xyz"))
    for n in summary.get("notes", []):
        print(f"  note: {n}")
    if summary.get("magnitude_metrics"):
        m = summary["magnitude_metrics"]
        print(f"  reference magnitude from {m['reference']} ({m['n']} rows): |B| RMSE {m['rmse']:.4g} uT"
              + ("" if m["rmse_in_domain"] is None else f" ({m['rmse_in_domain']:.4g} in domain)")
              + f", mean error (reference - calibrated) {m['mean_error']:+.3g} uT, {summary['level']:.0%} coverage "
              f"{m['coverage']:.1%}" + ("" if m["coverage_in_domain"] is None else f" ({m['coverage_in_domain']:.1%} "
                                        "in domain)"))
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
    from bayesmag._src.app.outdir import reserve
    from bayesmag._src.app.study import load_study_config, run_study

    cfg_path = _resolve_config(args.config)
    _refuse_fleet_config(cfg_path, "study")
    cfg = load_study_config(cfg_path, args.set or [])      # the study's checks, before any computation
    out = Path(args.out) if args.out else Path("runs") / Path(args.config).stem
    with reserve(out, inputs=[cfg_path, cfg.data.path], kind="study"):
        res = run_study(cfg, out, progress=_progress(args) and cfg.output.progress)
    print(f"bayesmag: wrote {out}/ ({res['seconds_total']:.0f} s, peak memory {res['peak_rss_gb']:.2f} GB)")
    print((out / "simulation_study.md").read_text())
    return 0


def _cmd_export(args) -> int:
    from bayesmag._src.app.export import ExportError, export_run, limitations

    try:
        path, ex = export_run(args.run_dir, args.format, args.out, t_ref=args.temperature, force=args.force)
    except ExportError as e:
        print(f"bayesmag: error: {e}", file=sys.stderr)
        return 2
    print(f"bayesmag: wrote {path}")
    for line in limitations(args.format, ex):
        print(f"  {line}")
    return 0


def _progress(args) -> bool:
    """Progress bars unless ``--no-progress`` or nobody watches stderr (no carriage returns in logs)."""
    from bayesmag._src.app.terminal import interactive_output
    return not args.no_progress and interactive_output()


def _cmd_config(args) -> int:
    from bayesmag._src.app.config_docs import list_configs, show_config

    if args.action == "list":
        print(list_configs(packaged_configs_dir()), end="")
        return 0
    if not args.name:
        print("bayesmag config show: name a config, e.g. `bayesmag config show quickstart`", file=sys.stderr)
        return 2
    print(show_config(_resolve_config(args.name)), end="")
    return 0


#: The ``--help`` description of every subcommand.
DESCRIPTIONS = {
    "run": "Run a calibration job from a TOML config: fit, uncertainty, optional network and NUTS; writes the run "
           "folder (metrics.json, params.json, predictions.csv, calibration.json, report.md, report.html, figures).",
    "apply": "Apply a saved calibration to a recording: calibrated field with intervals, the transfer part for a new "
             "session, and the training-domain flag per row; scores it when reference columns are present.",
    "study": "The paper's simulation study: one simulated data set per size, the full job on each.",
    "report": "(Re)write the certificate report.md and report.html of a run folder from its files.",
    "export": "Write a run's calibration for firmware or another tool (json, c-header, ardupilot, px4, magcal) and "
              "print what the target cannot hold, with the accuracy lost on the run's held-out rows.",
    "discover": "Find physics missing from the calibration model (bayesmag discover --help for its options).",
    "data": "Named datasets: list them, or fetch one (sha256 verified).",
    "fleet": "Calibrate many sensors in one compiled batch: a calibration folder per sensor, fleet.json, verdicts "
             "against the [fleet.limits] and robust outliers against the fleet (docs/fleet.md).",
    "config": "The packaged configs: list them, or show one's keys with values, defaults, units and meaning.",
}


def _cmd_report(args) -> int:
    from bayesmag._src.app.report import write_report

    md = write_report(args.run_dir)
    print(f"bayesmag: wrote {md} and {md.with_suffix('.html')} (figures embedded)")
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
    r.add_argument("--field-unit", choices=["uT", "nT", "mT", "G"], default=None,
                   help="declare the field unit of the data file (converted to uT and trusted: e.g. uT for a "
                        "genuine low-field session); same as --set data.field_unit=...")
    r.set_defaults(func=_cmd_run)

    a = sub.add_parser("apply", help="apply a saved calibration to a recording (reference columns optional)")
    a.add_argument("--model", required=True, help="run folder written by `bayesmag run` (a vector or a field "
                                                    "calibration; a field run gives the calibrated field and its "
                                                    "magnitude interval)")
    a.add_argument("--data", required=True, help="the recording: a CSV or Parquet file with the canonical columns "
                   "(time,run,bx_meas,by_meas,bz_meas,temperature[,*_ref]; others via --columns), or an archive "
                   "(a folder of Parquet/CSV files or a glob: applied on Dask)")
    a.add_argument("--out", required=True, help="output CSV (for an archive: a folder, written as a Parquet dataset)")
    a.add_argument("--level", type=float, default=None, help="central interval level (default: the run's)")
    a.add_argument("--uq", choices=["auto", "analytic", "psqmc"], default="auto",
                   help="physics uncertainty method (auto, the default everywhere: analytic -- exact moments, "
                        "fastest -- where the model allows it, else psqmc)")
    a.add_argument("--n-params", type=int, default=100, help="Np for --uq psqmc")
    a.add_argument("--n-qmc", type=int, default=256, help="Nq for --uq psqmc")
    a.add_argument("--temperature-unit", choices=["C", "K"], default="C", help="temperature unit of --data")
    a.add_argument("--field-unit", choices=["uT", "nT", "mT", "G"], default=None,
                   help="declare the field unit of --data (converted to uT at load and trusted; default: uT, checked)")
    a.add_argument("--time-unit", choices=["s", "ms", "us", "min", "h"], default="s",
                   help="unit of --data's time column (converted to seconds; loggers often stamp ms or us since boot)")
    a.add_argument("--columns", metavar="NAME=COL,...",
                   help="map canonical columns to the file's, e.g. time=t,bx_meas=X,by_meas=Y,bz_meas=Z,temperature=T")
    a.add_argument("--no-progress", action="store_true")
    a.add_argument("--force", action="store_true",
                   help="replace an existing --out file that `bayesmag apply` did not write (never a recording, a "
                        "read-only file or a file of a run folder)")
    dk = a.add_argument_group("archives on Dask (--data a folder of Parquet or CSV files, or a glob such as "
                              "'logs/*.csv'; one file too with --scheduler; --out is then a folder of Parquet parts; "
                              "pip install 'bayesmag[dask]'; docs/fleet.md)")
    dk.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler (default: a local cluster)")
    dk.add_argument("--workers", type=int, default=2, help="local cluster: worker processes")
    dk.add_argument("--threads-per-worker", type=int, default=1, help="local cluster: threads per worker")
    dk.add_argument("--memory-limit", default="900MB", help="local cluster: memory limit per worker")
    dk.add_argument("--blocksize-mb", type=float, default=16.0, help="CSV bytes per partition (MB)")
    a.set_defaults(func=_cmd_apply)

    fl = sub.add_parser("fleet", help="calibrate many sensors in one batch; verdicts and outliers (docs/fleet.md)")
    fl.add_argument("config", help="fleet config (or a packaged one, e.g. fleet_simulated)")
    fl.add_argument("--out", help="output folder (default runs/<config name>)")
    fl.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a key, e.g. fleet.simulate.n_sensors=1000")
    fl.add_argument("--no-progress", action="store_true")
    fl.set_defaults(func=_cmd_fleet)

    st = sub.add_parser("study", help="the paper's simulation study over sample sizes")
    st.add_argument("config")
    st.add_argument("--out")
    st.add_argument("--set", action="append", metavar="KEY=VALUE")
    st.add_argument("--no-progress", action="store_true")
    st.set_defaults(func=_cmd_study)

    rp = sub.add_parser("report", help="(re)write report.md and report.html in a run folder")
    rp.add_argument("run_dir")
    rp.set_defaults(func=_cmd_report)

    ex = sub.add_parser("export", help="write a run's calibration for firmware/other tools")
    ex.add_argument("run_dir", help="run folder written by `bayesmag run`")
    ex.add_argument("--format", required=True, choices=["json", "c-header", "ardupilot", "px4", "magcal"])
    ex.add_argument("--out", help="output file (default RUN_DIR/calibration.<ext>)")
    ex.add_argument("--temperature", type=float, default=None,
                    help="reference temperature (C) of the hard/soft-iron and PX4 forms (default: median training temperature)")
    ex.add_argument("--force", action="store_true",
                    help="replace an existing --out file that bayesmag export did not write (never a file of a run "
                         "folder or the training recording); also export a fleet sensor whose data cannot inform "
                         "every parameter (fleet verdict 'unidentifiable')")
    ex.set_defaults(func=_cmd_export)

    dc = sub.add_parser("discover", help="find physics missing from the calibration model", add_help=False)
    dc.add_argument("rest", nargs=argparse.REMAINDER)
    dc.set_defaults(func=lambda a: __import__("bayesmag._src.app.discover_cli", fromlist=["main"]).main(a.rest))

    d = sub.add_parser("data", help="named datasets: list, fetch")
    d.add_argument("action", choices=["fetch", "list"])
    d.add_argument("name", nargs="?")
    d.add_argument("--force", action="store_true", help="download again even if present")
    d.set_defaults(func=_cmd_data)

    cf = sub.add_parser("config", help="packaged configs: list, show NAME (keys, defaults, units, meaning)")
    cf.add_argument("action", choices=["list", "show"])
    cf.add_argument("name", nargs="?", help="config name (e.g. quickstart) or file, for show")
    cf.set_defaults(func=_cmd_config)
    for name, sp in sub.choices.items():
        sp.description = sp.description or DESCRIPTIONS[name]
    return p


def _cmd_discover(argv: list[str]) -> int:
    """``bayesmag discover``: check and lock --out before the search, then run discover's own CLI."""
    from bayesmag._src.app.config import read_config_dict
    from bayesmag._src.app.discover_cli import build_parser as discover_parser, default_out, main as discover_main, \
        resolve_config
    from bayesmag._src.app.outdir import reserve

    args = discover_parser().parse_args(argv)
    if bool(args.data) == bool(args.config):
        return discover_main(argv)          # discover names the usage error
    raw = read_config_dict(resolve_config(args.config), args.set or []) if args.config else {}
    name = Path(args.data).stem if args.data else raw.get("name", "bayesmag")
    out = Path(args.out) if args.out else default_out(name)
    data_table = raw.get("data") if isinstance(raw.get("data"), dict) else {}
    with reserve(out, inputs=[args.data, args.config, data_table.get("path")], kind="discover"):
        return discover_main(argv)


def _one_line(e: BaseException) -> str:
    if isinstance(e, OSError) and e.strerror and not type(e).__module__.startswith("bayesmag"):
        where = f" {e.filename}" if e.filename else ""
        return f"cannot use{where}: {e.strerror}" + (f" (errno {e.errno})" if e.errno else "")
    return " ".join(str(e).split())


def main(argv: list[str] | None = None) -> int:
    """The console entry point; ``argv`` None (the ``bayesmag`` command) also installs the signal handling.

    Ctrl-C / SIGTERM then print one line and end the process with status 130 / 143 within about
    a second (:mod:`~bayesmag._src.app.signals`); a call with ``argv`` from Python leaves signals alone.
    """
    console = argv is None
    argv = sys.argv[1:] if argv is None else list(argv)
    if not console:
        return _main(argv)
    import os

    from bayesmag._src.app.signals import Interrupted, announce, handling
    with handling():
        try:
            rc = _main(argv)
        except Interrupted as e:
            announce(e.signum)
            sys.stdout.flush()
            os._exit(e.code)                # no waiting for training threads to finish their batch
    import gc
    gc.freeze()         # every file is written and closed: the exit skips a last walk of the heap (~0.5 CPU-s)
    return rc


def _main(argv: list[str]) -> int:
    from bayesmag._src.core.cache import ensure_compile_cache
    ensure_compile_cache(default=True)      # before the first compilation: on unless BAYESMAG_COMPILE_CACHE=0
    from bayesmag._src.app.artifact import ArtifactError
    from bayesmag._src.app.config import ConfigError
    from bayesmag._src.core.data import DataError
    from bayesmag._src.app.job import JobError
    from bayesmag._src.app.outdir import OutputError

    import warnings

    from bayesmag._src.core.data import CalibrationWarning, DataNote

    expected = (ConfigError, DataError, JobError, ArtifactError, OutputError, OSError)
    show = warnings.showwarning

    def note(message, category, *a, **k):       # a DataNote is one line on stderr, not a warning with a source line
        if issubclass(category, DataNote):
            print(f"bayesmag: note: {_one_line(message)}", file=sys.stderr)
        elif issubclass(category, CalibrationWarning):
            pass                                # the job prints each from metrics.json's warnings, once
        else:
            show(message, category, *a, **k)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", DataNote)
            warnings.showwarning = note
            if argv[:1] == ["discover"]:        # discover parses its own options (argparse REMAINDER drops --flags)
                return _cmd_discover(argv[1:])
            args = build_parser().parse_args(argv)
            return args.func(args)
    except BrokenPipeError:                 # `bayesmag run ... | head -1`: the reader left; the result is written
        import contextlib
        import os
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())   # no second error at exit's flush
        return 0
    except expected as e:
        print(f"bayesmag: error: {_one_line(e)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
