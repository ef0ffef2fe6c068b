"""The stages of a calibration, each a pure function of library settings and rows to a frozen result.

* :func:`run_physics_stage` -> :class:`PhysicsStage`: LM fit, input noise, residual term, transfer
  (between-session) part, the physics :class:`~bayesmag.Predictor`, and its prediction of the test rows;
* :func:`~bayesmag._src.pipeline.hybrid.run_hybrid_stage` -> :class:`~bayesmag._src.pipeline.hybrid.HybridStage`:
  residual networks, cross-conformal scale, fused predictors;
* :func:`run_nuts_stage` -> :class:`~bayesmag.NutsResult`: the NUTS cross-check of the physics posterior.

:func:`~bayesmag.calibrate` runs them in that order.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from bayesmag._src.core.data import AXES, CalibrationData
from bayesmag._src.core.fit import PhysicsFit, fit_physics
from bayesmag._src.core.physics import PhysicsModel, inputs_from_data
from bayesmag._src.core.physics_uq import PhysicsUQ, physics_uncertainty
from bayesmag._src.core.predictor import Components, Prediction, Predictor, TransferEstimate, estimate_transfer
from bayesmag._src.pipeline.hybrid import HybridStage, run_hybrid_stage
from bayesmag._src.pipeline.settings import NutsSettings, UQSettings

__all__ = ["CalibrationError", "PhysicsStage", "HybridStage", "run_physics_stage", "run_hybrid_stage",
           "run_nuts_stage", "residual_variance"]


class CalibrationError(RuntimeError):
    """A calibration could not finish; the message says why and what to change."""


def residual_variance(uq: UQSettings, fit: PhysicsFit, train: CalibrationData, sigma_in: np.ndarray,
                      series=None) -> np.ndarray:
    """Per-axis residual variance beyond the propagated input noise, from the training rows only.

    ``max(s^2 - mean_train(aleatoric^2), 0)``: a fixed property of the calibration (stored in the
    artifact), so applying it later gives the same intervals as the run itself. ``series``: ``(recording,
    train_index)``, for a model whose rows depend on their neighbours (``PhysicsModel.needs_series``).
    """
    exact = fit.model.is_linear and fit.model.degree is not None
    whole = series is not None and fit.model.needs_series
    u = physics_uncertainty(fit, inputs_from_data(series[0] if whole else train), sigma_in=sigma_in,
                            method="analytic" if exact else uq.method,
                            n_params=min(uq.n_params, 50), n_qmc=min(uq.n_qmc, 256), seed=uq.seed,
                            chunk_size=uq.chunk_size)
    alea = np.asarray(u.aleatoric)[series[1]] if whole else u.aleatoric
    return np.maximum(fit.s2 - np.mean(alea**2, axis=0), 0.0)


@dataclasses.dataclass(frozen=True)
class PhysicsStage:
    """The physics stage's result: fit, noise model, predictor, and its prediction of the test rows
    (``uq``, ``prediction``, ``paper_prediction`` and ``new_session`` are None without test rows)."""

    fit: PhysicsFit
    sigma_in: np.ndarray
    sigma_source: str
    residual_sd: np.ndarray
    predictor: Predictor
    uq: PhysicsUQ | None                  # physics part on the test rows (shared with the hybrid stage)
    prediction: Prediction | None         # physics-only predictive distribution (with the residual term)
    paper_prediction: Prediction | None   # the paper's physics total sqrt(alea^2 + epi^2), for comparison
    transfer: TransferEstimate            # between-session sd (zero with transfer "off")
    new_session: np.ndarray | None        # (n_test,) test rows from runs the fit did not see (they get the transfer part)


def series_rows(parts, idx):
    """Rows ``idx`` of per-row results computed on a whole series (a :class:`PhysicsUQ`, an (n, 3) array or None)."""
    if parts is None:
        return None
    if isinstance(parts, PhysicsUQ):
        return parts.rows(idx)
    return np.asarray(parts)[idx]


#: what ``[uq] transfer = "off"`` leaves out, said as the other missing-transfer cases are (a script that chose it, or
#: misspelled another value before settings were checked, got intervals 85-93 % on new sessions without a word)
TRANSFER_OFF_WARNING = ("[uq] transfer = \"off\": the calibration holds no between-session (transfer) term, so its "
                        "intervals for a new session (another recording of the sensor) cover only the error within a "
                        "session and can be far too narrow. Use transfer = \"loro\" or \"hierarchical\" with 3 or "
                        "more recorded sessions.")


def run_physics_stage(uq_settings: UQSettings, train: CalibrationData, test: CalibrationData | None,
                      model: PhysicsModel, domain, timings: dict[str, float], *, covariance: str = "white",
                      progress: bool = False, after_fit=None, series=None) -> PhysicsStage:
    """Fit ``model`` on ``train`` and (when given) predict ``test`` through a :class:`Predictor`.

    ``series``: ``(recording, train_index, test_index)``, the recording ``train`` and ``test`` were cut from
    and their rows in it. A model whose rows depend on their neighbours (``PhysicsModel.needs_series``: a thermal lag, a
    timing offset, hysteresis) is fitted on the training rows within the whole recording
    (:func:`~bayesmag._src.core.fit.fit_physics` ``keep``) and predicts the test rows within it: alone, the lag
    would run across every held-out block as if the temperature had stopped, and each test block would restart
    it as at a run start.

    Adds ``timings["physics_fit"]``, ``["physics_uq"]`` and ``["transfer"]`` (s). ``after_fit(fit)``: called
    once the fit converged, before the uncertainty parts (the hybrid stage starts its training there).

    Raises:
        CalibrationError: the Levenberg-Marquardt fit did not converge.
        ValueError: an invalid ``sigma_in`` matrix.
    """
    t = time.perf_counter()
    whole = series is not None and model.needs_series
    if whole:
        keep = np.zeros(series[0].n, bool)
        keep[series[1]] = True
        fit = fit_physics(series[0], model, covariance_method=covariance, keep=keep)
    else:
        fit = fit_physics(train, model, covariance_method=covariance)
    timings["physics_fit"] = time.perf_counter() - t
    if not fit.converged:
        raise CalibrationError(f"The Levenberg-Marquardt fit did not converge: {dict(zip(AXES, fit.result))}. "
                               "Check the data for outliers or give a better starting point.")
    if after_fit is not None:
        after_fit(fit)

    t = time.perf_counter()
    sigma_in, sigma_src = uq_settings.sigma_in_matrix(train)
    # The paper's physics total sqrt(alea^2 + epi^2) leaves out the scatter the fit could not explain
    # (reference noise, model discrepancy): its 95% intervals cover 39-46% on the paper split. The residual
    # term is the fit's residual variance beyond what the propagated input noise already accounts for.
    resid_var = (residual_variance(uq_settings, fit, train, sigma_in, series=series[:2] if whole else None)
                 if uq_settings.residual_term else np.zeros(3))
    predictor = Predictor(fit=fit, sigma_in=sigma_in, residual_sd=np.sqrt(resid_var), domain=domain,
                          uq=uq_settings.options(), level=uq_settings.level)
    in_series = test is not None and whole
    if in_series:
        uq = series_rows(predictor.physics_part(series[0], progress=progress), series[2])
    else:
        uq = predictor.physics_part(test, progress=progress) if test is not None else None
    timings["physics_uq"] = time.perf_counter() - t

    t = time.perf_counter()
    sessions = None
    if uq_settings.transfer == "loro":
        tr = estimate_transfer(train, fit, series=series[:2] if whole else None)    # folds: one compiled fit
    elif uq_settings.transfer.startswith("hierarchical"):
        from bayesmag._src.pipeline.sessions import hierarchical_transfer
        tr, sessions = hierarchical_transfer(train, fit, method="nuts" if uq_settings.transfer.endswith("nuts") else
                                             "laplace", level=uq_settings.level, seed=uq_settings.seed,
                                             likelihood=uq_settings.transfer_likelihood, df=uq_settings.transfer_df,
                                             uninformed=uq_settings.transfer_uninformed,
                                             check=uq_settings.transfer_check,
                                             series=series[:2] if whole else None)
    else:
        tr = TransferEstimate(np.zeros(3), "off", {}, warning=TRANSFER_OFF_WARNING)
    predictor = dataclasses.replace(predictor, transfer_sd=None if sessions is not None else tr.sd,
                                    sessions=sessions)
    timings["transfer"] = time.perf_counter() - t
    if test is None:
        return PhysicsStage(fit, sigma_in, sigma_src, np.sqrt(resid_var), predictor, None, None, None, tr, None)
    new = ~np.isin(test.run, train.run)
    comp = Components(uq, None, series_rows(predictor.transfer_part(series[0]), series[2]) if in_series
                      else predictor.transfer_part(test))
    paper = dataclasses.replace(predictor, residual_sd=np.zeros(3), transfer_sd=None)
    return PhysicsStage(fit, sigma_in, sigma_src, np.sqrt(resid_var), predictor, uq,
                        predictor.compose(comp, new_session=new), paper.compose(comp), tr, new)


def run_nuts_stage(settings: NutsSettings, fit: PhysicsFit, train: CalibrationData, *, progress: bool = False,
                   series=None):
    """The NUTS cross-check of ``fit`` on ``train`` (:func:`~bayesmag.run_nuts`); a :class:`~bayesmag.NutsResult`.

    ``series = (recording, train_index)``: a model that needs its series (``fit.model.needs_series``) is
    evaluated on the whole recording, as it was fitted."""
    from bayesmag._src.pipeline.nuts import run_nuts

    import warnings

    from bayesmag._src.pipeline.nuts.constants import NutsWarning

    n = settings
    # every warning raised while sampling ends up once in res.warnings (the job prints them and puts them
    # in metrics.json), never as a raw Python warning line: the NutsWarnings are there already, any other
    # user or runtime warning (e.g. from NumPyro) is added once
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = run_nuts(train, fit, chains=n.chains, warmup=n.warmup, draws=n.draws, target_accept=n.target_accept,
                       chain_method=n.chain_method, likelihood=n.likelihood, priors=n.priors, seed=n.seed,
                       progress=progress, series=series if fit.model.needs_series else None)
    found = list(res.warnings)
    for w in caught:             # library deprecation notices are for developers, not a calibration's user
        if not issubclass(w.category, (UserWarning, RuntimeWarning)):
            continue
        msg = str(w.message) if issubclass(w.category, NutsWarning) else f"NUTS ({w.category.__name__}): {w.message}"
        if msg not in found:
            found.append(msg)
    return dataclasses.replace(res, warnings=tuple(dict.fromkeys(found)))
