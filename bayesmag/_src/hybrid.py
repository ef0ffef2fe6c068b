r"""Hybrid stage: physics prediction + residual network, uncertainty fusion, likelihood comparison.

Shetty & Marndi (2026), sections 2.4-2.6 and 3.7-3.8. For every likelihood named in
``[network] likelihoods`` one :mod:`~bayesmag._src.network` residual network per axis is
trained on the same rows with the same seed, evaluated on the test rows by Monte-Carlo
DropConnect, and fused with the physics uncertainty.

**Residual targets.** :math:`r = B_{ref} - \hat y_{phys}(x)` on the training rows uses the
plug-in physics prediction ``fit.predict(x)`` (:math:`f(x, \hat\theta)`), not the PS-QMC mean
of sec. 2.3.3. For the thermo-affine model (linear in its parameters, bilinear in B and T)
the two are equal up to the PS-QMC sampling noise whenever the input noise of B and T is
uncorrelated (the nested average of :math:`\phi(x+\epsilon)^T\theta` is
:math:`E[\phi(x+\epsilon)]^T\hat\theta = \phi(x)^T\hat\theta + \mathrm{cov}(\epsilon_B, \epsilon_T)`
terms); the plug-in is exact and costs nothing on 3000 rows. On the test rows the hybrid
mean adds the network correction to the job's PS-QMC mean (``result["uq"].mean``), the same
physics prediction the physics-only metrics use.

**Fusion** (``network.fusion``), per row and axis, with NN aleatoric variance
:math:`a^2`, NN epistemic variance :math:`e^2` (MC DropConnect, :func:`~bayesmag._src.network.mc_predict`)
and the physics aleatoric/epistemic sds :math:`a_p, e_p` from the PS-QMC stage:

* ``"moment_match"`` (default): mean :math:`\hat y = \bar y_{phys} + \bar\mu_{NN}`, variance
  :math:`\sigma^2 = a^2 + e^2 + e_p^2`. The physics aleatoric part :math:`a_p^2` (input noise
  pushed through the model) is *not* added: the network learned :math:`a^2` from residuals
  that already contain that noise, so adding it counts the measurement noise twice -- the
  reason the paper's 95 % intervals cover 98-99 %. The predictive distribution is the trained
  family moment-matched to :math:`(\hat y, \sigma^2)`
  (:func:`~bayesmag.likelihoods.moment_match`): Gaussian :math:`N(\hat y, \sigma^2)`;
  Laplace with :math:`b = \sigma/\sqrt2`; Student-t keeping its degrees of freedom -- the
  fixed ``network.student_t_df``, or with ``student_t_df = "learn"`` the per-row mean over
  MC passes of the learned :math:`\nu` -- and scale :math:`\sigma\sqrt{(\nu-2)/\nu}`.
* ``"paper"``: the paper's root-sum-of-squares (sec. 2.5),
  :math:`\sigma^2 = a_p^2 + a^2 + e_p^2 + e^2`, with Gaussian predictive intervals
  (sec. 2.6) for every family: :math:`N(\hat y, \sigma^2)`.

RMSE and MAE are of :math:`\hat y`; coverage, interval width, NLL and CRPS all come from
that one predictive distribution (central interval of level ``uq.level``). The fusion not
selected is scored too (``metrics["hybrid_<other>_fusion"]``) for comparison.

Outputs: ``metrics["hybrid"][likelihood]`` = ``rmse, mae, coverage, nll, crps, mean_width``
per axis; ``metrics["network"]`` = settings and per-likelihood training outcome (epochs
run, best epoch, NaN epoch, seconds); ``metrics["hybrid_vs_physics"]`` = paired squared-error
test (sec. 4.4); prediction columns for the first (primary) likelihood; with several
likelihoods, ``likelihood_comparison.md`` / ``.json`` (the layout of the paper's Table 7);
figures (:mod:`~bayesmag._src.hybrid_plots`).
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np

from . import metrics as M
from .config import Config, NetworkConfig, config_error
from .data import AXES, CalibrationData
from .likelihoods import Gaussian, Likelihood, moment_match
from .network import (MCPrediction, NetworkSpec, ResidualNetwork, check_network_size, fit_residual_network,
                      mc_predict, recalibrate, validation_rows)
from .physics import inputs_from_data
from .physics_uq import PhysicsUQ

__all__ = ["FUSIONS", "HybridPrediction", "check_network_config", "network_inputs", "train_network", "fuse", "score",
           "run_hybrid_stage", "comparison_markdown", "comparison_records"]

FUSIONS = ("moment_match", "paper")


class HybridPrediction(NamedTuple):
    """Fused hybrid prediction, each array ``(n, 3)`` in uT (sds, not variances).

    ``dist`` is the predictive distribution all probabilistic scores come from.
    """

    mean: np.ndarray
    dist: Likelihood
    total: np.ndarray
    aleatoric_nn: np.ndarray
    epistemic_nn: np.ndarray
    aleatoric_physics: np.ndarray
    epistemic_physics: np.ndarray
    fusion: str


def check_network_config(cfg: Config) -> list[NetworkSpec]:
    """Validate the ``[network]`` table; return one :class:`NetworkSpec` per likelihood.

    The settings were validated when the config was loaded (``NetworkConfig``).
    """
    return [cfg.network.spec(name) for name in cfg.network.likelihoods]   # validated at load (config.py)


def network_inputs(data: CalibrationData) -> np.ndarray:
    """The network's inputs ``(n, 4)``: measured field (3) and temperature, float64 (standardised later)."""
    return np.column_stack([data.b_meas, data.temperature]).astype(np.float64)


