"""The config-driven calibration job: data -> split -> physics fit -> physics UQ -> (network) -> outputs.

:func:`run_job` writes everything into a temporary sibling folder and renames it to the
output folder only when the whole job has succeeded, so a failed run never leaves a
half-written folder that looks complete.
"""

from __future__ import annotations

import csv
import dataclasses
import time
from pathlib import Path

import numpy as np

from bayesmag._src.core.jsonio import write_json
from bayesmag._src.app.config import Config, ConfigError, to_toml
from bayesmag._src.core.data import AXES, CalibrationData, DataError, load_csv, make_split, validate
from bayesmag._src.core.datasets import load_dataset
from bayesmag._src.core.fit import PhysicsFit, fit_physics
from bayesmag._src.core.catalogue import make_extra
from bayesmag._src.core.physics import PhysicsModel, inputs_from_data
from bayesmag._src.app.outdir import staging_dir
from bayesmag._src.core.physics_uq import PhysicsUQ, estimate_input_noise, physics_uncertainty
from bayesmag._src.core.predictor import Components, Prediction, Predictor, TransferEstimate, UQOptions, estimate_transfer
from bayesmag._src.core import metrics as M

__all__ = ["run_job", "run_physics_stage", "load_data", "build_model", "resolve_sigma_in", "uq_options", "JobError",
           "JobResult", "PhysicsStage"]


class JobError(RuntimeError):
    """The job could not finish; the message says why and what to change."""


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


def build_model(cfg: Config, train: CalibrationData) -> PhysicsModel:
    t0 = float(np.mean(train.temperature)) if cfg.physics.t0 == "mean" else float(cfg.physics.t0)
    try:
        extra = tuple(make_extra(s, t0=t0) for s in cfg.physics.extra_terms)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"[physics] extra_terms: {e}") from None
    return PhysicsModel.paper(t0=t0, temperature=cfg.physics.temperature_terms, extra=extra)


def resolve_sigma_in(cfg: Config, train: CalibrationData) -> tuple[np.ndarray, str]:
    s = cfg.uq.sigma_in
    if s == "auto":
        return estimate_input_noise(train), "auto: within-run second differences, 1.4826*MAD/sqrt(6)"
    arr = np.asarray(s, dtype=np.float64)
    if arr.ndim == 1:
        return np.diag(arr**2), "config: standard deviations"
    if not np.allclose(arr, arr.T) or np.linalg.eigvalsh(arr).min() < -1e-12:
        raise ConfigError("Config key 'uq.sigma_in' as a 4x4 matrix must be symmetric positive semi-definite.")
    return arr, "config: covariance matrix"


def _residual_variance(cfg: Config, fit: PhysicsFit, train: CalibrationData, sigma_in: np.ndarray) -> np.ndarray:
    """Per-axis residual variance beyond the propagated input noise, from the training rows only.

    ``max(s^2 - mean_train(aleatoric^2), 0)``: a fixed property of the calibration (stored in the
    artifact), so applying it later gives the same intervals as the run itself.
    """
    exact = fit.model.is_linear and fit.model.degree is not None
    uq = physics_uncertainty(fit, inputs_from_data(train), sigma_in=sigma_in,
                             method="analytic" if exact else cfg.uq.method,
                             n_params=min(cfg.uq.n_params, 50), n_qmc=min(cfg.uq.n_qmc, 256), seed=cfg.uq.seed,
                             chunk_size=cfg.uq.chunk_size)
    return np.maximum(fit.s2 - np.mean(uq.aleatoric**2, axis=0), 0.0)


class JobResult(dict):
    """What a job computed (metrics, fit, uq, predictor, ...) beside the files it wrote.

    Assembled by :func:`run_job` alone from the typed stage results (:class:`PhysicsStage`,
    :class:`~bayesmag._src.pipeline.hybrid.HybridStage`, :class:`~bayesmag.NutsResult`); no stage writes into it.
    A dict so that callers index it by name.
    """


