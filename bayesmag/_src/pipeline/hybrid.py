r"""Hybrid stage: physics prediction + residual network, uncertainty fusion, likelihood comparison.

Shetty & Marndi (2026), sections 2.4-2.6 and 3.7-3.8. For every likelihood named in
``[network] likelihoods`` one :mod:`~bayesmag._src.core.network` residual network per axis is
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
:math:`a^2`, NN epistemic variance :math:`e^2` (MC DropConnect, :func:`~bayesmag._src.core.network.mc_predict`)
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
likelihoods, the rows of ``likelihood_comparison.md`` / ``.json`` (the layout of the paper's Table 7).
This module computes; the application layer writes the files and draws the figures
(``bayesmag._src.app.hybrid_outputs``).
"""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from bayesmag._src.core import metrics as M
from bayesmag._src.core.data import AXES, CalibrationData
from bayesmag._src.core.network import (MCPrediction, NetworkEnsemble, NetworkSpec, ResidualNetwork, check_network_size, ensemble_passes,
                      fit_residual_network, merged_reporter, progress_bar, recalibrate, training_threads,
                      validation_rows)
from bayesmag._src.core.physics import inputs_from_data
from bayesmag._src.core.physics_uq import PhysicsUQ
from bayesmag._src.core.predictor import FUSIONS, Components, Prediction, Predictor, compose, network_inputs
from bayesmag._src.pipeline.network_transfer import (NetworkTransfer, fold_domain_mask, hybrid_session_model,
                                                    network_transfer_sd, new_session_transfer_rows, run_folds)
from bayesmag._src.pipeline.conformal import conformal_folds, conformal_plan, conformal_quantile, conformal_ratios
from bayesmag._src.pipeline.settings import ConformalPlan, NetworkSettings

__all__ = ["FUSIONS", "HybridPrediction", "HybridStage", "NetworkSizeError", "check_network_config", "conformal_folds",
           "conformal_plan", "network_inputs", "train_network",
           "fuse", "score", "run_hybrid_stage", "hybrid_metrics", "hybrid_columns",
           "comparison_markdown", "comparison_records"]


class NetworkSizeError(ValueError):
    """The training rows are too few for the network settings (the message names the setting)."""


class _RandomSplit:
    """A split without time blocks, for :func:`conformal_plan`'s default."""

    kind = "random"


#: The fused hybrid prediction: a :class:`~bayesmag._src.core.predictor.Prediction` (mean, dist, total,
#: and the named parts ``aleatoric_nn, epistemic_nn, aleatoric_physics, epistemic_physics``).
HybridPrediction = Prediction


@dataclasses.dataclass(frozen=True)
class HybridStage:
    """What the hybrid stage computed, per likelihood name (the first is the primary one).

    ``predictors``: the full :class:`Predictor` (physics + network + fusion) per likelihood;
    ``predictions`` / ``alternates``: its prediction of the test rows with the configured and
    with the other fusion; ``training``: per-axis training outcome and seconds.
    """

    specs: tuple
    networks: dict
    predictors: dict
    predictions: dict
    alternates: dict
    training: dict
    nan_messages: list
    fusion: str
    other_fusion: str
    network_transfer: dict = dataclasses.field(default_factory=dict)   # per likelihood: NetworkTransfer (by-run folds)

    @property
    def primary(self) -> str:
        return self.specs[0].likelihood


def check_network_config(settings) -> list[NetworkSpec]:
    """One :class:`NetworkSpec` per likelihood of a :class:`NetworkSettings` (or of an object holding
    one as ``.network``, such as the job's config); the settings validated themselves when built."""
    net = getattr(settings, "network", settings)
    return [net.spec(name) for name in net.likelihoods]


