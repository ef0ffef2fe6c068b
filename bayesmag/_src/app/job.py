"""The config-driven calibration job: load, split, :func:`~bayesmag.calibrate`, write.

The computing is the library's (:func:`~bayesmag._src.pipeline.calibrate.calibrate` on library
settings, ``Config.settings()``); this module loads the data, splits it, checks it, scores the
:class:`~bayesmag._src.pipeline.calibrate.CalibrationRun` into ``metrics.json`` and writes the files.
:func:`run_job` writes everything into a temporary sibling folder and renames it to the
output folder only when the whole job has succeeded, so a failed run never leaves a
half-written folder that looks complete.
"""

from __future__ import annotations

import contextlib
import csv
import time
from pathlib import Path

import numpy as np

from bayesmag._src.core.jsonio import write_json
from bayesmag._src.app.config import Config, ConfigError, config_error, to_toml
from bayesmag._src.core.data import AXES, CalibrationData, DataError, check_time_order, make_split, validate
from bayesmag._src.app.inputs import load_data
from bayesmag._src.core.fit import PhysicsFit
from bayesmag._src.core.physics import PhysicsModel
from bayesmag._src.app.outdir import staging_dir
from bayesmag._src.core.predictor import UQOptions
from bayesmag._src.core import metrics as M
from bayesmag._src.pipeline.settings import input_noise_warning
from bayesmag._src.pipeline.stages import CalibrationError, PhysicsStage, residual_variance

__all__ = ["run_job", "run_physics_stage", "load_data", "build_model", "resolve_sigma_in", "uq_options", "JobError",
           "JobResult", "PhysicsStage", "job_metrics", "write_predictions"]


#: The job could not finish; the message says why and what to change (the library's :class:`CalibrationError`).
JobError = CalibrationError


def build_model(cfg: Config, train: CalibrationData) -> PhysicsModel:
    """The physics model of ``[physics]`` for the training rows (T0 resolved once, :func:`resolve_t0`)."""
    from bayesmag._src.pipeline.settings import PhysicsSettings
    p = cfg.physics
    try:
        return PhysicsSettings(t0=p.t0, temperature_terms=p.temperature_terms, extra_terms=tuple(p.extra_terms),
                               covariance=p.covariance).model(train)
    except (ValueError, TypeError) as e:
        if str(e).startswith("t0 = "):
            raise ConfigError(f"Config key 'physics.t0' = {str(e)[5:]}") from None
        raise ConfigError(f"[physics] extra_terms: {e}") from None


def time_order_reasons(cfg: Config, model: PhysicsModel) -> list[str]:
    """What in this job takes the rows in time order (so unsorted rows are refused): the time-block split, a model
    whose rows depend on their neighbours, an autocorrelation-aware covariance, the session model's AR(1) noise."""
    return [cfg.split.kind == "time_blocks" and "the time-block split",
            model.needs_series and "the model's " + ", ".join(
                [c.name for c in model.transforms] + [t.name for t in model.terms if t.history]),
            cfg.physics.covariance != "white" and f"the {cfg.physics.covariance} covariance",
            str(cfg.uq.transfer).startswith("hierarchical") and "the session model's AR(1) noise"]


def resolve_sigma_in(cfg: Config, train: CalibrationData) -> tuple[np.ndarray, str]:
    """The (4, 4) input-noise covariance of ``[uq] sigma_in`` and where it came from."""
    from bayesmag._src.pipeline.settings import sigma_in_matrix
    try:
        return sigma_in_matrix(cfg.uq.sigma_in, train)
    except ValueError:
        raise ConfigError("Config key 'uq.sigma_in' as a 4x4 matrix must be symmetric positive semi-definite.") from None


def _residual_variance(cfg: Config, fit: PhysicsFit, train: CalibrationData, sigma_in: np.ndarray) -> np.ndarray:
    return residual_variance(cfg.uq, fit, train, sigma_in)      # reads method, n_params, n_qmc, seed, chunk_size