@dataclasses.dataclass(frozen=True)
class PhysicsStage:
    """The physics stage's result: fit, noise model, predictor, and its prediction of the test rows."""

    fit: PhysicsFit
    sigma_in: np.ndarray
    sigma_source: str
    residual_sd: np.ndarray
    predictor: Predictor
    uq: PhysicsUQ                  # physics part on the test rows (shared with the hybrid stage)
    prediction: Prediction         # physics-only predictive distribution (with the residual term)
    paper_prediction: Prediction   # the paper's physics total sqrt(alea^2 + epi^2), for comparison
    transfer: TransferEstimate     # between-session sd (zero with method "off")
    new_session: np.ndarray        # (n_test,) test rows from runs the fit did not see (they get the transfer part)


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
            rec = [int(rows[k]), f"{data.time[k]:.6f}", int(data.run[k]), f"{data.temperature[k]:.6g}"]
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
    """Fit the physics model on ``train`` and predict ``test`` through a :class:`Predictor`."""
    t = time.perf_counter()
    fit = fit_physics(train, model, covariance_method=cfg.physics.covariance)
    timings["physics_fit"] = time.perf_counter() - t
    if not fit.converged:
        raise JobError(f"The Levenberg-Marquardt fit did not converge: {dict(zip(AXES, fit.result))}. "
                       "Check the data for outliers or give a better starting point.")

    t = time.perf_counter()
    sigma_in, sigma_src = resolve_sigma_in(cfg, train)
    # The paper's physics total sqrt(alea^2 + epi^2) leaves out the scatter the fit could not explain
    # (reference noise, model discrepancy): its 95% intervals cover 39-46% on the paper split. The residual
    # term is the fit's residual variance beyond what the propagated input noise already accounts for.
    resid_var = _residual_variance(cfg, fit, train, sigma_in) if cfg.uq.residual_term else np.zeros(3)
    predictor = Predictor(fit=fit, sigma_in=sigma_in, residual_sd=np.sqrt(resid_var), domain=domain,
                          uq=uq_options(cfg))
    uq = predictor.physics_part(test, progress=progress)
    timings["physics_uq"] = time.perf_counter() - t

    t = time.perf_counter()
    sessions = None
    if cfg.uq.transfer == "loro":
        tr = estimate_transfer(train, fit)       # leave-one-run-out folds in one compiled fit
    elif cfg.uq.transfer.startswith("hierarchical"):
        from bayesmag._src.pipeline.sessions import hierarchical_transfer
        tr, sessions = hierarchical_transfer(train, fit, method="nuts" if cfg.uq.transfer.endswith("nuts") else
                                             "laplace", level=cfg.uq.level, seed=cfg.uq.seed)
    else:
        tr = TransferEstimate(np.zeros(3), "off", {})
    predictor = dataclasses.replace(predictor, transfer_sd=None if sessions is not None else tr.sd,
                                    sessions=sessions)
    timings["transfer"] = time.perf_counter() - t
    new = ~np.isin(test.run, train.run)
    comp = Components(uq, None, predictor.transfer_part(test))
    paper = dataclasses.replace(predictor, residual_sd=np.zeros(3), transfer_sd=None)
    return PhysicsStage(fit, sigma_in, sigma_src, np.sqrt(resid_var), predictor, uq,
                        predictor.compose(comp, new_session=new), paper.compose(comp), tr, new)


def run_job(cfg: Config, out: str | Path, *, progress: bool | None = None, figure_worker: bool = False) -> JobResult:
    """Run the calibration job described by ``cfg`` and write its outputs into ``out``.

    Figures (``[output] figures``) are drawn in this process by default: a library call spawns
    nothing and never re-imports the caller's ``__main__``. ``figure_worker=True`` (the command
    line with ``BAYESMAG_FIGURE_WORKER=1``) draws the physics stage's figures in one child process
    (:class:`~bayesmag._src.app.figure_worker.FigureWorker`), which exits when this process does:
    right after the physics stage when there is no network, else after the training (whose
    threads keep the cores busy) while this process draws the hybrid stage's. The output folder
    is swapped in only after they are all drawn.
    """
    from bayesmag._src.core.cache import compile_cache
    from bayesmag._src.app.figure_worker import figures
    from bayesmag._src.app.outdir import reserve
    with reserve(out, inputs=[cfg.data.path]):      # refuse a foreign or locked --out before any work
        # [output] compile_cache: on or off for this job only (the environment variable wins)
        with compile_cache(cfg.output.compile_cache):
            with figures(cfg.output.figures, worker=figure_worker) as figs:
                figs.warm()                         # its interpreter starts while the physics stage runs
                return _run_job(cfg, out, figs, progress=progress)