def train_network(x: np.ndarray, r: np.ndarray, spec: NetworkSpec, net_cfg: NetworkSettings,
                  groups: np.ndarray | None = None, progress=False, pool=None) -> ResidualNetwork:
    """Train the axis networks as the settings say: validation rows, then optional recalibration.

    ``groups``: the run of every row (time order within a run), used by ``validation = "time_blocks"``;
    ``progress`` and ``pool``: as in :func:`~bayesmag._src.core.network.fit_residual_network`.
    """
    net = fit_residual_network(x, r, spec, validation_fraction=net_cfg.validation_fraction, seed=net_cfg.seed,
                               validation=net_cfg.validation, groups=groups, progress=progress, pool=pool)
    return recalibrated(net, x, r, net_cfg)


def recalibrated(net: ResidualNetwork, x: np.ndarray, r: np.ndarray, net_cfg: NetworkSettings) -> ResidualNetwork:
    """``net`` with its MC variances recalibrated on its validation rows of ``(x, r)`` when the settings ask."""
    if net_cfg.recalibrate:
        net = recalibrate(net, x[net.val_rows], r[net.val_rows], passes=net_cfg.mc_passes, seed=net_cfg.seed)
    return net


def train_fold_networks(x: np.ndarray, r: np.ndarray, spec: NetworkSpec, net_cfg: NetworkSettings, groups: np.ndarray,
                        folds: np.ndarray, n_folds: int, progress: bool = False) -> list[ResidualNetwork]:
    """The ``n_folds`` cross-conformal networks, network ``k`` trained without the rows of fold ``k``
    (``folds == k``), all at once: every fold's axes share one pool of
    :func:`~bayesmag._src.core.network.training_threads` threads, so the K x 3 trainings keep the cores
    busy however unequal their early stops (trained one fold after the other, the two cores of the
    paper's machine often waited on one fold's last axis). Each network is the one
    :func:`train_network` gives alone (the axes do not depend on the threads).
    """
    return train_networks_excluding(x, r, spec, net_cfg, groups, [folds == k for k in range(n_folds)],
                                    progress=progress)


def train_networks_excluding(x: np.ndarray, r: np.ndarray, spec: NetworkSpec, net_cfg: NetworkSettings,
                             groups: np.ndarray, excluded: list, progress: bool = False) -> list[ResidualNetwork]:
    """One network per (n,) bool mask in ``excluded``, network ``k`` trained without the rows of ``excluded[k]``,
    all at once on one pool of threads (:func:`train_fold_networks`; the cross-conformal folds and the
    by-run folds of ``[uq] transfer_networks`` train together)."""
    n_folds, n_axes = len(excluded), r.shape[1]
    report, bar = None, None
    if progress:                                        # folds still waiting for a thread count as epoch 0
        update, bar = progress_bar(spec.max_epochs, n_folds * n_axes, desc=f"network training ({spec.likelihood}, "
                                                                          f"{n_folds} fold networks x {n_axes} axes)")
        report = merged_reporter(n_folds, n_axes, update)

    def one(k: int, pool) -> ResidualNetwork:
        rows = np.flatnonzero(~np.asarray(excluded[k], bool))
        return train_network(x[rows], r[rows], spec, net_cfg, groups=groups[rows], pool=pool,
                             progress=(lambda p: report(k, p)) if report is not None else False)

    try:
        with ThreadPoolExecutor(training_threads(), thread_name_prefix="bayesmag-train") as pool, \
                ThreadPoolExecutor(n_folds, thread_name_prefix="bayesmag-fold") as fold_threads:
            return [f.result() for f in [fold_threads.submit(one, k, pool) for k in range(n_folds)]]
    finally:
        if bar is not None:
            bar.close()


def fuse(physics: PhysicsUQ, nn: MCPrediction, spec: NetworkSpec, *, fusion: str = "moment_match",
         level: float = 0.95) -> Prediction:
    """Combine the physics PS-QMC prediction and the MC-DropConnect residual prediction.

    See the module docstring for the two rules (:func:`~bayesmag._src.core.predictor.compose`).
    ``physics`` and ``nn`` are for the same rows; ``level``: the prediction's interval level.
    """
    return compose(physics, nn, fusion=fusion, family=spec.likelihood, fixed_shape=spec.fixed_shape, level=level)