class JobResult(dict):
    """What a job computed (metrics, fit, uq, predictor, ``run``: the :class:`CalibrationRun`, ...) beside
    the files it wrote. Built once by :func:`run_job` from the frozen run; a dict so that callers index it by name.
    """


def _per_axis(v) -> dict:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    return {ax: float(x) for ax, x in zip(AXES, v)}


def write_predictions(path: Path, data: CalibrationData, rows: np.ndarray, columns: dict[str, np.ndarray]) -> None:
    """CSV of per-row predictions: identifiers, then ``{axis}_{column}`` for every column (n, 3)."""
    header = ["row", "time", "run", "temperature"] + [f"{ax}_{c}" for ax in AXES for c in columns]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        cols = list(columns.values())
        for k in range(data.n):
            rec = [int(rows[k]), f"{data.time[k]:.6f}", int(data.run[k]), f"{data.temperature[k]:.10g}"]
            for a in range(3):
                for c in cols:
                    v = c[k, a]
                    rec.append(bool(v) if isinstance(v, (np.bool_, bool)) else v if isinstance(v, str)
                               else f"{float(v):.8g}")
            w.writerow(rec)


def uq_options(cfg: Config) -> UQOptions:
    u = cfg.uq
    return UQOptions(method=u.method, n_params=u.n_params, n_qmc=u.n_qmc, seed=u.seed, chunk_size=u.chunk_size)


def run_physics_stage(cfg: Config, train: CalibrationData, test: CalibrationData, model: PhysicsModel,
                      domain, timings: dict[str, float], *, progress: bool = False) -> PhysicsStage:
    """The physics stage with the settings of ``cfg`` (:func:`~bayesmag._src.pipeline.stages.run_physics_stage`)."""
    from bayesmag._src.pipeline import stages
    return stages.run_physics_stage(cfg.settings().uq, train, test, model, domain, timings,
                                    covariance=cfg.physics.covariance, progress=progress)


def run_job(cfg: Config, out: str | Path, *, progress: bool | None = None, figure_worker=False) -> JobResult:
    """Run the calibration job described by ``cfg`` and write its outputs into ``out``.

    Figures (``[output] figures``) are drawn in this process by default, after
    :func:`~bayesmag.calibrate`: a library call spawns nothing and never re-imports the caller's
    ``__main__``. ``figure_worker=True`` (the command line, unless ``BAYESMAG_FIGURE_WORKER=0``) shares
    them with one child process (:class:`~bayesmag._src.app.figure_worker.FigureWorker`, which exits
    when this process does): both draw from one queue of figure tasks after the training. A started
    ``FigureWorker`` may be given instead (the command line starts it before its own imports; the
    caller closes it). The output folder is swapped in only after they are all drawn. ``progress``:
    None (default) draws bars as ``[output] progress`` says, but only where someone watches (stderr a
    terminal, or a Jupyter kernel: never into a log); True / False force it.
    """
    from bayesmag._src.core.cache import compile_cache, release_compiled_if_crowded
    from bayesmag._src.app.figure_worker import JOB_BARE, JOB_MODULES, FigureWorker, InlineFigures, figures
    from bayesmag._src.app.outdir import reserve
    release_compiled_if_crowded()           # many jobs in one process: stay under the kernel's mapping limit
    with reserve(out, inputs=[cfg.data.path], kind="run"):      # refuse a foreign or locked --out before any work
        # [output] compile_cache: on or off for this job only (the environment variable wins); "auto" leaves
        # the process's setting (on from the command line, the caller's from Python)
        cc = cfg.output.compile_cache
        with contextlib.nullcontext() if cc == "auto" else compile_cache(bool(cc)):
            drawer = (contextlib.nullcontext(figure_worker if cfg.output.figures else InlineFigures(False))
                      if isinstance(figure_worker, FigureWorker)
                      else figures(cfg.output.figures, worker=bool(figure_worker), preload=JOB_MODULES,
                                   bare=JOB_BARE))
            with drawer as figs:
                figs.warm()                         # its interpreter starts while the physics stage runs
                return _run_job(cfg, out, figs, progress=progress)


