"""A fleet's per-sensor stage: the batched residual networks, each sensor's predictions, and its calibration folder.

* :func:`fleet_networks`: the residual network of every sensor trained in one compiled batch
  (:func:`~bayesmag._src.core.network_batch.fit_residual_networks`, the ``[network]`` settings of a single run,
  one likelihood, no conformal folds) and predicted on its test rows in one batch
  (:func:`~bayesmag._src.core.network_batch.mc_predict_many`); fused with each sensor's physics prediction by the
  single run's :class:`~bayesmag._src.core.predictor.Predictor` and scored by the single run's
  :func:`~bayesmag._src.pipeline.hybrid.hybrid_metrics`.
* :func:`write_sensor_folder`: ``sensors/<id>/`` with the files of a single ``bayesmag run`` folder --
  ``calibration.json``/``.npz`` (``bayesmag apply --model`` and ``bayesmag export`` take the folder),
  ``params.json``, ``predictions.csv`` (the single run's columns), ``metrics.json`` (the single run's blocks plus
  ``fleet``: the sensor's verdict), ``config.resolved.toml``, ``report.md``/``report.html`` and, with
  ``[output] figures = true``, the single run's figures.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import time
from pathlib import Path

import numpy as np

from bayesmag._src.core import metrics as M
from bayesmag._src.core.jsonio import write_json
from bayesmag._src.core.data import AXES, CalibrationData
from bayesmag._src.core.domain import budget_row_mask, budget_rows_note
from bayesmag._src.core.physics_uq import PhysicsUQ
from bayesmag._src.core.predictor import Components, Predictor, TransferEstimate, UQOptions, network_inputs

__all__ = ["SensorStage", "sensor_stages", "fleet_networks", "write_sensor_folder"]

SIGMA_SOURCE = "auto: within-run second differences, 1.4826*MAD/sqrt(6)"


@dataclasses.dataclass(frozen=True)
class SensorStage:
    """One sensor's calibration and its prediction of its test rows (physics, and hybrid with a network)."""

    sid: str
    train: CalibrationData
    test: CalibrationData
    test_rows: np.ndarray          # row numbers of the test rows in the recording
    train_residual: np.ndarray     # (n_train, 3) b_ref - plug-in physics prediction of the training rows
    split: dict
    fit: object                    # PhysicsFit
    predictor: Predictor           # physics, or physics + network (the one saved)
    uq: PhysicsUQ                  # physics part on the test rows
    prediction: object             # physics prediction (with the residual term)
    paper_prediction: object       # the paper's physics total sqrt(alea^2 + epi^2)
    hybrid: object = None          # HybridStage with a network, else None


def sensor_stages(ids, trains, tests, test_rows, splits, fit, uq, sigma_in, residual_sd,
                  train_pred, design=None, *, level: float = 0.95) -> list[SensorStage]:
    """Each sensor's physics :class:`Predictor` and prediction of its test rows, from the batched fit and UQ
    (``train_pred``: :func:`~bayesmag._src.core.fleet_fit.fleet_predict` of the training rows; ``design``: each
    sensor's design warnings, kept with its fit; ``level``: the fleet's ``[uq] level``)."""
    from bayesmag._src.core.domain import Domain
    out = []
    for i, sid in enumerate(ids):
        pf = sensor_fit(fit, i, () if design is None else tuple(design[i]))
        pr = Predictor(fit=pf, sigma_in=np.asarray(sigma_in[i]), residual_sd=np.asarray(residual_sd[i]),
                       domain=Domain.from_data(trains[i]), uq=UQOptions(method="analytic"), level=level)
        k = tests[i].n
        ep = uq.epistemic[i, :k]
        u = PhysicsUQ(uq.mean[i, :k], uq.aleatoric[i, :k], ep, ep, ep)
        comp = Components(u, None, None)
        paper = dataclasses.replace(pr, residual_sd=np.zeros(3))
        resid = trains[i].b_ref - train_pred[i, :trains[i].n]
        out.append(SensorStage(sid, trains[i], tests[i], test_rows[i], resid, splits[i], pf, pr, u,
                               pr.compose(comp, new_session=False), paper.compose(comp, new_session=False)))
    return out