def score(y: np.ndarray, pred: Prediction, level: float) -> tuple[dict, np.ndarray, np.ndarray]:
    """Per-axis ``rmse, mae, coverage, nll, crps, mean_width`` (:func:`~bayesmag.metrics.score`) and the
    central ``level`` interval."""
    lo, hi = pred.interval(level)
    return M.score_per_axis(y, pred.dist, level, mean=pred.mean), lo, hi


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


def still_improving(info: dict, max_epochs: int) -> bool:
    """True when training stopped at ``max_epochs`` with its best validation loss in the last tenth of the epochs
    (at least the last 2): the loss was still falling, so more epochs would likely have given a better network."""
    return info["nan_epoch"] < 0 and info["epochs_run"] >= max_epochs and \
        info["best_epoch"] >= max_epochs - max(2, int(round(0.1 * max_epochs)))


def _warn_max_epochs(name: str, net: ResidualNetwork, max_epochs: int) -> list[str]:
    """One message for the axes whose network was still improving when ``max_epochs`` stopped it (:func:`calibrate`
    raises it, with the run's other warnings, once)."""
    axes = [ax for ax, info in net.info_dict().items() if still_improving(info, max_epochs)]
    if not axes:
        return []
    msg = (f"Residual network '{name}', axis {', '.join(axes)}: training stopped at network.max_epochs = {max_epochs} "
           f"with the validation loss still falling (best epoch in the last tenth); the network is likely "
           f"under-trained. Raise network.max_epochs (early stopping, network.patience, still ends it).")
    return [msg]


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
            msgs.append(msg)
    return msgs


