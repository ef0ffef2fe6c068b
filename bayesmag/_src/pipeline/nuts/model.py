"""The NUTS model of one output axis: the problem arrays, the numpyro model and its whitening."""

from __future__ import annotations

from typing import Any, Mapping, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from numpyro.distributions import constraints

from bayesmag._src.core.fit import PhysicsFit, covariance
from bayesmag._src.core.likelihoods import get_likelihood
from bayesmag._src.core.physics import AXES, Inputs, PhysicsModel, inputs_from_data
from bayesmag._src.pipeline.nuts.constants import PARAMETRISATIONS
from bayesmag._src.pipeline.nuts.priors import NutsPriors, parse_priors

__all__ = ["NutsProblem", "nuts_model", "mean_of", "build_problem", "obs_dist", "constrain", "learned_shape", "chol_root",
           "white_cov"]


class NutsProblem(NamedTuple):
    """Everything one axis's posterior needs, as arrays (a pytree; stack problems to batch them).

    ``root`` is a square root of the LM covariance used for whitening (``root @ root.T``);
    ``scale_hat``/``scale_step`` whiten the noise scale; ``shape`` holds the family's shape
    fields (``{"df": ...}`` for Student-t), fixed or, when learned, the initial value.
    ``inputs`` is the series the model is evaluated on and ``rows`` the (n,) indices of the
    observed rows ``y`` in it: the training rows themselves, or, for a model whose rows depend on
    their neighbours (a thermal lag), the whole recording with the training rows picked out.
    """

    inputs: Inputs
    y: jax.Array            # (n,)
    rows: jax.Array         # (n,) int: the rows of ``inputs`` that ``y`` observes
    theta_hat: jax.Array    # (p,)
    root: jax.Array         # (p, p)
    prior_loc: jax.Array    # (p,)
    prior_sd: jax.Array     # (p,)
    scale_hat: jax.Array    # ()
    scale_step: jax.Array   # ()
    sigma_prior: jax.Array  # ()
    shape: dict             # {field: ()}


def obs_dist(family: str, mu, scale, shape: Mapping[str, Any]):
    """The numpyro observation distribution of a registered likelihood family."""
    cls = get_likelihood(family)
    return cls(loc=mu, scale=scale, **{f: shape[f] for f in cls.shape_names()}).to_numpyro()


def learned_shape(family: str, learn: Sequence[str] | bool) -> tuple[str, ...]:
    """The shape fields NUTS samples: ``learn`` names them (``True``: every field with a prior)."""
    cls = get_likelihood(family)
    if learn is True:
        return tuple(f for f, p in cls.shape_params.items() if p.prior is not None)
    if not learn:
        return ()
    bad = [f for f in learn if f not in cls.shape_params or cls.shape_params[f].prior is None]
    if bad:
        raise ValueError(f"likelihood {family!r} has no prior for shape field(s) {bad}; "
                         f"learnable: {[f for f, p in cls.shape_params.items() if p.prior is not None]}.")
    return tuple(learn)


def mean_of(physics: PhysicsModel, theta, problem: NutsProblem):
    """The model's prediction at the observed rows: evaluated on the series, then ``problem.rows`` taken."""
    return physics.predict(theta, problem.inputs)[problem.rows]


def constrain(problem: NutsProblem, params: dict, learned: Sequence[str] = ()) -> dict:
    """Physical parameters from the whitened sample sites (the model's own transform).

    A learned shape field ``f`` (positive) is ``exp(log f0 + v_f)`` around its initial value ``f0``.
    """
    theta = problem.theta_hat + problem.root @ params["z"]
    log_scale = jnp.log(problem.scale_hat) + problem.scale_step * params["u"]
    out = {"theta": theta, "sigma": jnp.exp(log_scale), "log_sigma": log_scale}
    for f in learned:
        out["log_" + f] = jnp.log(problem.shape[f]) + params["v_" + f]
        out[f] = jnp.exp(out["log_" + f])
    return out


def nuts_model(problem: NutsProblem, *, physics: PhysicsModel, family: str = "gaussian",
               learned: Sequence[str] = (), predictive: bool = False) -> None:
    r"""NumPyro model of one output axis (package docstring): whitened sites ``z``, ``u`` (``v_<field>``).

    Deterministic sites ``theta`` (p,), ``sigma`` (and each learned shape field) hold the
    physical values; the observation site is ``b_ref`` (n,), distributed as the registered
    family ``family`` (:meth:`~bayesmag.likelihoods.Likelihood.to_numpyro`).
    ``physics.predict`` is the model function of the LM fit. ``predictive=True`` leaves
    ``b_ref`` unobserved (posterior predictive draws).
    """
    p = problem.theta_hat.shape[-1]
    params = {
        "z": numpyro.sample("z", dist.ImproperUniform(constraints.real_vector, (), (p,))),
        "u": numpyro.sample("u", dist.ImproperUniform(constraints.real, (), ())),
    }
    for f in learned:
        params["v_" + f] = numpyro.sample("v_" + f, dist.ImproperUniform(constraints.real, (), ()))
    c = constrain(problem, params, learned)
    theta = numpyro.deterministic("theta", c["theta"])
    sigma = numpyro.deterministic("sigma", c["sigma"])
    numpyro.factor("theta_prior", jnp.sum(dist.Normal(problem.prior_loc, problem.prior_sd).log_prob(theta)))
    # prior on sigma plus log|d sigma / d u| of the whitening map
    numpyro.factor("sigma_prior", dist.HalfNormal(problem.sigma_prior).log_prob(sigma) + c["log_sigma"]
                   + jnp.log(problem.scale_step))
    shape = dict(problem.shape)
    params_of = get_likelihood(family).shape_params
    for f in learned:
        shape[f] = numpyro.deterministic(f, c[f])
        numpyro.factor(f + "_prior", params_of[f].prior().log_prob(shape[f]) + c["log_" + f])
    mu = mean_of(physics, theta, problem)
    numpyro.sample("b_ref", obs_dist(family, mu, sigma, shape), obs=None if predictive else problem.y)