def training_reporter(stream=None):
    """A progress callback for batched network training: one line redrawn in place on a terminal; in a log
    (file, pipe) a new line only when another network stops, so a long run does not fill the log.

    Example:
        >>> import io, numpy as np, types
        >>> log = io.StringIO(); report = training_reporter(log)
        >>> for e, d in [(10, [0, 0]), (20, [0, 0]), (30, [1, 0])]:
        ...     report(types.SimpleNamespace(done=np.array(d, bool), epochs=np.array([e, e])))
        >>> len(log.getvalue().splitlines())
        2
    """
    import sys

    from bayesmag._src.app.terminal import interactive_output
    stream = sys.stderr if stream is None else stream
    live, last = interactive_output(stream), [None]

    def report(p):
        done = int(p.done.sum())
        if not live and done == last[0]:
            return
        last[0] = done
        msg = (f"  fleet: network training, {done} of {p.done.size} (sensor, axis) networks of this "
               f"batch stopped, epoch {int(p.epochs.max())}")
        end = "" if live and done < p.done.size else "\n"
        print(("\r" + msg) if live else msg, end=end, file=stream, flush=True)
    return report


def fleet_networks(stages: list[SensorStage], net_cfg, *, level: float, batch_size: int,
                   progress: bool = False) -> tuple[list[SensorStage], float]:
    """Train every sensor's residual network in one batch, predict its test rows, fuse; returns the stages with
    ``hybrid`` and ``predictor`` set, and the training seconds."""
    from bayesmag._src.core.network_batch import fit_residual_networks, mc_predict_many
    from bayesmag._src.pipeline.hybrid import HybridStage, _warn_nan

    from bayesmag._src.app.config import config_error
    from bayesmag._src.core.network import check_network_size, validation_rows
    spec = net_cfg.spec(net_cfg.likelihoods[0])
    for s in stages:                        # sizes first, before any training: one line naming the sensor
        try:
            fit_rows, _ = validation_rows(s.train.n, net_cfg.validation_fraction, seed=net_cfg.seed,
                                          kind=net_cfg.validation, groups=s.train.run)
            check_network_size(spec, fit_rows.size)
        except ValueError as e:
            err = config_error(e, "network", net_cfg.table())
            raise type(err)(f"sensor {s.sid}: {err}") from None
    xs = [network_inputs(s.train) for s in stages]
    rs = [s.train_residual for s in stages]
    report = None
    if progress:
        report = training_reporter()
    t = time.perf_counter()
    nets = fit_residual_networks(xs, rs, spec, validation_fraction=net_cfg.validation_fraction, seed=net_cfg.seed,
                                 validation=net_cfg.validation, groups=[s.train.run for s in stages],
                                 batch_size=batch_size, progress=report)
    if net_cfg.recalibrate:
        from bayesmag._src.core.network import recalibrate
        nets = [recalibrate(n, x[n.val_rows], r[n.val_rows], passes=net_cfg.mc_passes, seed=net_cfg.seed)
                for n, x, r in zip(nets, xs, rs)]
    train_s = time.perf_counter() - t
    mcs = mc_predict_many(nets, [network_inputs(s.test) for s in stages], passes=net_cfg.mc_passes,
                          seed=net_cfg.seed, batch_size=batch_size)
    other = "paper" if net_cfg.fusion == "moment_match" else "moment_match"
    name = spec.likelihood
    out = []
    for s, net, mc in zip(stages, nets, mcs):
        pr = dataclasses.replace(s.predictor, network=net, passes=net_cfg.mc_passes, network_seed=net_cfg.seed,
                                 fusion=net_cfg.fusion)
        comp = Components(s.uq, mc, None)
        training = {name: {**net.info_dict(), "train_seconds": round(train_s / len(stages), 4),
                           "train_seconds_note": "the fleet's batched training time divided by the sensors"}}
        if net.variance_scale is not None:
            for a, ax in enumerate(AXES):
                training[name][ax]["variance_scale"] = float(net.variance_scale[a])
        hs = HybridStage((spec,), {name: net}, {name: pr}, {name: pr.compose(comp, new_session=False)},
                         {name: pr.compose(comp, fusion=other, new_session=False)}, training,
                         _warn_nan(f"{name}, sensor {s.sid}", net), net_cfg.fusion, other)
        out.append(dataclasses.replace(s, predictor=pr, hybrid=hs))
    return out, train_s


#: Rows per compiled evaluation of a predictive distribution (:func:`rowwise`): every sensor's rows are cut into
#: blocks of this many (the last one padded), so sensors of any length share the compiled programs instead of
#: compiling each jax operation again for every new row count (measured: 27 compilations, ~2 s, per sensor).
ROW_BLOCK = 512