def run_hybrid_stage(settings: NetworkSettings, physics: Predictor, uq: PhysicsUQ | None, train: CalibrationData,
                     test: CalibrationData | None, timings: dict[str, float], *, level: float = 0.95,
                     conformal: ConformalPlan | None = None, new_session=False,
                     progress: bool = False, transfer_networks: str = "none", uq_settings=None,
                     pretrained=None, series=None) -> HybridStage:
    """Train the residual networks and predict the test rows; ``uq`` is ``physics``'s part on them
    (``test`` and ``uq`` None: train only, ``predictions`` and ``alternates`` empty). ``series``: as
    :func:`~bayesmag._src.pipeline.stages.run_physics_stage`'s (the row-dependent transfer of a model whose
    rows depend on their neighbours is then taken within the recording).

    ``settings``: a :class:`NetworkSettings`; ``level``: the intervals' level (conformal scores);
    ``conformal``: the cross-conformal plan, needed with ``interval_calibration = "conformal"``
    (None there: ``(validation_fraction, conformal_folds)`` as for a random split).

    With ``network.interval_calibration = "conformal"`` the interval scale is cross-conformal over
    K time-block folds (:func:`conformal_folds`; each one block of every run, as long as
    ``validation_fraction`` of it or as the job's test blocks if those are longer, K at most
    ``network.conformal_folds``: :func:`conformal_plan`): for every fold a network is trained without that fold's rows
    (and without its own early-stopping block), and the fold's rows are scored by it
    (:func:`~bayesmag._src.core.predictor.conformal_ratios`); the scale is the split-conformal quantile of the
    scores of all K folds pooled (:func:`~bayesmag._src.core.predictor.conformal_quantile`), floored at 1. The
    predictor keeps all K fold networks as a :class:`~bayesmag._src.core.network.NetworkEnsemble` (deep
    ensemble x MC DropConnect: ``mc_passes`` split over the members, moments pooled over all passes,
    :func:`~bayesmag._src.core.network.mc_predict`) with that scale; ``networks[name]`` (training
    diagnostics, metrics) stays fold 0's network. The K fold networks train at once
    (:func:`train_fold_networks`). Without conformal folds the predictor keeps the one network, as
    before. ``new_session``: test rows that get the transfer part. ``transfer_networks = "by_run_folds"``
    (``[uq] transfer_networks``): the network's own new-session error enters the transfer part
    (:mod:`~bayesmag._src.pipeline.network_transfer`; its fold networks train with the others, and
    ``training[name]["transfer_network"]`` reports it); it needs a physics transfer part and 2 runs, else it is
    skipped. With a hierarchical physics session model and ``uq_settings`` (the :class:`UQSettings`) the
    hybrid's session model is refitted on the out-of-fold hybrid residuals and replaces physics model + network
    part (:func:`~bayesmag._src.pipeline.network_transfer.hybrid_session_model`; ``timings["hybrid_transfer"]``).
    Adds ``timings["network_train"]`` (all networks) and ``["hybrid_inference"]`` (s). ``pretrained``:
    a :class:`~bayesmag._src.pipeline.prefetch.Training` started on the physics fit, whose networks the plain
    stage takes instead of training them (the same networks).
    """
    if hasattr(settings, "network") and hasattr(settings, "split"):    # the job's Config (the old signature)
        full = settings.settings()
        settings, conformal, level = full.network, full.conformal, settings.uq.level
    specs = check_network_config(settings)
    net_cfg = settings
    # Conformal rows: K folds of held-out time blocks, each seen neither by its network's training nor by its early
    # stopping (scores on the early-stopping rows are optimistic: their coverage overstates).
    folds = np.zeros(train.n, int) - 1
    n_folds = 0
    if net_cfg.interval_calibration == "conformal":
        plan = conformal if conformal is not None else ConformalPlan(*conformal_plan(_RandomSplit(), net_cfg))
        fold_fraction, n_folds = plan.fraction, plan.folds
        folds = conformal_folds(train.run, fraction=fold_fraction, folds=n_folds, seed=net_cfg.seed + 1)
    fit_idx = np.flatnonzero(folds != 0)
    run_fold, n_run_folds = None, 0
    if (transfer_networks == "by_run_folds" and np.unique(train.run).size >= 2
            and (physics.transfer_sd is not None or physics.sessions is not None)):
        run_fold, n_run_folds = run_folds(train.run, net_cfg.conformal_folds, net_cfg.seed + 2)
    # Size checks for every likelihood before any training.
    try:
        smallest = min([fit_idx.size] + [int(np.sum(run_fold != k)) for k in range(n_run_folds)])
        fit_rows, _ = validation_rows(smallest, net_cfg.validation_fraction, seed=net_cfg.seed)
        for spec in specs:
            check_network_size(spec, fit_rows.size)
    except ValueError as e:
        raise NetworkSizeError(str(e)) from None

    fit = physics.fit
    x_train = network_inputs(train)
    r_train = fit.residuals(train, None if series is None else series[:2])
    other = "paper" if net_cfg.fusion == "moment_match" else "moment_match"
    networks, predictors, preds, alts, training, network_transfer = {}, {}, {}, {}, {}, {}
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
            run_nets, own_s = [], None
            if n_run_folds:                  # every network of this likelihood on one pool of threads
                main = [folds == k for k in range(max(n_folds, 1))]
                nets = train_networks_excluding(x_train, r_train, spec, net_cfg, train.run,
                                                main + [run_fold == k for k in range(n_run_folds)], progress=progress)
                nets, run_nets = nets[:len(main)], nets[len(main):]
            elif n_folds:
                nets = train_fold_networks(x_train, r_train, spec, net_cfg, train.run, folds, n_folds,
                                           progress=progress)
            elif pretrained is not None and name in pretrained:      # trained while the physics stage finished
                net, own_s = pretrained.network(name)                 # (its own time: it overlapped that stage)
                nets = [net]
            else:
                nets = [train_network(x_train[fit_idx], r_train[fit_idx], spec, net_cfg, groups=train.run[fit_idx],
                                      progress=progress)]
            net = nets[0]
            train_s = own_s if own_s is not None else time.perf_counter() - t
            timings["network_train"] += train_s
            for k, nk in enumerate(nets):
                nan_messages += _warn_nan(name if k == 0 else f"{name}, conformal fold {k}", nk)
            nan_messages += _warn_max_epochs(name, net, net_cfg.max_epochs)
            for k, nk in enumerate(run_nets):
                nan_messages += _warn_nan(f"{name}, transfer run fold {k}", nk)

            pr = dataclasses.replace(physics, network=net, passes=net_cfg.mc_passes, network_seed=net_cfg.seed,
                                     fusion=net_cfg.fusion)
            if n_folds:
                t = time.perf_counter()
                ratios = []
                # a model whose rows depend on their neighbours predicts the calibration blocks within the
                # training series (as the residuals the networks learned were computed), not each on its own
                whole = None
                if pr.fit.model.needs_series:
                    whole = (pr.physics_part(train) if series is None else
                             pr.physics_part(series[0]).rows(series[1]))
                for k, nk in enumerate(nets):
                    pk = dataclasses.replace(pr, network=nk)
                    rows = np.flatnonzero(folds == k)
                    val = train.subset(rows)
                    comp = (pk.components(val) if whole is None else
                            Components(whole.rows(rows), pk.network_part(val), None))
                    ratios.append(conformal_ratios(val.b_ref, pk.compose(comp, new_session=False), level))
                timings["hybrid_inference"] += time.perf_counter() - t
                # only ever widen: a factor < 1 would trust the calibration blocks over the network's own sd
                # the K fold networks predict together (deep ensemble), with the scale their held-out folds gave
                pr = dataclasses.replace(pr, network=NetworkEnsemble(tuple(nets)),
                                         scale=np.maximum(conformal_quantile(np.concatenate(ratios), level), 1.0))
            nt = None
            if run_nets:
                t = time.perf_counter()
                nt = _network_transfer(pr, train, run_fold, run_nets, level, r_train)
                timings["hybrid_inference"] += time.perf_counter() - t
                hsm = None
                if (pr.sessions is not None and uq_settings is not None
                        and str(uq_settings.transfer).startswith("hierarchical")):
                    t = time.perf_counter()
                    hsm = hybrid_session_model(train, fit, nt, uq_settings,
                                               series=None if series is None else series[:2])
                    timings["hybrid_transfer"] = timings.get("hybrid_transfer", 0.0) + time.perf_counter() - t
                if hsm is not None:     # tau_n is inside the out-of-fold residuals: not added again
                    nt = dataclasses.replace(nt, session_model=hsm[0])
                    failed = (hsm[0].per_run or {}).get("model", {}).get("check", {}).get("failed_axes")
                    if failed and hsm[0].warning:   # raised with the run's others (it was in metrics.json only)
                        nan_messages.append(f"Residual network '{name}', the hybrid's session model (fitted on the "
                                            f"out-of-fold hybrid residuals; [uq] transfer_check only warns on it, and "
                                            f"its sd is kept): " + hsm[0].warning + " For this model a fourth cause "
                                            f"is measured: the fold networks' error on runs they did not see "
                                            f"(docs/sessions.md).")
                    pr = dataclasses.replace(pr, sessions=hsm[1], network_transfer_sd=None)
                else:
                    pr = dataclasses.replace(pr, network_transfer_sd=nt.sd)
            networks[name], predictors[name] = net, pr
            if test is not None:
                t = time.perf_counter()
                in_series = series is not None and pr.fit.model.needs_series
                tp = pr.transfer_part(series[0] if in_series else test)
                comp = Components(uq, pr.network_part(test), tp[series[2]] if in_series and tp is not None else tp)
                preds[name] = pr.compose(comp, new_session=new_session)
                timings["hybrid_inference"] += time.perf_counter() - t
                alts[name] = pr.compose(comp, fusion=other, new_session=new_session)
            training[name] = {**net.info_dict(), "train_seconds": round(train_s, 3)}
            if pr.scale is not None:
                training[name]["conformal"] = {"folds": n_folds, "block_fraction": round(fold_fraction, 6),
                                               "rows": int(np.sum(folds >= 0)),
                                               "ensemble_passes": list(ensemble_passes(net_cfg.mc_passes, n_folds))}
                for a, ax in enumerate(AXES):
                    training[name][ax]["interval_scale"] = float(pr.scale[a])
            budget = None if test is None else _new_session_budget(pr, preds[name], train,
                                                                    None if series is None else series[:2], test)
            if budget is not None:          # the certificate's U of the hybrid predictor (what `apply` uses)
                training[name]["budget"] = budget
            if nt is not None:
                training[name]["transfer_network"] = nt.as_dict()
                network_transfer[name] = nt
            if net.variance_scale is not None:
                for a, ax in enumerate(AXES):
                    training[name][ax]["variance_scale"] = float(net.variance_scale[a])
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return HybridStage(tuple(specs), networks, predictors, preds, alts, training, nan_messages, net_cfg.fusion,
                       other, network_transfer)