def _run_job(cfg: Config, out: str | Path, figs, *, progress: bool | None = None) -> JobResult:
    if progress is None:                    # [output] progress, and only where someone watches (no \r in logs)
        from bayesmag._src.app.terminal import interactive_output
        progress = cfg.output.progress and interactive_output()
    if cfg.measurement.kind != "vector" or cfg.data.source == "field_simulated":   # field calibration (docs/field.md)
        from bayesmag._src.app.field_job import run_field_job
        return JobResult(run_field_job(cfg, out, progress=progress))
    t_all = time.perf_counter()

    t = time.perf_counter()
    if cfg.network.enabled:                 # bad likelihood names and network settings fail before any work
        from bayesmag._src.pipeline.hybrid import check_network_config
        check_network_config(cfg)
    data = load_data(cfg)
    try:
        split = make_split(data, kind=cfg.split.kind, test_fraction=cfg.split.test_fraction, seed=cfg.split.seed,
                           test_runs=cfg.split.test_runs, n_blocks=cfg.split.n_blocks)
    except ValueError as e:
        raise ConfigError(f"[split]: {e}") from None
    train, test = data.subset(split.train), data.subset(split.test)
    model = build_model(cfg, train)
    validate(data, n_params=model.n_params, origin=data.source,
             need_temperature_variation=cfg.physics.temperature_terms,
             allow_duplicate_times=False)
    check_time_order(data, time_order_reasons(cfg, model), origin=data.source)
    if train.n < model.n_params + 1:
        raise ConfigError(f"[split] leaves {train.n} training rows of {data.n} ({split.description}), but the physics "
                          f"model has {model.n_params} parameters per axis: at least {model.n_params + 1} training rows "
                          f"are needed (many more for a useful calibration). Lower split.test_fraction or give "
                          f"more data.")
    if cfg.physics.temperature_terms and np.ptp(train.temperature) < 1e-6:
        raise DataError("The training rows have constant temperature: Ks and Ko are not identifiable. "
                        "Set [physics] temperature_terms = false or use a split that keeps temperature variation.")
    if not isinstance(cfg.uq.sigma_in, str):
        resolve_sigma_in(cfg, train)        # a bad [uq] sigma_in matrix fails before any work
    nuts_priors = None
    if cfg.nuts.enabled:                    # check NUTS settings and priors now (once), not after the fit
        from bayesmag._src.app.nuts_stage import check_nuts_config
        nuts_priors = check_nuts_config(cfg, model.param_names)
    settings = cfg.settings(nuts_priors=nuts_priors)
    load_s = time.perf_counter() - t

    from bayesmag._src.pipeline.calibrate import calibrate
    from bayesmag._src.pipeline.hybrid import NetworkSizeError

    def physics_figures(ps) -> None:
        """The physics figures as tasks, queued as soon as the physics stage is done: the figure process draws
        them while the networks train, instead of after the training."""
        from bayesmag._src.app import plots
        lo, hi = ps.prediction.interval(cfg.uq.level)
        physics_columns = {"reference": test.b_ref, "predicted": ps.uq.mean, "lower": lo, "upper": hi,
                           "total": ps.prediction.total}      # the columns they show, as job_metrics makes them
        tasks = plots.physics_figure_tasks(test, physics_columns, {
            "train": train, "train_residual": ps.fit.residuals(train, (data, split.train)),
            "pit": M.pit(ps.prediction.dist, test.b_ref), "level": cfg.uq.level})
        for draw, args, kwargs in plots.by_cost(tasks):     # the most expensive first
            figs.submit(draw, *args, **kwargs)

    try:
        run = calibrate(train, settings, test=test, progress=progress, series=(data, split.train, split.test),
                        on_physics=physics_figures if cfg.output.figures else None)
    except NetworkSizeError as e:
        raise config_error(e, "network", cfg.network.table()) from None
    timings = {"load": load_s, **run.timings}
    ps = run.physics
    metrics, columns = job_metrics(cfg, run, data, split, test)

    writers: list = []              # writer(staging_dir) for stage files, called in the staging folder
    if cfg.output.figures:
        from bayesmag._src.app import plots
        tasks = []
        if run.hybrid is not None:
            from bayesmag._src.app.hybrid_outputs import hybrid_figure_tasks
            tasks += hybrid_figure_tasks(run.hybrid, columns, test, cfg.uq.level)
        tasks.append(plots.residual_histogram_task(columns["reference"], ps.uq.mean, columns.get("hybrid_predicted")))
        for draw, args, kwargs in plots.by_cost(tasks):
            figs.submit(draw, *args, **kwargs)
    if run.hybrid is not None:
        from bayesmag._src.app.hybrid_outputs import hybrid_writers
        writers += hybrid_writers(cfg, run.hybrid, columns, test, cfg.uq.level, figures=False)
    if run.nuts is not None:
        from bayesmag._src.app.nuts_outputs import write_nuts_outputs
        res, figures = run.nuts, cfg.output.figures
        writers.append(lambda staging: write_nuts_outputs(res, staging, figures=figures))

    ps, hs = run.physics, run.hybrid
    extra = {} if hs is None else {"networks": hs.networks, "hybrid": hs.predictions,
                                   "primary_likelihood": hs.primary}
    if run.nuts is not None:
        extra["nuts"] = run.nuts
    result = JobResult(config=cfg, data=data, split=split, fit=run.fit, uq=ps.uq, metrics=metrics,
                       sigma_in=ps.sigma_in, domain=run.domain, residual_sd=ps.residual_sd, network_artifact=None,
                       physics=ps, predictor=run.predictor, run=run, writers=tuple(writers), **extra)

    with staging_dir(Path(out), kind="run") as tmp:
        t = time.perf_counter()
        write_json(tmp / "params.json", run.fit.to_json())
        write_predictions(tmp / "predictions.csv", test, split.test, columns)
        (tmp / "config.resolved.toml").write_text(to_toml(cfg.to_dict()))
        from bayesmag._src.app.artifact import save_calibration
        save_calibration(tmp, run.predictor, config=cfg.to_dict(), level=cfg.uq.level)
        from bayesmag._src.app.artifact import ArtifactError, read_calibration
        try:                    # what `apply` and `export` will load: never report success for a file they refuse
            read_calibration(tmp)
        except ArtifactError as e:
            raise JobError(f"bayesmag wrote a calibration its own loader refuses ({e}); nothing was written to "
                           f"{out}. Please report this as a bug.") from None
        for writer in writers:                      # stage files (and NUTS figures), while the figure
            writer(tmp)                             # process draws
        figs.finish(tmp)                            # this process draws the figures the worker has not taken
        timings["write"] = time.perf_counter() - t     # files and figures (total: the whole job)
        timings["total"] = time.perf_counter() - t_all
        metrics["timings"] = {k: round(v, 4) for k, v in timings.items()}
        write_json(tmp / "metrics.json", metrics)
        from bayesmag._src.app.report import write_report
        write_report(tmp, require_marker=False)     # the staging folder: its marker says incomplete
    return result