@functools.lru_cache(maxsize=None)
def _block_program(kind: str, level: float):
    """The compiled evaluation of one row block: ``interval`` (lower, upper), ``score`` (lower, upper, nll, crps)
    or ``pit``."""
    import jax
    if kind == "interval":
        return jax.jit(lambda d: d.interval(level))
    if kind == "score":
        return jax.jit(lambda d, y: (*d.interval(level), d.nll(y), d.crps(y)))
    return jax.jit(lambda d, y: (d.pit(y),))


def rowwise(dist, kind: str, level: float, *ys) -> tuple[np.ndarray, ...]:
    """:func:`_block_program` ``kind`` over blocks of :data:`ROW_BLOCK` rows of ``dist`` (and ``ys``), joined."""
    import jax.numpy as jnp
    n = int(dist.batch_shape[0])
    m = max(ROW_BLOCK, -(-n // ROW_BLOCK) * ROW_BLOCK)
    pad = lambda v: np.pad(np.asarray(v), [(0, m - n)] + [(0, 0)] * (np.ndim(v) - 1), mode="edge")  # noqa: E731
    fields = {f.name: pad(getattr(dist, f.name)) for f in dataclasses.fields(dist)
              if np.ndim(getattr(dist, f.name)) >= 1 and np.shape(getattr(dist, f.name))[0] == n}
    dt = jnp.result_type(*[v for v in fields.values()], 1.0)
    ys = [pad(y) for y in ys]
    prog = _block_program(kind, float(level))
    parts = []
    for lo in range(0, m, ROW_BLOCK):
        blk = dataclasses.replace(dist, **{k: jnp.asarray(v[lo:lo + ROW_BLOCK]) for k, v in fields.items()})
        parts.append([np.asarray(a, np.float64) for a in prog(blk, *[jnp.asarray(y[lo:lo + ROW_BLOCK], dt) for y in ys])])
    return tuple(np.concatenate([p[j] for p in parts])[:n] for j in range(len(parts[0])))


def interval(pred, level: float) -> tuple[np.ndarray, np.ndarray]:
    """``pred.interval(level)`` evaluated in row blocks (:func:`rowwise`)."""
    return rowwise(pred.dist, "interval", level)


def score_rows(y, dist, level: float = 0.95, *, mean=None) -> dict:
    """:func:`~bayesmag.metrics.score_per_axis` (the same numbers), the distribution evaluated in row blocks."""
    y = np.asarray(y, np.float64)
    lower, upper, nll, crps = rowwise(dist, "score", level, y)
    mean = np.asarray(dist.mean if mean is None else mean, np.float64)
    out = {"rmse": M.rmse(y, mean), "mae": M.mae(y, mean), "coverage": M.coverage(y, lower, upper),
           "nll": np.mean(nll, axis=0), "crps": np.mean(crps, axis=0), "mean_width": M.interval_width(lower, upper)}
    return {k: {ax: float(v[i]) for i, ax in enumerate(AXES)} for k, v in out.items()}


def write_predictions(path: Path, data: CalibrationData, rows: np.ndarray, columns: dict[str, np.ndarray]) -> None:
    """:func:`bayesmag._src.app.job.write_predictions` (the same bytes), formatting whole columns at once: a fleet
    writes one per sensor, and the row-by-row writer took ~0.1 s for 1,000 rows."""
    import csv

    out = [[str(int(r)) for r in np.asarray(rows).tolist()], [f"{v:.6f}" for v in np.asarray(data.time).tolist()],
           [str(int(r)) for r in np.asarray(data.run).tolist()],
           [f"{v:.10g}" for v in np.asarray(data.temperature, np.float64).tolist()]]
    header = ["row", "time", "run", "temperature"] + [f"{ax}_{c}" for ax in AXES for c in columns]
    for a in range(3):
        for c in columns.values():
            col = np.asarray(c)[:, a]
            if col.dtype == bool:
                out.append(["True" if v else "False" for v in col.tolist()])
            elif col.dtype.kind in "US":
                out.append([str(v) for v in col.tolist()])
            elif col.dtype.kind == "O":            # as the single writer: per value
                out.append([str(bool(v)) if isinstance(v, (np.bool_, bool)) else v if isinstance(v, str)
                            else f"{float(v):.8g}" for v in col.tolist()])
            else:
                out.append([f"{v:.8g}" for v in col.astype(np.float64).tolist()])
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(zip(*out))


def _or_zeros(a, like) -> np.ndarray:
    return np.zeros_like(like) if a is None else a


def _per_axis(v) -> dict:
    return {ax: float(x) for ax, x in zip(AXES, np.asarray(v, np.float64).reshape(3))}


def _certificate(conf_toml: str, sid: str, parts: tuple[CalibrationData, ...], recording=None) -> dict:
    """The identity block of a single run's metrics.json for one sensor: the sha256 of its recording file
    (``recording``: ``(path, sha256)``; ``bayesmag export`` checks it as a run's), else of its rows' arrays."""
    import datetime

    from bayesmag._src.core.version import __version__
    h = hashlib.sha256()
    for data in parts:
        for arr in (data.b_meas, data.temperature, data.b_ref, data.time, data.run):
            h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
    digest, what = h.hexdigest(), f"fleet sensor {sid} (sha256 of its train + test rows, float64)"
    if recording is not None:
        digest, what = recording[1], f"file {Path(recording[0]).name}"
    return {"calibration_id": hashlib.sha256((conf_toml + sid + digest).encode()).hexdigest()[:16],
            "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "bayesmag_version": __version__, "data": what,
            "data_sha256": digest, "dut": sid, "reference": "", "operator": ""}


def write_sensor_folder(d: Path, s: SensorStage, *, cfg, verdict: dict, sigma_in: np.ndarray, source: str,
                        timings: dict, recording=None) -> None:
    """Write sensor ``s``'s calibration folder ``d`` (the file set of a single ``bayesmag run`` folder).
    ``recording``: ``(path, sha256)`` of its file, saved as a run's ``[data] path`` and data sha256, so ``apply`` and
    ``export`` never write over it and ``export`` refuses to measure on it once it changed."""
    from bayesmag._src.app.artifact import save_calibration
    from bayesmag._src.app.config import to_toml
    from bayesmag._src.app.report import write_report

    d.mkdir(parents=True)
    level, test, y = cfg.level, s.test, s.test.b_ref
    pred, uq, fit, train = s.prediction, s.uq, s.fit, s.train
    lo, hi = interval(pred, level)
    domain = s.predictor.domain
    outside = domain.outside(test, uq.mean)
    budget = budget_row_mask(outside)
    resid_train = s.train_residual
    phys = score_rows(y, pred.dist, level, mean=pred.mean)
    paper = score_rows(y, s.paper_prediction.dist, level, mean=s.paper_prediction.mean)
    conf = {**cfg.to_dict(), "sensor_id": s.sid, "fleet_base": str(Path(cfg.base).resolve()),
            **({"data": {"path": str(recording[0])}} if recording is not None else {})}
    conf_toml = to_toml(conf)
    runs = np.union1d(train.run, test.run)
    transfer = TransferEstimate(np.zeros(3), "off", {})
    metrics = {
        "raw": {"rmse": _per_axis(M.rmse(y, test.b_meas)), "mae": _per_axis(M.mae(y, test.b_meas))},
        "physics": phys,
        "physics_paper_total": {k: paper[k] for k in ("coverage", "nll", "crps", "mean_width")},
        "physics_in_sample": {"rmse": _per_axis(fit.rmse_in_sample), "residual_std_error": _per_axis(np.sqrt(fit.s2)),
                              "mae": _per_axis(np.mean(np.abs(resid_train), axis=0))},
        "uq": {"method": "analytic", "n_params": None, "n_qmc": None, "level": level,
               "sigma_in_sd": dict(zip(["bx", "by", "bz", "T"], map(float, np.sqrt(np.diag(sigma_in))))),
               "sigma_in_source": SIGMA_SOURCE if cfg.sigma_in == "auto" else "config: standard deviations",
               "residual_term": _per_axis(s.predictor.residual_sd),
               "mean_aleatoric": _per_axis(uq.aleatoric[budget].mean(0)),
               "mean_epistemic": _per_axis(uq.epistemic[budget].mean(0)), "budget_rows": budget_rows_note(outside)},
        "split": s.split,
        "data": {"source": source, "n_rows": int(train.n + test.n), "runs": [int(r) for r in runs],
                 "train_runs": [int(r) for r in np.unique(train.run)]},
        "field": {"raw": M.field_metrics(test.b_meas, y, test.run), "physics": M.field_metrics(pred.mean, y, test.run)},
        "certificate": _certificate(conf_toml, s.sid, (train, test), recording),
        "domain": domain.summary(test, uq.mean),
        "transfer": {**transfer.as_dict(), "n_test_rows_new_session": 0},
        "warnings": [w for w in [*verdict.get("warnings", []), domain.warning(test, uq.mean)] if w],
    }
    columns = {
        "measured": test.b_meas, "reference": y, "predicted": uq.mean,
        "aleatoric_physics": uq.aleatoric, "epistemic_physics": uq.epistemic,
        "residual_physics": _or_zeros(pred.residual_physics, y), "transfer": _or_zeros(pred.transfer, y),
        "total": pred.total, "lower": lo, "upper": hi, "covered": (y >= lo) & (y <= hi),
        "in_domain": np.broadcast_to(~outside.any(axis=1)[:, None], y.shape),
        "in_domain_reason": np.broadcast_to(domain.reasons(outside)[:, None], y.shape),
    }
    writers = []
    hs = s.hybrid
    if hs is not None:
        from bayesmag._src.app.hybrid_outputs import hybrid_writers
        from bayesmag._src.pipeline.hybrid import hybrid_metrics
        metrics.update(hybrid_metrics(hs, y, uq.mean, level, cfg.network.mc_passes, scorer=score_rows))
        metrics["field"].update({f"hybrid ({name})": M.field_metrics(p.mean, y, test.run)
                                 for name, p in hs.predictions.items()})
        metrics["warnings"] += hs.nan_messages
        hp = hs.predictions[hs.primary]
        hlo, hhi = interval(hp, level)
        columns = {**columns, "hybrid_predicted": hp.mean, "aleatoric_nn": hp.aleatoric_nn,   # hybrid_columns
                   "epistemic_nn": hp.epistemic_nn, "hybrid_total": hp.total, "hybrid_lower": hlo,
                   "hybrid_upper": hhi, "hybrid_covered": (y >= hlo) & (y <= hhi)}
        writers = hybrid_writers(_FigureSwitch(cfg.sensor_figures), hs, columns, test, level)
    metrics["fleet"] = verdict
    metrics["timings"] = timings
    write_json(d / "params.json", fit.to_json())
    write_predictions(d / "predictions.csv", test, s.test_rows, columns)
    (d / "config.resolved.toml").write_text(conf_toml)
    save_calibration(d, s.predictor, config=conf, level=level)
    for w in writers:
        w(d)
    if cfg.sensor_figures:
        from bayesmag._src.app import plots
        from bayesmag._src.app.plots import physics_figures
        physics_figures(d, test, {k: columns[k] for k in ("measured", "predicted", "reference", "total", "lower",
                                                          "upper")},
                        {"train": train, "train_residual": resid_train, "pit": rowwise(pred.dist, "pit", level, y)[0],
                         "level": level})
        plots.residual_histogram_figure(d, {"uq": uq}, columns)
    write_json(d / "metrics.json", metrics)
    write_report(d, require_marker=False)   # inside the fleet's staging folder: its marker lists the files


class _FigureSwitch:
    """The ``cfg.output.figures`` that :func:`~bayesmag._src.pipeline.hybrid.hybrid_writers` reads."""

    def __init__(self, figures: bool):
        self.output = type("Output", (), {"figures": bool(figures)})()


def sensor_fit(fit, i: int, design_warnings: tuple[str, ...] = ()):
    """Sensor ``i``'s :class:`~bayesmag.PhysicsFit` (diagnostics from its covariance) from the batched fit."""
    from bayesmag._src.core.fit import RESULTS, PhysicsFit, identifiability
    names = fit.model.param_names
    infos = tuple({"s2": float(fit.s2[i, a]), "dof": int(fit.n[i] - fit.model.n_params), "rho1": float(fit.rho1[i, a]),
                   "method": fit.covariance_method} for a in range(3))
    return PhysicsFit(model=fit.model, theta=fit.theta[i], cov=fit.cov[i], s2=fit.s2[i], n=int(fit.n[i]),
                      rmse_in_sample=fit.rmse[i], result=tuple(RESULTS[int(r)] for r in fit.result[i]),
                      n_steps=fit.n_steps[i], covariance_method=fit.covariance_method, cov_info=infos,
                      diagnostics=tuple(identifiability(fit.cov[i, a], names) for a in range(3)),
                      design_warnings=design_warnings)