def _network_transfer(pr: Predictor, train: CalibrationData, run_fold: np.ndarray, run_nets: list,
                      level: float, resid: np.ndarray) -> NetworkTransfer:
    """The network part of the transfer sd (:mod:`~bayesmag._src.pipeline.network_transfer`) of the calibrated
    hybrid predictor ``pr``, from its by-run fold networks ``run_nets`` (network ``k`` never saw ``run_fold == k``);
    ``resid``: the physics residuals of ``train`` the networks learned (within the recording where needed)."""
    nn_oof = np.zeros(train.b_ref.shape)
    for k, nk in enumerate(run_nets):          # K <= network.conformal_folds MC predictions
        rows = np.flatnonzero(run_fold == k)
        nn_oof[rows] = dataclasses.replace(pr, network=nk).network_part(train.subset(rows)).mean
    nn_full = pr.network_part(train).mean
    inside = fold_domain_mask(train, run_fold)          # extrapolation is the domain check's, not transfer
    sd = network_transfer_sd(nn_oof[inside], nn_full[inside], train.run[inside], level) if inside.any() else np.zeros(3)
    rmse = lambda e: np.sqrt(np.mean(e[inside] ** 2, axis=0)) if inside.any() else np.full(3, np.nan)  # noqa: E731
    fold_runs = tuple(tuple(np.unique(train.run[run_fold == k]).tolist()) for k in range(len(run_nets)))
    return NetworkTransfer(sd, len(run_nets), fold_runs, rmse(resid - nn_oof), rmse(resid - nn_full), int(inside.sum()),
                           {"nn_oof": nn_oof, "nn_full": nn_full, "resid": resid, "run": train.run, "inside": inside})


