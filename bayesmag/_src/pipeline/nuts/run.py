"""``run_nuts``: sample the physics posterior of an LM fit and cross-check it (the package's entry point)."""

from __future__ import annotations

import json
import time
import warnings
from typing import Mapping, Sequence

import numpy as np

from bayesmag._src.core.fit import PhysicsFit
from bayesmag._src.core.physics import AXES
from bayesmag._src.pipeline.nuts.constants import NutsWarning
from bayesmag._src.pipeline.nuts.crosscheck import crosscheck
from bayesmag._src.pipeline.nuts.idata import build_idata, summary_frame
from bayesmag._src.pipeline.nuts.model import build_problem, white_cov
from bayesmag._src.pipeline.nuts.priors import NutsPriors, parse_priors
from bayesmag._src.pipeline.nuts.result import NutsResult
from bayesmag._src.pipeline.nuts.sampler import sample_nuts

__all__ = ["run_nuts"]


def run_nuts(data, fit: PhysicsFit, *, chains: int = 4, warmup: int = 1000, draws: int = 1000,
             target_accept: float = 0.8, chain_method: str = "vectorized", likelihood: str = "gaussian",
             priors: Mapping | NutsPriors | None = None, seed: int = 0, axes: Sequence[str] = AXES,
             progress: bool = False, pointwise_draws: int = 1000, predictive_draws: int = 200,
             parametrisation: str = "whitened", dense_mass: bool = False, max_tree_depth: int = 10,
             series=None) -> NutsResult:
    r"""Sample the physics posterior of ``fit`` with NUTS and cross-check it against the LM fit.

    Args:
      data: the :class:`~bayesmag.CalibrationData` ``fit`` was fitted on (with a reference).
      fit: a converged :class:`~bayesmag.PhysicsFit`; its model (extra terms included) is
        the likelihood's mean function, its estimate and covariance centre the priors and
        whiten the sampler.
      chains, warmup, draws, target_accept, chain_method, seed: NUTS settings (``[nuts]``).
      likelihood: observation model, a family of :mod:`bayesmag.likelihoods` (``"gaussian"``,
        ``"laplace"``, ``"student_t"``, or one registered by the user with ``to_numpyro``).
      priors: ``[nuts] priors`` table (:func:`parse_priors`) or a :class:`NutsPriors`.
      axes: the output axes to sample (each independently).
      progress: show a progress bar.
      pointwise_draws, predictive_draws: draws kept (evenly thinned, all chains together) in
        the log_likelihood and posterior_predictive groups, which share their draws (the
        larger of the two); they are (draws x rows x axes) arrays, so keeping all 4000 draws
        of 3000 rows would take ~300 MB.
      parametrisation: ``"whitened"`` (default, module docstring) or ``"scaled"``.
      dense_mass: adapt a dense mass matrix (useful with ``"scaled"``).
      series: optional ``(recording, index)`` with ``data = recording.subset(index)``, as the fit was made
        with ``fit_physics(recording, keep=)``: the model is evaluated on the whole recording and the
        likelihood takes the rows ``index``, so an input transform (a thermal lag) or a history term runs
        through held-out blocks rather than across them. Needed only for such models
        (``fit.model.needs_series``).
    Returns:
      :class:`NutsResult`; warnings found are also issued as :class:`NutsWarning`.

    Example:
      >>> import bayesmag as bm  # doctest: +SKIP
      >>> res = bm.run_nuts(train, bm.fit_physics(train), chains=4, draws=1000)  # doctest: +SKIP
      >>> res.verdicts["x"]  # doctest: +SKIP
      'Laplace approximation adequate: NUTS means within 0.021 LM sd ...'
    """
    t_all = time.perf_counter()
    if not data.has_reference:
        raise ValueError("run_nuts needs data with a reference field (b_ref).")
    if data.n != fit.n:
        raise ValueError(f"run_nuts: data has {data.n} rows but the fit was made on {fit.n}; pass the training rows.")
    if not fit.converged:
        raise ValueError(f"run_nuts: the LM fit did not converge ({dict(zip(AXES, fit.result))}); NUTS is whitened "
                         f"with its covariance, so fix the fit first.")
    if series is not None:
        recording, index = series
        index = np.asarray(index)
        if index.shape != (data.n,) or not np.array_equal(np.asarray(recording.b_meas)[index],
                                                           np.asarray(data.b_meas), equal_nan=True):
            raise ValueError("run_nuts: series = (recording, index) must give the training rows "
                             "(recording.subset(index) is data); it does not.")
        series = (recording, index)
    axes = tuple(axes)
    for ax in axes:
        if ax not in AXES:
            raise ValueError(f"run_nuts: axis {ax!r} is not one of {list(AXES)}.")
    if pointwise_draws < 1 or predictive_draws < 1:
        raise ValueError("run_nuts: pointwise_draws and predictive_draws must be >= 1.")
    pri = priors if isinstance(priors, NutsPriors) else parse_priors(priors, fit.param_names, likelihood=likelihood)
    learned = tuple(f for f, (_, learn) in pri.shape().items() if learn)
    problems = [build_problem(data, fit, ax, likelihood=likelihood, priors=pri, parametrisation=parametrisation,
                              series=series) for ax in axes]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", NutsWarning)
        dr = sample_nuts(problems, fit.model, likelihood=likelihood, learned=learned, chains=chains, warmup=warmup,
                         draws=draws, target_accept=target_accept, chain_method=chain_method, seed=seed,
                         progress=progress, max_tree_depth=max_tree_depth, dense_mass=dense_mass, names=axes)
    setting_warnings = [str(w.message) for w in caught if issubclass(w.category, NutsWarning)]
    for w in caught:                                   # re-issue everything, now that it is recorded
        warnings.warn(w.message, w.category, stacklevel=2)
    t_post = time.perf_counter()
    a_idx = [AXES.index(a) for a in axes]
    lm_cov = np.stack([np.asarray(pr.root) @ np.asarray(pr.root).T if parametrisation == "whitened"
                       else white_cov(data, fit, a, series) for pr, a in zip(problems, a_idx)])
    lm_theta = np.asarray(fit.theta)[a_idx]
    settings = {"chains": chains, "warmup": warmup, "draws": draws, "target_accept": target_accept,
                "chain_method": chain_method, "likelihood": likelihood, "seed": seed, "axes": list(axes),
                "parametrisation": parametrisation, "dense_mass": bool(dense_mass), "max_tree_depth": max_tree_depth,
                "pointwise_draws": pointwise_draws, "predictive_draws": predictive_draws,
                "priors": pri.describe(), "n_rows": data.n, "model": fit.model.describe()}
    attrs = {"created_by": "bayesmag.run_nuts", "likelihood": likelihood, "parametrisation": parametrisation,
             "max_tree_depth": max_tree_depth, "priors": json.dumps(pri.describe()),
             "settings": json.dumps({k: v for k, v in settings.items() if k not in ("priors", "model")})}
    idata = build_idata(dr, problems, axes, fit.param_names, fit.model, likelihood, pointwise_draws,
                         predictive_draws, lm_theta, lm_cov, attrs, seed)
    summary = summary_frame(idata, lm_theta, np.sqrt(np.diagonal(lm_cov, axis1=1, axis2=2)))
    high = {AXES[a]: fit.diagnostics[a]["high_corr_pairs"] for a in a_idx}
    fit_cov = None if fit.covariance_method == "white" else np.asarray(fit.cov)[a_idx]
    cc, verdicts, warns = crosscheck(idata, fit_cov=fit_cov, high_corr=high, likelihood=likelihood, summary=summary)
    if fit.covariance_method != "white":
        for ax in axes:
            r = cc[ax]["sd_ratio_vs_fit_covariance"]
            cc[ax]["note"] = (f"the fit's covariance is {fit.covariance_method!r}; the cross-check uses the white LM "
                              f"covariance (same independent-error likelihood as NUTS). Against the "
                              f"{fit.covariance_method} covariance the sd ratios are {min(r.values()):.2f}-"
                              f"{max(r.values()):.2f}.")
    for w in warns:
        warnings.warn(w, NutsWarning, stacklevel=2)
    t_end = time.perf_counter()
    seconds = dict(dr.seconds)
    seconds["postprocess"] = t_end - t_post
    seconds["total"] = t_end - t_all
    return NutsResult(idata=idata, summary=summary, crosscheck=cc, verdicts=verdicts,
                      warnings=tuple(setting_warnings + warns), seconds=seconds, settings=settings, fit=fit)