def train_network(x: np.ndarray, r: np.ndarray, spec: NetworkSpec, net_cfg: NetworkConfig,
                  groups: np.ndarray | None = None, progress: bool = False) -> ResidualNetwork:
    """Train the axis networks as ``[network]`` says: validation rows, then optional recalibration.

    ``groups``: the run of every row (time order within a run), used by ``validation = "time_blocks"``.
    """
    net = fit_residual_network(x, r, spec, validation_fraction=net_cfg.validation_fraction, seed=net_cfg.seed,
                               validation=net_cfg.validation, groups=groups, progress=progress)
    if net_cfg.recalibrate:
        net = recalibrate(net, x[net.val_rows], r[net.val_rows], passes=net_cfg.mc_passes, seed=net_cfg.seed)
    return net


def fuse(physics: PhysicsUQ, nn: MCPrediction, spec: NetworkSpec, *, fusion: str = "moment_match") -> HybridPrediction:
    """Combine the physics PS-QMC prediction and the MC-DropConnect residual prediction.

    See the module docstring for the two rules. ``physics`` and ``nn`` are for the same rows.
    """
    if fusion not in FUSIONS:
        raise ValueError(f"fusion {fusion!r} is not known; it must be one of {list(FUSIONS)}")
    mean = np.asarray(physics.mean, np.float64) + nn.mean
    var = nn.aleatoric**2 + nn.epistemic**2 + physics.epistemic**2
    if fusion == "paper":
        var = var + physics.aleatoric**2
        dist = Gaussian(mean, np.sqrt(var))
    else:
        dist = moment_match(spec.likelihood, mean, var, **spec.shape_for(nn.shape))
    return HybridPrediction(mean, dist, np.sqrt(var), nn.aleatoric, nn.epistemic, np.asarray(physics.aleatoric),
                            np.asarray(physics.epistemic), fusion)


def _per_axis(v) -> dict:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    return {ax: float(x) for ax, x in zip(AXES, v)}


def score(y: np.ndarray, pred: HybridPrediction, level: float) -> tuple[dict, np.ndarray, np.ndarray]:
    """Per-axis ``rmse, mae, coverage, nll, crps, mean_width`` and the central ``level`` interval."""
    lo, hi = (np.asarray(a, np.float64) for a in pred.dist.interval(level))
    scores = {
        "rmse": _per_axis(M.rmse(y, pred.mean)),
        "mae": _per_axis(M.mae(y, pred.mean)),
        "coverage": _per_axis(M.coverage(y, lo, hi)),
        "nll": _per_axis(M.nll(pred.dist, y)),
        "crps": _per_axis(M.crps(pred.dist, y)),
        "mean_width": _per_axis(M.interval_width(lo, hi)),
    }
    return scores, lo, hi