def _new_session_budget(pr: Predictor, pred: Prediction, train: CalibrationData, series=None,
                        test: CalibrationData | None = None) -> dict:
    """The hybrid's new-session budget for the certificate (``app/report.py``): the within-session parts of
    ``pred`` (root mean square sd over its rows, the test rows in the calibration domain: the parts' squares add up
    to the rows' mean variance), the interval scale, the family's interval factor (the median over those rows of
    the central interval's half-width over the total sd: 1.96 for a Gaussian at 95 %, 2.12 for a Laplace, the
    certificate's k uses it), the transfer sd the hybrid adds to a new session (root mean square over the training
    rows) and, with a session model, at the training domain's corners."""
    ax = lambda v: {a: float(x) for a, x in zip(AXES, v)}  # noqa: E731
    names = ["aleatoric_nn", "epistemic_nn", "epistemic_physics"] + (["aleatoric_physics"] if pred.fusion == "paper"
                                                                     else [])
    # the means over the test rows inside the calibration domain (the certificate's U is stated there only)
    if test is not None and pr.domain is not None:
        from bayesmag._src.core.domain import budget_row_mask
        rows = budget_row_mask(pr.domain.outside(test, pred.mean))
    else:
        rows = slice(None)
    rms = lambda v: np.sqrt(np.mean(np.broadcast_to(np.asarray(v, np.float64), pred.mean.shape)[rows] ** 2,  # noqa: E731
                                    axis=0))
    lo, hi = pred.interval()
    factor = np.median(((hi - lo) / 2 / np.maximum(pred.total, 1e-300))[rows], axis=0)
    out = {"parts": {k: ax(rms(pred.parts[k])) for k in names}, "average": "rms",
           "interval_factor": ax(factor), "interval_level": float(pred.level),
           "interval_scale": ax(np.ones(3) if pr.scale is None else pr.scale),
           "transfer_sd": ax(np.sqrt(np.mean(new_session_transfer_rows(pr, train, series) ** 2, axis=0))),
           "family": pred.family}
    if pr.sessions is not None:
        from bayesmag._src.pipeline.sessions.hierarchical import condition_table

        class _Rows:        # the transfer sd the hybrid adds at a row, as condition_table asks a posterior for it
            transfer_sd_for = staticmethod(lambda fit, rows: new_session_transfer_rows(pr, rows))

        out["conditions"] = condition_table(_Rows(), pr.fit, train)
    return out