def _run_job(cfg: Config, out: str | Path, figs, *, progress: bool | None = None) -> JobResult:
    progress = cfg.output.progress if progress is None else progress
    if cfg.measurement.kind != "vector" or cfg.data.source == "field_simulated":   # field calibration (docs/field.md)
        from bayesmag._src.app.field_job import run_field_job
        return JobResult(run_field_job(cfg, out, progress=progress))
    timings: dict[str, float] = {}
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
    if train.n < model.n_params + 1:
        raise ConfigError(f"[split] leaves {train.n} training rows of {data.n} ({split.description}), but the physics "
                          f"model has {model.n_params} parameters per axis: at least {model.n_params + 1} training rows "
                          f"are needed (many more for a useful calibration). Lower split.test_fraction or give "
                          f"more data.")
    if cfg.physics.temperature_terms and np.ptp(train.temperature) < 1e-6:
        raise DataError("The training rows have constant temperature: Ks and Ko are not identifiable. "
                        "Set [physics] temperature_terms = false or use a split that keeps temperature variation.")
    nuts_priors = None
    if cfg.nuts.enabled:                    # check NUTS settings and priors now (once), not after the fit
        from bayesmag._src.app.nuts_stage import check_nuts_config
        nuts_priors = check_nuts_config(cfg, model.param_names)
    timings["load"] = time.perf_counter() - t

    from bayesmag._src.core.domain import Domain
    domain = Domain.from_data(train)
    ps = run_physics_stage(cfg, train, test, model, domain, timings, progress=progress)
    fit, uq, sigma_in = ps.fit, ps.uq, ps.sigma_in

    y = test.b_ref
    level = cfg.uq.level
    phys_scores = M.score_per_axis(y, ps.prediction.dist, level, mean=ps.prediction.mean)
    paper_scores = M.score_per_axis(y, ps.paper_prediction.dist, level, mean=ps.paper_prediction.mean)
    lo, hi = ps.prediction.interval(level)
    resid_train = train.b_ref - fit.predict(inputs_from_data(train))
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
               "sigma_in_sd": dict(zip(["bx", "by", "bz", "T"], map(float, np.sqrt(np.diag(sigma_in))))),
               "sigma_in_source": ps.sigma_source, "residual_term": _per_axis(ps.residual_sd),
               "mean_aleatoric": _per_axis(uq.aleatoric.mean(0)), "mean_epistemic": _per_axis(uq.epistemic.mean(0))},
        "split": split.as_dict(),
        "data": {"source": data.source, "n_rows": data.n, "runs": [int(r) for r in data.runs]},
    }
    metrics["field"] = {"raw": M.field_metrics(test.b_meas, y, test.run),
                        "physics": M.field_metrics(ps.prediction.mean, y, test.run)}
    from bayesmag._src.app.report import certificate_record
    metrics["certificate"] = certificate_record(cfg, data)
    metrics["domain"] = domain.summary(test, uq.mean)
    metrics["transfer"] = {**ps.transfer.as_dict(), "n_test_rows_new_session": int(ps.new_session.sum())}
    warnings_ = [w for w in [domain.warning(test, uq.mean), ps.transfer.warning] if w]
    metrics["warnings"] = warnings_
    outside = domain.outside(test, uq.mean)
    result = JobResult(config=cfg, data=data, split=split, fit=fit, uq=uq, metrics=metrics, sigma_in=sigma_in,
                       domain=domain, residual_sd=ps.residual_sd, network_artifact=None, physics=ps,
                       predictor=ps.predictor)
    columns = {
        "measured": test.b_meas, "reference": y, "predicted": uq.mean,
        "aleatoric_physics": uq.aleatoric, "epistemic_physics": uq.epistemic,
        "residual_physics": ps.prediction.residual_physics, "transfer": ps.prediction.transfer,
        "total": ps.prediction.total, "lower": lo, "upper": hi, "covered": (y >= lo) & (y <= hi),
        "in_domain": np.broadcast_to(~outside.any(axis=1)[:, None], y.shape),
        "in_domain_reason": np.broadcast_to(domain.reasons(outside)[:, None], y.shape),
    }

    physics_figure_task = ()
    if cfg.output.figures:
        from bayesmag._src.app.plots import physics_figures
        physics_figure_task = (physics_figures, test, {k: columns[k] for k in ("measured", "predicted", "reference",
                                                                               "total", "lower", "upper")},
                               {"train": train, "train_residual": resid_train,
                                "pit": M.pit(ps.prediction.dist, y), "level": level})

    writers: list = []              # (name, writer(staging_dir)) for stage files, called in the staging folder
    hs = None
    if not cfg.network.enabled:
        if physics_figure_task:
            figs.submit(*physics_figure_task)
    else:
        from bayesmag._src.pipeline.hybrid import hybrid_columns, hybrid_metrics, hybrid_writers, run_hybrid_stage
        hs = run_hybrid_stage(cfg, ps.predictor, uq, train, test, timings, new_session=ps.new_session,
                              progress=progress)
        # after the training, not during it: its threads keep both cores of a 2-core machine busy, and
        # figures drawn alongside only slowed it (2.8 s of 9.7); now they are drawn while this process
        # draws the hybrid stage's
        if physics_figure_task:
            figs.submit(*physics_figure_task)
        metrics.update(hybrid_metrics(hs, y, uq.mean, level, cfg.network.mc_passes))
        metrics["field"].update({f"hybrid ({name})": M.field_metrics(p.mean, y, test.run)
                                 for name, p in hs.predictions.items()})
        columns = {**columns, **hybrid_columns(hs, y, level)}
        result.update(networks=hs.networks, hybrid=hs.predictions, primary_likelihood=hs.primary,
                      predictor=hs.predictors[hs.primary])
        writers += hybrid_writers(cfg, hs, columns, test, level)
    if cfg.nuts.enabled:
        from bayesmag._src.pipeline.nuts import write_nuts_outputs
        from bayesmag._src.app.nuts_stage import run_nuts_stage
        t = time.perf_counter()
        res = run_nuts_stage(cfg, fit, train, nuts_priors, progress=progress)
        timings["nuts"] = time.perf_counter() - t
        result["nuts"] = res
        metrics["nuts"] = res.metrics()
        metrics["warnings"].extend(w for w in res.warnings if w not in metrics["warnings"])   # each once
        figures = cfg.output.figures
        writers.append(lambda staging: write_nuts_outputs(res, staging, figures=figures))
    result["writers"] = writers

    with staging_dir(Path(out)) as tmp:
        t = time.perf_counter()
        write_json(tmp / "params.json", fit.to_json())
        write_predictions(tmp / "predictions.csv", test, split.test, columns)
        (tmp / "config.resolved.toml").write_text(to_toml(cfg.to_dict()))
        from bayesmag._src.app.artifact import save_calibration
        save_calibration(tmp, result["predictor"], config=cfg.to_dict(), level=cfg.uq.level)
        from bayesmag._src.app.artifact import ArtifactError, read_calibration
        try:                    # what `apply` and `export` will load: never report success for a file they refuse
            read_calibration(tmp)
        except ArtifactError as e:
            raise JobError(f"bayesmag wrote a calibration its own loader refuses ({e}); nothing was written to "
                           f"{out}. Please report this as a bug.") from None
        for writer in result.get("writers", []):    # stage files and figures, drawn here while the figure
            writer(tmp)                             # process draws the physics stage's
        if cfg.output.figures:
            from bayesmag._src.app import plots
            plots.residual_histogram_figure(tmp, result, columns)
            figs.finish(tmp)
        timings["write"] = time.perf_counter() - t     # files and figures (total: the whole job)
        timings["total"] = time.perf_counter() - t_all
        metrics["timings"] = {k: round(v, 4) for k, v in timings.items()}
        write_json(tmp / "metrics.json", metrics)
        from bayesmag._src.app.report import write_report
        write_report(tmp, require_marker=False)     # the staging folder: its marker says incomplete
    return result