def chol_root(cov: np.ndarray) -> np.ndarray:
    """A square root of ``cov`` (Cholesky of the correlation-scaled matrix; eigen fallback)."""
    d = np.sqrt(np.clip(np.diag(cov), 0, None))
    dd = np.where(d > 0, d, 1.0)
    R = cov / np.outer(dd, dd)
    R = 0.5 * (R + R.T)
    try:
        return d[:, None] * np.linalg.cholesky(R)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(R)
        return d[:, None] * (V * np.sqrt(np.clip(w, 1e-12 * w.max(), None)))


def _series(data, series):
    """The inputs the model runs on and the rows of ``data`` in them (``series = (recording, index)``)."""
    if series is None:
        return inputs_from_data(data), np.arange(data.n)
    recording, index = series
    return inputs_from_data(recording), np.asarray(index, dtype=np.int64)


def white_cov(data, fit: PhysicsFit, axis: int, series=None) -> np.ndarray:
    """The white LM covariance of ``axis`` on ``data`` (the fit's own when it is white)."""
    if fit.covariance_method == "white":
        return np.asarray(fit.cov[axis])
    inputs, rows = _series(data, series)
    th = jnp.asarray(fit.theta[axis])
    J = np.asarray(jax.jacfwd(fit.model.predict)(th, inputs))[rows]
    r = np.asarray(data.b_ref[:, axis]) - np.asarray(fit.model.predict(th, inputs))[rows]
    return covariance(J, r, method="white")[0]


def build_problem(data, fit: PhysicsFit, axis: int | str, *, likelihood: str = "gaussian",
                  priors: NutsPriors | Mapping | None = None, parametrisation: str = "whitened",
                  series=None) -> NutsProblem:
    """The :class:`NutsProblem` of output ``axis`` of ``fit`` on ``data`` (the rows it was fitted on).

    ``series = (recording, index)``: ``data`` is ``recording.subset(index)`` and the model is evaluated on
    the whole recording (as ``fit_physics(keep=)`` fitted it), so an input transform runs through the
    held-out blocks instead of across them.

    Raises:
      ValueError: unknown likelihood/parametrisation, or an LM standard error that is not
        finite and positive (the parameter is not identified: fix it or give it a prior).
    """
    a = AXES.index(axis) if isinstance(axis, str) else int(axis)
    family = get_likelihood(likelihood)
    if parametrisation not in PARAMETRISATIONS:
        raise ValueError(f"parametrisation {parametrisation!r} is not known; it must be one of "
                         f"{list(PARAMETRISATIONS)}.")
    if not isinstance(priors, NutsPriors):
        priors = parse_priors(priors, fit.param_names, likelihood=likelihood)
    names = fit.param_names
    cov = white_cov(data, fit, a, series)
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    theta_hat = np.asarray(fit.theta[a], dtype=np.float64)
    for j, name in enumerate(names):
        if not (np.isfinite(sd[j]) and sd[j] > 0):
            raise ValueError(f"The LM standard error of {name} on axis {AXES[a]} is {sd[j]!r}: the data do not "
                             f"identify it, so neither the whitening nor the default prior exist. Remove the term "
                             f"from the model or change the design so that the data identify it.")
    loc, psd = theta_hat.copy(), priors.scale * sd
    for (ax, name), (mean, s) in priors.overrides:
        if ax is None or ax == a:
            j = names.index(name)
            psd[j] = s
            if mean is not None:
                loc[j] = mean
    root = chol_root(cov) if parametrisation == "whitened" else np.diag(sd)
    inputs, rows = _series(data, series)
    y = np.asarray(data.b_ref[:, a], dtype=np.float64)
    r = y - np.asarray(fit.model.predict(jnp.asarray(theta_hat), inputs))[rows]
    n, p = y.size, theta_hat.size
    sd_r = float(np.sqrt(r @ r / max(n - p, 1)))
    shape0 = {f: v for f, (v, _) in priors.shape().items()}
    # the noise scale is whitened around the family's estimate from the LM residuals, with the step
    # 1/sqrt(I n) of its Fisher information I per row (Gaussian 2, Laplace and Student-t 1)
    scale_hat = family.scale_from_residuals(r, sd_r, **shape0)
    step = 1.0 / np.sqrt(family.log_scale_information * n)
    scale_hat = max(scale_hat, 1e-12 * (np.std(y) + 1e-300))
    sig = priors.sigma[a] if priors.sigma[a] is not None else float(np.std(y))
    f = lambda v: jnp.asarray(v, dtype=jnp.float64)  # noqa: E731
    return NutsProblem(inputs=inputs, y=f(y), rows=jnp.asarray(rows), theta_hat=f(theta_hat), root=f(root), prior_loc=f(loc), prior_sd=f(psd),
                       scale_hat=f(scale_hat), scale_step=f(step), sigma_prior=f(sig),
                       shape={k: f(v) for k, v in shape0.items()})