def hybrid_metrics(hs: HybridStage, y: np.ndarray, physics_mean: np.ndarray, level: float, passes: int, *,
                   scorer=M.score_per_axis) -> dict:
    """``hybrid``, ``hybrid_<other>_fusion``, ``hybrid_vs_physics`` and ``network`` blocks of metrics.json
    (``scorer``: :func:`~bayesmag.metrics.score_per_axis` or one with its results, e.g. the fleet's)."""
    scores, other, paired = {}, {}, {}
    for name, pred in hs.predictions.items():
        scores[name] = scorer(y, pred.dist, level, mean=pred.mean)
        alt = scorer(y, hs.alternates[name].dist, level, mean=hs.alternates[name].mean)
        other[name] = {k: alt[k] for k in ("coverage", "nll", "crps", "mean_width")}
        pt = M.paired_test(y - physics_mean, y - pred.mean)
        paired[name] = {ax: {"mean_diff": float(pt["mean_diff"][a]), "t": float(pt["t"][a]),
                             "p": float(pt["p"][a]), "cohens_d": float(pt["cohens_d"][a])}
                        for a, ax in enumerate(AXES)}
    first = hs.networks[hs.primary]
    return {
        "hybrid": scores,
        f"hybrid_{hs.other_fusion}_fusion": other,
        "hybrid_vs_physics": paired,
        "network": {
            "fusion": hs.fusion,
            "primary": hs.primary,
            "residual_physics_mean": "plug-in fit.predict on the training rows; PS-QMC mean on the test rows",
            "n_fit_rows": first.n_fit, "n_validation_rows": first.n_val,
            "n_params_per_axis": {s.likelihood: s.n_params for s in hs.specs},
            "mc_passes": passes,
            "training": hs.training,
            "warnings": hs.nan_messages,
        },
    }


def hybrid_columns(hs: HybridStage, y: np.ndarray, level: float) -> dict[str, np.ndarray]:
    """predictions.csv columns of the primary likelihood's hybrid prediction: its family by name
    (``hybrid_family``; with several ``network.likelihoods`` the columns are the first's) and its shape parameters
    per row (``hybrid_df`` of a Student-t, learned or fixed), so that its scores can be recomputed from the file."""
    pred = hs.predictions[hs.primary]
    lo, hi = pred.interval(level)
    shape = {f"hybrid_{k}": np.broadcast_to(np.asarray(getattr(pred.dist, k), np.float64), pred.mean.shape)
             for k in type(pred.dist).shape_names()}
    return {"hybrid_predicted": pred.mean, "aleatoric_nn": pred.aleatoric_nn, "epistemic_nn": pred.epistemic_nn,
            "hybrid_total": pred.total, "hybrid_lower": lo, "hybrid_upper": hi,
            "hybrid_covered": (y >= lo) & (y <= hi),
            "hybrid_family": np.full(pred.mean.shape, str(hs.primary), dtype=object), **shape}