def job_metrics(cfg: Config, run, data: CalibrationData, split, test: CalibrationData) -> tuple[dict, dict]:
    """``metrics.json`` (without timings) and the ``predictions.csv`` columns of a :class:`CalibrationRun`
    scored on the ``test`` rows (pure: a function of the run and the rows)."""
    ps, fit, uq, domain = run.physics, run.fit, run.physics.uq, run.domain
    train = data.subset(split.train)
    y = test.b_ref
    level = cfg.uq.level
    phys_scores = M.score_per_axis(y, ps.prediction.dist, level, mean=ps.prediction.mean)
    paper_scores = M.score_per_axis(y, ps.paper_prediction.dist, level, mean=ps.paper_prediction.mean)
    lo, hi = ps.prediction.interval(level)
    resid_train = fit.residuals(train, (data, split.train))      # within the recording for a thermal lag
    from bayesmag._src.core.domain import budget_row_mask, budget_rows_note
    outside = domain.outside(test, uq.mean)
    budget_rows = budget_row_mask(outside)
    metrics = {
        "raw": {"rmse": _per_axis(M.rmse(y, test.b_meas)), "mae": _per_axis(M.mae(y, test.b_meas))},
        "physics": phys_scores,
        "physics_paper_total": {k: paper_scores[k] for k in ("coverage", "nll", "crps", "mean_width")},
        "physics_in_sample": {
            "rmse": _per_axis(fit.rmse_in_sample),
            "residual_std_error": _per_axis(np.sqrt(fit.s2)),
            "mae": _per_axis(np.mean(np.abs(resid_train), axis=0)),
        },
        "uq": {"method": cfg.uq.method, "n_params": cfg.uq.n_params, "n_qmc": cfg.uq.n_qmc, "level": cfg.uq.level,
               "sigma_in_sd": dict(zip(["bx", "by", "bz", "T"], map(float, np.sqrt(np.diag(ps.sigma_in))))),
               "sigma_in_source": ps.sigma_source, "residual_term": _per_axis(ps.residual_sd),
               "mean_aleatoric": _per_axis(uq.aleatoric[budget_rows].mean(0)),
               "mean_epistemic": _per_axis(uq.epistemic[budget_rows].mean(0)),
               # the certificate's budget: root mean square over the rows, so u_c^2 is the rows' mean variance
               "rms_aleatoric": _per_axis(np.sqrt(np.mean(uq.aleatoric[budget_rows] ** 2, axis=0))),
               "rms_epistemic": _per_axis(np.sqrt(np.mean(uq.epistemic[budget_rows] ** 2, axis=0))),
               "budget_rows": budget_rows_note(outside), "budget_rows_in_domain": int((~outside.any(axis=1)).sum())},
        "split": split.as_dict(),
        "data": {"source": data.source, "n_rows": data.n, "runs": [int(r) for r in data.runs],
                 "train_runs": [int(r) for r in np.unique(train.run)]},
    }
    metrics["field"] = {"raw": M.field_metrics(test.b_meas, y, test.run),
                        "physics": M.field_metrics(ps.prediction.mean, y, test.run)}
    from bayesmag._src.app.report import certificate_record
    metrics["certificate"] = certificate_record(cfg, data)
    metrics["domain"] = domain.summary(test, uq.mean)
    metrics["transfer"] = {**ps.transfer.as_dict(), "n_test_rows_new_session": int(ps.new_session.sum())}
    from bayesmag._src.core.data import time_step_warning
    metrics["warnings"] = [w for w in [time_step_warning(data), *fit.design_warnings, domain.warning(test, uq.mean),
                                       ps.transfer.warning, input_noise_warning(ps.sigma_source, uq.aleatoric, ps.fit)]
                           if w]
    columns = {
        "measured": test.b_meas, "reference": y, "predicted": uq.mean,
        "aleatoric_physics": uq.aleatoric, "epistemic_physics": uq.epistemic,
        "residual_physics": ps.prediction.residual_physics, "transfer": ps.prediction.transfer,
        "total": ps.prediction.total, "lower": lo, "upper": hi, "covered": (y >= lo) & (y <= hi),
        "in_domain": np.broadcast_to(~outside.any(axis=1)[:, None], y.shape),
        "in_domain_reason": np.broadcast_to(domain.reasons(outside)[:, None], y.shape),
    }
    if run.hybrid is not None:
        from bayesmag._src.pipeline.hybrid import hybrid_columns, hybrid_metrics
        metrics.update(hybrid_metrics(run.hybrid, y, uq.mean, level, cfg.network.mc_passes))
        metrics["field"].update({f"hybrid ({name})": M.field_metrics(p.mean, y, test.run)
                                 for name, p in run.hybrid.predictions.items()})
        columns = {**columns, **hybrid_columns(run.hybrid, y, level)}
        metrics["warnings"].extend(w for w in run.hybrid.nan_messages if w not in metrics["warnings"])
    if run.nuts is not None:
        metrics["nuts"] = run.nuts.metrics()
        metrics["warnings"].extend(w for w in run.nuts.warnings if w not in metrics["warnings"])   # each once
    return metrics, columns