def comparison_records(hybrid_metrics: dict[str, dict]) -> list[dict]:
    """Rows of ``likelihood_comparison.json``: likelihood, rmse, mae, coverage, nll, crps, mean_width."""
    keys = ("rmse", "mae", "coverage", "nll", "crps", "mean_width")
    return [{"likelihood": name, **{k: block[k] for k in keys}} for name, block in hybrid_metrics.items()]


def comparison_markdown(hybrid_metrics: dict[str, dict], *, fusion: str, level: float, n_test: int) -> str:
    """The paper's Table 7 layout: one row per likelihood and axis."""
    lines = [
        "# Likelihood comparison (hybrid, test rows)",
        "",
        f"{n_test} test rows; fusion `{fusion}`; coverage of the central {level:.0%} interval; NLL and CRPS of the "
        "fused predictive distribution (uT units). Lower RMSE, MAE, NLL, CRPS are better; coverage should be "
        f"near {level:.0%}.",
        "",
        "| Likelihood | Axis | RMSE (uT) | MAE (uT) | Coverage (%) | NLL | CRPS (uT) | Mean width (uT) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, b in hybrid_metrics.items():
        for ax in AXES:
            lines.append(f"| {name} | {ax} | {b['rmse'][ax]:.5f} | {b['mae'][ax]:.5f} | "
                         f"{100 * b['coverage'][ax]:.2f} | {b['nll'][ax]:.3f} | {b['crps'][ax]:.5f} | "
                         f"{b['mean_width'][ax]:.4f} |")
    return "\n".join(lines) + "\n"


def _warn_nan(name: str, net: ResidualNetwork) -> list[str]:
    msgs = []
    for ax, info in net.info_dict().items():
        if info["nan_epoch"] >= 0:
            kept = (f"the weights of epoch {info['best_epoch']} (best finite validation loss) are used"
                    if info["best_epoch"] >= 0
                    else "no epoch finished with a finite loss, so the initial weights are used")
            msg = (f"Residual network '{name}', axis {ax}: the training loss became NaN/inf in epoch "
                   f"{info['nan_epoch']}; training stopped there and {kept}. Usual causes: a learning rate too "
                   "high for the data (lower 'network.learning_rate') or a log-scale clip that lets the scale "
                   "collapse (raise the low end of 'network.log_scale_clip').")
            warnings.warn(msg, RuntimeWarning, stacklevel=3)
            msgs.append(msg)
    return msgs


def run_hybrid_stage(cfg: Config, result: dict, train: CalibrationData, test: CalibrationData,
                     columns: dict[str, np.ndarray], timings: dict[str, float], *,
                     progress: bool = False) -> dict[str, np.ndarray]:
    """Train the residual networks, fuse, score; extend ``result`` and return the extended ``columns``.

    Adds ``result["metrics"]["hybrid"]``, ``["network"]``, ``["hybrid_vs_physics"]`` and
    ``["hybrid_<other fusion>_fusion"]``, ``result["networks"]`` (name -> ResidualNetwork),
    ``result["hybrid"]`` (name -> HybridPrediction), writers for the comparison table and
    figures, and ``timings["network_train"]`` / ``["hybrid_inference"]`` (s).
    """
    specs = check_network_config(cfg)
    net_cfg = cfg.network
    # Size checks for every likelihood before any training.
    try:
        fit_rows, _ = validation_rows(train.n, net_cfg.validation_fraction, seed=net_cfg.seed)
        for spec in specs:
            check_network_size(spec, fit_rows.size)
    except ValueError as e:
        raise config_error(e, "network", net_cfg.table()) from None

    fit, uq = result["fit"], result["uq"]
    level = cfg.uq.level
    y = test.b_ref
    x_train, x_test = network_inputs(train), network_inputs(test)
    r_train = train.b_ref - fit.predict(inputs_from_data(train))

    networks: dict[str, ResidualNetwork] = {}
    preds: dict[str, HybridPrediction] = {}
    hybrid_metrics: dict[str, dict] = {}
    other = "paper" if net_cfg.fusion == "moment_match" else "moment_match"
    other_metrics: dict[str, dict] = {}
    paired: dict[str, dict] = {}
    training: dict[str, dict] = {}
    nan_messages: list[str] = []
    timings.setdefault("network_train", 0.0)
    timings.setdefault("hybrid_inference", 0.0)

    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=len(specs), desc="residual networks (3 axes each)", unit="likelihood")
    try:
        for spec in specs:
            name = spec.likelihood
            if bar is not None:
                bar.set_postfix_str(f"training {name}")
            t = time.perf_counter()
            net = train_network(x_train, r_train, spec, net_cfg, groups=train.run, progress=progress)
            train_s = time.perf_counter() - t
            timings["network_train"] += train_s
            nan_messages += _warn_nan(name, net)

            t = time.perf_counter()
            nn = mc_predict(net, x_test, passes=net_cfg.mc_passes, seed=net_cfg.seed)
            pred = fuse(uq, nn, spec, fusion=net_cfg.fusion)
            timings["hybrid_inference"] += time.perf_counter() - t

            networks[name], preds[name] = net, pred
            hybrid_metrics[name], lo, hi = score(y, pred, level)
            alt, _, _ = score(y, fuse(uq, nn, spec, fusion=other), level)
            other_metrics[name] = {k: alt[k] for k in ("coverage", "nll", "crps", "mean_width")}
            pt = M.paired_test(y - uq.mean, y - pred.mean)
            paired[name] = {ax: {"mean_diff": float(pt["mean_diff"][a]), "t": float(pt["t"][a]),
                                 "p": float(pt["p"][a]), "cohens_d": float(pt["cohens_d"][a])}
                            for a, ax in enumerate(AXES)}
            training[name] = {**net.info_dict(), "train_seconds": round(train_s, 3)}
            if net.variance_scale is not None:
                for a, ax in enumerate(AXES):
                    training[name][ax]["variance_scale"] = float(net.variance_scale[a])
            if name == specs[0].likelihood:
                columns = dict(columns)
                columns.update({
                    "hybrid_predicted": pred.mean, "aleatoric_nn": pred.aleatoric_nn,
                    "epistemic_nn": pred.epistemic_nn, "hybrid_total": pred.total,
                    "hybrid_lower": lo, "hybrid_upper": hi, "hybrid_covered": (y >= lo) & (y <= hi),
                })
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()

    first = networks[specs[0].likelihood]
    m = result["metrics"]
    m["hybrid"] = hybrid_metrics
    m[f"hybrid_{other}_fusion"] = other_metrics
    m["hybrid_vs_physics"] = paired
    m["network"] = {
        "fusion": net_cfg.fusion,
        "primary": specs[0].likelihood,
        "residual_physics_mean": "plug-in fit.predict on the training rows; PS-QMC mean on the test rows",
        "n_fit_rows": first.n_fit, "n_validation_rows": first.n_val,
        "n_params_per_axis": {s.likelihood: s.n_params for s in specs},
        "mc_passes": net_cfg.mc_passes,
        "training": training,
        "warnings": nan_messages,
    }
    result["networks"] = networks
    result["hybrid"] = preds

    writers = result.setdefault("writers", [])
    if len(specs) > 1:
        md = comparison_markdown(hybrid_metrics, fusion=net_cfg.fusion, level=level, n_test=test.n)
        records = comparison_records(hybrid_metrics)

        def write_comparison(out: Path) -> None:
            (Path(out) / "likelihood_comparison.md").write_text(md)
            (Path(out) / "likelihood_comparison.json").write_text(json.dumps(records, indent=2))

        writers.append(write_comparison)
    if cfg.output.figures:
        temperature = np.asarray(test.temperature)
        dists = {name: p.dist for name, p in preds.items()}
        cols = dict(columns)

        def write_figures(out: Path) -> None:
            from .hybrid_plots import hybrid_figures
            hybrid_figures(Path(out), cols, temperature, dists, level=level)
            from .network_plots import loss_curves
            loss_curves(Path(out) / "network_loss.png", networks)

        writers.append(write_figures)
    return columns
