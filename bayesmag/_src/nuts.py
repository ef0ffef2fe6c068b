r"""Full-Bayesian cross-check of the physics posterior with NumPyro NUTS.

The Levenberg-Marquardt fit (:func:`~bayesmag.fit_physics`) reports the Laplace
approximation :math:`\theta_i \sim \mathcal N(\hat\theta_i, \hat\Sigma_i)` of each output
axis :math:`i` (Shetty & Marndi 2026, sec. 2.2-2.3). This module samples the posterior the
approximation stands for, with the No-U-Turn Sampler (Hoffman & Gelman 2014) of NumPyro,
and says per axis whether the approximation is adequate.

**Model** (one axis; the three axes are independent, as in the row-wise LM fit):

.. math::

   y_k &\sim \mathcal D\big(f(x_k; \theta),\ \sigma\big), \quad k = 1..n, \\
   \theta_j &\sim \mathcal N(\hat\theta_j,\ (c\, \hat s_j)^2) \text{ independently}, \quad c = 100, \\
   \sigma &\sim \mathrm{HalfNormal}(\mathrm{sd}(y)), \qquad
   \nu \sim \mathrm{Gamma}(2, 0.1) \ \text{(Student-t only)},

with :math:`f` = :meth:`PhysicsModel.predict` -- the very function the LM fit minimises,
extra terms and input transforms included -- and :math:`\mathcal D` Normal (default),
Laplace or Student-t (numpyro distributions), :math:`\hat s_j` the LM standard error.

**Priors.** Centred at the LM estimate with 100 LM standard errors: weakly informative by
construction for every parameter whatever its units (a gain near 1, a thermal coefficient
near 1e-3 /C, an offset in uT). The prior adds :math:`10^{-4}` of the data precision in
each coordinate, so it moves posterior means and sds by less than about 1e-4 of an LM sd;
it exists to make the posterior proper, not to inform it. It uses the data twice (an
empirical-Bayes centre), which is harmless at this width and documented. Overrides go in
``[nuts] priors`` (:func:`parse_priors`): ``scale`` (the 100), a parameter name with an
absolute sd (``"Ks_x" = 0.1``, all axes) or ``{mean = ..., sd = ...}``, per-axis tables
(``y = {Ks_x = 0.1}``), ``sigma`` (HalfNormal scale of the noise, uT) and ``df`` (fixes the
Student-t degrees of freedom instead of learning them).

**Parametrisation.** With :math:`T_0 = 0` the S-Ks and O-Ko pairs are correlated beyond
:math:`|\rho| > 0.999` (the posterior is a needle), which makes NUTS on the raw parameters
take thousands of leapfrog steps per draw. We sample the whitened coordinates

.. math::  \theta = \hat\theta + L z, \qquad L L^T = \hat\Sigma_{\mathrm{white}}, \qquad
           \sigma = \hat\sigma \exp(u / \sqrt{2n}),

with the priors above written on :math:`\theta` and :math:`\sigma` (the map is linear with
a constant Jacobian for :math:`\theta`; the :math:`\sigma` Jacobian is added), so the
posterior is exactly the same; only the geometry NUTS sees changes. We chose whitening over
``dense_mass=True`` because the LM fit already delivers the covariance: the target is
near-isotropic from the first warm-up iteration, whereas a dense mass matrix has to be
learned from early warm-up draws that mix badly in a condition-number-1e12 posterior. A
diagonal mass matrix is still adapted on top. ``parametrisation="scaled"`` (per-parameter
standardisation only) with ``dense_mass=True`` is available for comparison
(``benchmarks/bench_nuts.py --parametrisation scaled --dense-mass``).

**Cross-check.** Per parameter, :math:`(\bar\theta_\mathrm{NUTS} - \hat\theta)/\hat s`
and :math:`\mathrm{sd}_\mathrm{NUTS}/\hat s`, the largest correlation differences and the
eigenvalues of the NUTS covariance in whitened coordinates (all 1 when the Laplace
approximation is exact). For the linear Gaussian model the exact posterior is a
multivariate t with :math:`n-p` degrees of freedom, so the expected sd ratio is
:math:`\sqrt{(n-p)/(n-p-2)} \approx 1`; deviations beyond :data:`MEAN_DIFF_TOL` and
:data:`SD_RATIO_RANGE` mean the Laplace approximation (or the sampler) is wrong there.

The reference is the *white* LM covariance :math:`s^2 (J^T J)^{-1}` because it is the
Laplace approximation of this independent-error posterior; if the fit was made with
``covariance="ar1"``/``"newey_west"`` the cross-check also reports the sd ratio against
that covariance (NUTS with independent errors is then expected to be narrower).

References:
    Hoffman, M. D. & Gelman, A. (2014). The No-U-Turn Sampler. JMLR 15, 1593-1623.
    Vehtari, A., Gelman, A., Simpson, D., Carpenter, B. & Bürkner, P.-C. (2021).
    Rank-normalization, folding, and localization: an improved R-hat. Bayesian Analysis 16(2).
    Vehtari, A., Gelman, A. & Gabry, J. (2017). Practical Bayesian model evaluation using
    leave-one-out cross-validation and WAIC. Statistics and Computing 27, 1413-1432.
    Juárez, M. A. & Steel, M. F. J. (2010). Model-based clustering of non-Gaussian panel
    data based on skew-t distributions. JBES 28(1) (the Gamma(2, 0.1) prior on nu).
    Shetty & Marndi (2026). Hybrid physics + heteroscedastic-network magnetometer calibration.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
import warnings
from pathlib import Path
from typing import Any, Mapping, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from numpyro.distributions import constraints
from numpyro.infer.hmc import hmc
from numpyro.infer.util import log_density, potential_energy

from .config import ConfigError
from .fit import PhysicsFit, covariance
from .physics import AXES, Inputs, PhysicsModel, inputs_from_data

__all__ = [
    "NutsPriors", "parse_priors", "NutsProblem", "build_problem", "nuts_model", "NutsDraws", "sample_nuts",
    "NutsResult", "run_nuts", "crosscheck", "loo", "compare_models", "write_nuts_outputs", "run_nuts_stage",
    "check_settings", "NutsWarning", "FAMILIES", "RHAT_MAX", "ESS_MIN", "MEAN_DIFF_TOL", "SD_RATIO_RANGE",
]

#: Observation models: the ``likelihood`` names of ``[nuts]`` and the numpyro family used.
FAMILIES = ("gaussian", "laplace", "student_t")
#: Largest acceptable rank-normalised split R-hat (Vehtari et al. 2021).
RHAT_MAX = 1.01
#: Smallest acceptable bulk and tail ESS (Vehtari et al. 2021: 100 per chain with 4 chains).
ESS_MIN = 400
#: Largest |mean_NUTS - theta_LM| / sd_LM for "Laplace approximation adequate". The Monte
#: Carlo error of a posterior mean is ~1/sqrt(ESS) = 0.05 sd at ESS 400, so 0.2 is 4 MCSE.
MEAN_DIFF_TOL = 0.2
#: Acceptable sd_NUTS / sd_LM. The MC error of an sd at ESS 400 is ~1/sqrt(2*400) = 3.5%.
SD_RATIO_RANGE = (0.9, 1.1)
#: Fewer draws per chain than this (or fewer than 2 chains) make R-hat/ESS unreliable: warning.
MIN_DRAWS = 100
MIN_CHAINS = 2
#: Default prior sd of each physics parameter, in LM standard errors.
DEFAULT_PRIOR_SCALE = 100.0
#: Gamma(shape, rate) prior on the Student-t degrees of freedom (Juárez & Steel 2010).
DF_PRIOR = (2.0, 0.1)
#: Initial points: whitened coordinates drawn uniformly in [-INIT_RADIUS, INIT_RADIUS] (as
#: numpyro's init_to_uniform), overdispersed against the unit-scale whitened posterior.
INIT_RADIUS = 2.0
#: E-BFMI below this signals poor exploration of the energy distribution (Betancourt 2016).
EBFMI_MIN = 0.3

_RESERVED = ("scale", "sigma", "df")


class NutsWarning(UserWarning):
    """A NUTS result that should not be trusted as it stands; the message names the fix."""


# --------------------------------------------------------------------------- priors


@dataclasses.dataclass(frozen=True)
class NutsPriors:
    """Validated prior settings (see the module docstring and :func:`parse_priors`).

    Attributes:
      scale: prior sd of every physics parameter in LM standard errors (default 100).
      overrides: ``{(axis or None, parameter): (mean or None, sd)}``; mean None = LM estimate,
        axis None = every axis. Absolute units of the parameter.
      sigma: HalfNormal scale of the per-axis noise scale in uT, per axis; None = sd of the
        reference field on that axis.
      df: fixed Student-t degrees of freedom; None = learned with a Gamma(2, 0.1) prior.
    """

    scale: float = DEFAULT_PRIOR_SCALE
    overrides: tuple = ()
    sigma: tuple = (None, None, None)
    df: float | None = None

    def describe(self) -> dict:
        return {
            "theta": f"Normal(LM estimate, ({self.scale:g} x LM standard error)^2), independent",
            "overrides": {(f"{AXES[a]}." if a is not None else "") + name: {"mean": m, "sd": s}
                          for (a, name), (m, s) in self.overrides},
            "sigma": {ax: (f"HalfNormal({s:g})" if s is not None else "HalfNormal(sd of the reference on this axis)")
                      for ax, s in zip(AXES, self.sigma)},
            "df": (f"fixed at {self.df:g}" if self.df is not None
                   else f"Gamma({DF_PRIOR[0]:g}, rate {DF_PRIOR[1]:g}) (student_t only)"),
        }


def _positive(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"[nuts] priors.{where} = {value!r} must be a finite number > 0.")
    return float(value)


def _param_prior(value, where: str) -> tuple[float | None, float]:
    if isinstance(value, dict):
        unknown = set(value) - {"mean", "sd"}
        if unknown or "sd" not in value:
            raise ConfigError(f"[nuts] priors.{where} = {value!r} must be a number (the prior sd, centred at the LM "
                              f"estimate) or a table {{mean = ..., sd = ...}} with 'sd' given.")
        mean = value.get("mean")
        if mean is not None and (isinstance(mean, bool) or not isinstance(mean, (int, float))
                                 or not math.isfinite(mean)):
            raise ConfigError(f"[nuts] priors.{where}.mean = {mean!r} must be a finite number.")
        return (None if mean is None else float(mean)), _positive(value["sd"], where + ".sd")
    return None, _positive(value, where)


def parse_priors(priors: Mapping | None, param_names: Sequence[str], *, likelihood: str = "gaussian") -> NutsPriors:
    """Validate ``[nuts] priors`` against a model's parameter names.

    Keys: ``scale`` (> 0, prior sd in LM standard errors), ``sigma`` (> 0, HalfNormal scale
    of the noise in uT; a number or a table by axis), ``df`` (> 0, fixes the Student-t
    degrees of freedom; only with ``likelihood = "student_t"``), a parameter name (a number:
    the prior sd around the LM estimate in the parameter's units; or ``{mean, sd}``), or an
    axis ``x``/``y``/``z`` holding a table of parameter priors for that axis only.

    Raises:
      ConfigError: (a ValueError) naming the bad key or value and the valid choices.

    Example:
      >>> p = parse_priors({"scale": 10.0, "Ks_x": 0.1, "y": {"O": {"mean": 0.0, "sd": 5.0}}},
      ...                  ("S_x", "Ks_x", "O"))
      >>> p.scale, dict(p.overrides)[(None, "Ks_x")], dict(p.overrides)[(1, "O")]
      (10.0, (None, 0.1), (0.0, 5.0))
    """
    if priors is None:
        priors = {}
    if not isinstance(priors, Mapping):
        raise ConfigError(f"[nuts] priors = {priors!r} must be a table, e.g. {{scale = 10.0, \"Ks_x\" = 0.1}}.")
    if likelihood not in FAMILIES:
        raise ConfigError(f"[nuts] likelihood = {likelihood!r} is not valid; it must be one of {list(FAMILIES)}.")
    names = tuple(param_names)
    valid = f"'scale', 'sigma', 'df', an axis {list(AXES)} or a parameter name {list(names)}"
    scale, df, sigma, overrides = DEFAULT_PRIOR_SCALE, None, [None, None, None], {}
    for key, value in priors.items():
        if key == "scale":
            scale = _positive(value, "scale")
        elif key == "df":
            if likelihood != "student_t":
                raise ConfigError(f"[nuts] priors.df = {value!r} applies only to likelihood = \"student_t\" "
                                  f"(this job uses {likelihood!r}).")
            df = _positive(value, "df")
        elif key == "sigma":
            if isinstance(value, dict):
                for ax, v in value.items():
                    if ax not in AXES:
                        raise ConfigError(f"[nuts] priors.sigma has unknown axis {ax!r}; valid: {list(AXES)}.")
                    sigma[AXES.index(ax)] = _positive(v, f"sigma.{ax}")
            else:
                sigma = [_positive(value, "sigma")] * 3
        elif key in AXES:
            if not isinstance(value, dict):
                raise ConfigError(f"[nuts] priors.{key} = {value!r} must be a table of parameter priors for axis "
                                  f"{key}, e.g. {key} = {{\"{names[0]}\" = 0.1}}.")
            for name, v in value.items():
                if name not in names:
                    raise ConfigError(f"[nuts] priors.{key}.{name}: unknown parameter {name!r}; this model's "
                                      f"parameters are {list(names)}.")
                overrides[(AXES.index(key), name)] = _param_prior(v, f"{key}.{name}")
        elif key in names:
            overrides[(None, key)] = _param_prior(value, key)
        else:
            raise ConfigError(f"[nuts] priors has unknown key {key!r}; valid keys: {valid}.")
    order = sorted(overrides.items(), key=lambda kv: (kv[0][0] is not None, kv[0][0] or 0, kv[0][1]))
    return NutsPriors(scale=scale, overrides=tuple(order), sigma=tuple(sigma), df=df)


# --------------------------------------------------------------------------- the model


class NutsProblem(NamedTuple):
    """Everything one axis's posterior needs, as arrays (a pytree; stack problems to batch them).

    ``root`` is a square root of the LM covariance used for whitening (``root @ root.T``);
    ``scale_hat``/``scale_step`` whiten the noise scale; ``df`` is the fixed (or initial)
    Student-t degrees of freedom.
    """

    inputs: Inputs
    y: jax.Array            # (n,)
    theta_hat: jax.Array    # (p,)
    root: jax.Array         # (p, p)
    prior_loc: jax.Array    # (p,)
    prior_sd: jax.Array     # (p,)
    scale_hat: jax.Array    # ()
    scale_step: jax.Array   # ()
    sigma_prior: jax.Array  # ()
    df: jax.Array           # ()


def _obs_dist(family: str, mu, scale, df):
    if family == "gaussian":
        return dist.Normal(mu, scale)
    if family == "laplace":
        return dist.Laplace(mu, scale)
    if family == "student_t":
        return dist.StudentT(df, mu, scale)
    raise ValueError(f"likelihood {family!r} is not known; it must be one of {list(FAMILIES)}")


def _constrain(problem: NutsProblem, params: dict, learn_df: bool) -> dict:
    """Physical parameters from the whitened sample sites (the model's own transform)."""
    theta = problem.theta_hat + problem.root @ params["z"]
    log_scale = jnp.log(problem.scale_hat) + problem.scale_step * params["u"]
    out = {"theta": theta, "sigma": jnp.exp(log_scale), "log_sigma": log_scale}
    if learn_df:
        out["log_df"] = jnp.log(problem.df) + params["v"]
        out["df"] = jnp.exp(out["log_df"])
    return out


def nuts_model(problem: NutsProblem, *, physics: PhysicsModel, family: str = "gaussian", learn_df: bool = False,
               predictive: bool = False) -> None:
    r"""NumPyro model of one output axis (module docstring): whitened sites ``z``, ``u`` (``v``).

    Deterministic sites ``theta`` (p,), ``sigma`` (and ``df``) hold the physical values;
    the observation site is ``b_ref`` (n,). ``physics.predict`` is the model function of the
    LM fit. ``predictive=True`` leaves ``b_ref`` unobserved (posterior predictive draws).
    """
    p = problem.theta_hat.shape[-1]
    params = {
        "z": numpyro.sample("z", dist.ImproperUniform(constraints.real_vector, (), (p,))),
        "u": numpyro.sample("u", dist.ImproperUniform(constraints.real, (), ())),
    }
    if learn_df:
        params["v"] = numpyro.sample("v", dist.ImproperUniform(constraints.real, (), ()))
    c = _constrain(problem, params, learn_df)
    theta = numpyro.deterministic("theta", c["theta"])
    sigma = numpyro.deterministic("sigma", c["sigma"])
    numpyro.factor("theta_prior", jnp.sum(dist.Normal(problem.prior_loc, problem.prior_sd).log_prob(theta)))
    # prior on sigma plus log|d sigma / d u| of the whitening map
    numpyro.factor("sigma_prior", dist.HalfNormal(problem.sigma_prior).log_prob(sigma) + c["log_sigma"]
                   + jnp.log(problem.scale_step))
    df = problem.df
    if learn_df:
        df = numpyro.deterministic("df", c["df"])
        numpyro.factor("df_prior", dist.Gamma(*DF_PRIOR).log_prob(df) + c["log_df"])
    mu = physics.predict(theta, problem.inputs)
    numpyro.sample("b_ref", _obs_dist(family, mu, sigma, df), obs=None if predictive else problem.y)


def _chol_root(cov: np.ndarray) -> np.ndarray:
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


def _white_cov(data, fit: PhysicsFit, axis: int) -> np.ndarray:
    if fit.covariance_method == "white":
        return np.asarray(fit.cov[axis])
    inputs = inputs_from_data(data)
    th = jnp.asarray(fit.theta[axis])
    J = np.asarray(jax.jacfwd(fit.model.predict)(th, inputs))
    r = np.asarray(data.b_ref[:, axis]) - np.asarray(fit.model.predict(th, inputs))
    return covariance(J, r, method="white")[0]


def build_problem(data, fit: PhysicsFit, axis: int | str, *, likelihood: str = "gaussian",
                  priors: NutsPriors | Mapping | None = None, parametrisation: str = "whitened") -> NutsProblem:
    """The :class:`NutsProblem` of output ``axis`` of ``fit`` on ``data`` (the rows it was fitted on).

    Raises:
      ValueError: unknown likelihood/parametrisation, or an LM standard error that is not
        finite and positive (the parameter is not identified: fix it or give it a prior).
    """
    a = AXES.index(axis) if isinstance(axis, str) else int(axis)
    if likelihood not in FAMILIES:
        raise ValueError(f"likelihood {likelihood!r} is not known; it must be one of {list(FAMILIES)}.")
    if parametrisation not in ("whitened", "scaled"):
        raise ValueError(f"parametrisation {parametrisation!r} is not known; it must be 'whitened' or 'scaled'.")
    if not isinstance(priors, NutsPriors):
        priors = parse_priors(priors, fit.param_names, likelihood=likelihood)
    names = fit.param_names
    cov = _white_cov(data, fit, a)
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
    root = _chol_root(cov) if parametrisation == "whitened" else np.diag(sd)
    inputs = inputs_from_data(data)
    y = np.asarray(data.b_ref[:, a], dtype=np.float64)
    r = y - np.asarray(fit.model.predict(jnp.asarray(theta_hat), inputs))
    n, p = y.size, theta_hat.size
    sd_r = float(np.sqrt(r @ r / max(n - p, 1)))
    df0 = priors.df if priors.df is not None else 4.0
    if likelihood == "gaussian":
        scale_hat, step = sd_r, 1.0 / np.sqrt(2.0 * n)
    elif likelihood == "laplace":
        scale_hat, step = float(np.mean(np.abs(r))), 1.0 / np.sqrt(n)
    else:
        scale_hat, step = sd_r * np.sqrt(max(df0 - 2.0, 0.5) / df0), 1.0 / np.sqrt(n)
    scale_hat = max(scale_hat, 1e-12 * (np.std(y) + 1e-300))
    sig = priors.sigma[a] if priors.sigma[a] is not None else float(np.std(y))
    f = lambda v: jnp.asarray(v, dtype=jnp.float64)  # noqa: E731
    return NutsProblem(inputs=inputs, y=f(y), theta_hat=f(theta_hat), root=f(root), prior_loc=f(loc), prior_sd=f(psd),
                       scale_hat=f(scale_hat), scale_step=f(step), sigma_prior=f(sig), df=f(df0))


# --------------------------------------------------------------------------- the sampler


class NutsDraws(NamedTuple):
    """Raw output of :func:`sample_nuts` for B stacked problems, C chains, D draws (after warm-up).

    ``sites`` are the whitened sample sites, ``theta`` (B, C, D, p), ``sigma`` and ``df``
    (B, C, D; ``df`` None unless learned) their physical values; ``stats`` (B, C, D) hold
    ``diverging``, ``n_steps``, ``acceptance_rate``, ``energy``, ``lp`` and ``step_size``;
    ``warmup_divergences`` (B, C); ``seconds`` the compile and sampling wall times.
    """

    sites: dict
    theta: np.ndarray
    sigma: np.ndarray
    df: np.ndarray | None
    stats: dict
    warmup_divergences: np.ndarray
    seconds: dict


def check_settings(*, chains: int, warmup: int, draws: int, target_accept: float,
                   chain_method: str = "vectorized") -> list[str]:
    """Validate sampler settings; return warnings for settings too small for trustworthy diagnostics.

    Rule: fewer than :data:`MIN_CHAINS` chains (no between-chain R-hat) or fewer than
    :data:`MIN_DRAWS` draws per chain (R-hat and ESS estimates are themselves noisy) ->
    a warning naming the setting. Impossible settings raise ``ValueError``.

    Example:
      >>> check_settings(chains=1, warmup=100, draws=50, target_accept=0.8)[0][:40]
      '[nuts] chains = 1: R-hat compares chains'
    """
    for name, v, lo in (("chains", chains, 1), ("draws", draws, 4), ("warmup", warmup, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise ValueError(f"[nuts] {name} = {v!r} must be an integer >= {lo}.")
    if not 0 < target_accept < 1:
        raise ValueError(f"[nuts] target_accept = {target_accept!r} must be in (0, 1); 0.8 is the default, "
                         f"0.9-0.99 for difficult posteriors.")
    if chain_method not in ("vectorized", "parallel", "sequential"):
        raise ValueError(f"[nuts] chain_method = {chain_method!r} must be one of ['vectorized', 'parallel', "
                         f"'sequential'].")
    out = []
    if chains < MIN_CHAINS:
        out.append(f"[nuts] chains = {chains}: R-hat compares chains, so it needs at least {MIN_CHAINS} "
                   f"(4 recommended); convergence is unchecked.")
    if draws < MIN_DRAWS:
        out.append(f"[nuts] draws = {draws} per chain is too few for reliable R-hat and ESS (need >= {MIN_DRAWS}; "
                   f"1000 recommended).")
    if warmup < MIN_DRAWS:
        out.append(f"[nuts] warmup = {warmup} is too short for step-size and mass-matrix adaptation "
                   f"(need >= {MIN_DRAWS}; 1000 recommended).")
    return out


_PROGRESS: dict[str, Any] = {"bar": None}


def _tick(k) -> None:
    bar = _PROGRESS["bar"]
    if bar is not None:
        bar.update(int(k))


def _hashable(x) -> bool:
    try:
        hash(x)
        return True
    except TypeError:
        return False


class _Sampler(NamedTuple):
    model: Any          # the numpyro model with its static options bound
    run: Any            # jitted (z0, keys, problems) -> (sites, stats) for vectorized/sequential
    run_chain: Any      # (z0, key, problem) -> (sites, stats), single chain (for pmap)
    potential: Any      # jitted (params, problem) -> (pe, grad)
    compiled: dict


def _make_sampler(physics, family, learn_df, warmup, total, target_accept, chain_method, max_tree_depth,
                  dense_mass, every):
    model = functools.partial(nuts_model, physics=physics, family=family, learn_df=learn_df)

    def pe_gen(problem):
        return lambda params: potential_energy(model, (problem,), {}, params)

    init_kernel, sample_kernel = hmc(potential_fn_gen=pe_gen, algo="NUTS")

    def init(z0, key, problem):
        return init_kernel(z0, warmup, target_accept_prob=target_accept, max_tree_depth=max_tree_depth,
                           dense_mass=dense_mass, model_args=(problem,), rng_key=key)

    def step(state, problem):
        return sample_kernel(state, model_args=(problem,))

    def collect(s):
        return s.z, {"diverging": s.diverging, "n_steps": s.num_steps, "acceptance_rate": s.accept_prob,
                     "energy": s.energy, "lp": -s.potential_energy, "step_size": s.adapt_state.step_size}

    def tick(i):
        jax.lax.cond((i + 1) % every == 0, lambda: jax.debug.callback(_tick, every), lambda: None)

    def scan_chains(state, problem, stepper):
        def body(s, i):
            s = stepper(s, problem)
            tick(i)
            return s, collect(s)
        return jax.lax.scan(body, state, jnp.arange(total))[1]

    def run_chain(z0, key, problem):
        return scan_chains(init(z0, key, problem), problem, step)

    def run_problem(args):
        z0, keys, problem = args
        if chain_method == "vectorized":
            state = jax.vmap(init, in_axes=(0, 0, None))(z0, keys, problem)
            out = scan_chains(state, problem, jax.vmap(step, in_axes=(0, None)))
            return jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), out)     # (C, T, ...)
        return jax.lax.map(lambda a: run_chain(a[0], a[1], problem), (z0, keys))

    run = jax.jit(lambda z0, keys, problems: jax.lax.map(run_problem, (z0, keys, problems)))
    potential = jax.jit(jax.vmap(jax.vmap(jax.value_and_grad(lambda params, pr: pe_gen(pr)(params)),
                                          in_axes=(0, None)), in_axes=(0, 0)))
    return _Sampler(model=model, run=run, run_chain=run_chain, potential=potential, compiled={})


_make_sampler_cached = functools.lru_cache(maxsize=16)(_make_sampler)


def _stack(problems: Sequence[NutsProblem]) -> NutsProblem:
    shapes = {jax.tree.map(jnp.shape, p).__repr__() for p in problems}
    if len(shapes) != 1:
        raise ValueError("sample_nuts: all problems must have the same shapes (rows and parameters) to be batched.")
    return jax.tree.map(lambda *x: jnp.stack(x), *problems)


def _site_shapes(p: int, learn_df: bool) -> dict:
    out = {"z": (p,), "u": ()}
    if learn_df:
        out["v"] = ()
    return out


def _init_points(problems: NutsProblem, sampler, B: int, C: int, p: int, learn_df: bool, seed: int,
                 axis_names: Sequence[str]) -> dict:
    """Overdispersed, finite initial points; a clear error if the LM estimate itself is not finite."""
    shapes = _site_shapes(p, learn_df)
    zero = {k: jnp.zeros((B, 1) + s) for k, s in shapes.items()}
    pe0, g0 = sampler.potential(zero, problems)
    pe0 = np.asarray(pe0)[:, 0]
    g_ok = np.asarray(jnp.all(jnp.stack([jnp.all(jnp.isfinite(v), axis=tuple(range(2, v.ndim)))
                                         for v in jax.tree.leaves(g0)]), axis=0))[:, 0]
    for b in range(B):
        if not (np.isfinite(pe0[b]) and g_ok[b]):
            pr = jax.tree.map(lambda x: x[b], problems)
            raise ValueError(_nonfinite_message(pr, sampler.model, axis_names[b], learn_df, p))
    rng = np.random.default_rng(seed)
    z0 = {k: rng.uniform(-INIT_RADIUS, INIT_RADIUS, (B, C) + s) for k, s in shapes.items()}
    for _ in range(6):
        pe, g = sampler.potential(jax.tree.map(jnp.asarray, z0), problems)
        ok = np.isfinite(np.asarray(pe))
        for v in jax.tree.leaves(g):
            ok &= np.asarray(jnp.all(jnp.isfinite(v), axis=tuple(range(2, v.ndim))))
        if ok.all():
            break
        for k in z0:
            z0[k][~ok] *= 0.5
    else:
        for k in z0:
            z0[k][~ok] = 0.0
    return jax.tree.map(jnp.asarray, z0)


def _nonfinite_message(problem: NutsProblem, model_fn, axis_name: str, learn_df: bool, p: int) -> str:
    """Which term of the log-density is not finite at the LM estimate (z = u = 0)."""
    params = {k: jnp.zeros(s) for k, s in _site_shapes(p, learn_df).items()}
    bad = []
    try:
        _, tr = log_density(model_fn, (problem,), {}, params)
        for name, site in tr.items():
            if site["type"] == "deterministic" and not np.all(np.isfinite(np.asarray(site["value"]))):
                bad.append(f"'{name}' = {np.asarray(site['value'])}")
            elif site["type"] == "sample":
                lp = np.asarray(site["fn"].log_prob(site["value"]))
                if not np.all(np.isfinite(lp)):
                    bad.append(f"the likelihood '{name}' ({int(np.sum(~np.isfinite(lp)))} non-finite row(s))"
                               if site.get("is_observed") else f"the prior term '{name}'")
    except Exception as e:  # pragma: no cover - the message is the product here
        bad.append(f"evaluating the model ({type(e).__name__}: {e})")
    what = "; ".join(bad) if bad else "the gradient of the log-density"
    return (f"NUTS: the log-density is not finite at the initial point (the LM estimate) on axis {axis_name}: "
            f"{what} is not finite. Check that the fit converged with finite parameters, that the training rows "
            f"have no non-finite values, and that [nuts] priors are positive and finite.")


def sample_nuts(problems: Sequence[NutsProblem], physics: PhysicsModel, *, likelihood: str = "gaussian",
                learn_df: bool = False, chains: int = 4, warmup: int = 1000, draws: int = 1000,
                target_accept: float = 0.8, chain_method: str = "vectorized", seed: int = 0, progress: bool = False,
                max_tree_depth: int = 10, dense_mass: bool = False, names: Sequence[str] | None = None) -> NutsDraws:
    """Run NUTS on independent problems (axes, or repeated simulations) in one compiled program.

    The problems are mapped over sequentially inside one ``jit`` and their chains are
    vectorised (``jax.vmap``, the default), mapped (``"sequential"``) or spread over devices
    (``"parallel"``, ``jax.pmap``; needs ``numpyro.set_host_device_count(chains)`` before
    JAX starts, else it falls back to sequential with a warning). Each problem adapts its own
    step size and diagonal mass matrix. Compiled programs are cached per model, settings
    and shapes, so repeated calls compile once.

    Args:
      problems: :class:`NutsProblem` s of equal shapes (see :func:`build_problem`).
      physics: the model whose ``predict`` the problems were built for.
      names: labels for error messages (default the axis names or problem indices).
    Returns:
      :class:`NutsDraws`.
    """
    for w in check_settings(chains=chains, warmup=warmup, draws=draws, target_accept=target_accept,
                            chain_method=chain_method):
        warnings.warn(w, NutsWarning, stacklevel=2)
    if likelihood not in FAMILIES:
        raise ValueError(f"likelihood {likelihood!r} is not known; it must be one of {list(FAMILIES)}.")
    learn_df = bool(learn_df and likelihood == "student_t")
    problems = list(problems)
    B, p = len(problems), int(problems[0].theta_hat.shape[-1])
    names = list(names) if names is not None else [str(i) for i in range(B)]
    stacked = _stack(problems)
    method = chain_method
    if method == "parallel" and (chains < 2 or jax.local_device_count() < chains):
        if chains >= 2:
            warnings.warn(f"[nuts] chain_method = \"parallel\" needs {chains} devices but JAX sees "
                          f"{jax.local_device_count()}; call numpyro.set_host_device_count({chains}) before JAX "
                          f"starts to run chains on separate CPU cores. Running the chains sequentially instead.",
                          NutsWarning, stacklevel=2)
        method = "sequential"
    total = warmup + draws
    every = max(1, total // 50)
    key = (physics, likelihood, learn_df, int(warmup), int(total), float(target_accept), method,
           int(max_tree_depth), bool(dense_mass), every)
    sampler = _make_sampler_cached(*key) if _hashable(key) else _make_sampler(*key)

    z0 = _init_points(stacked, sampler, B, chains, p, learn_df, seed, names)
    keys = jax.random.split(jax.random.PRNGKey(seed), B * chains).reshape(B, chains, -1)

    from tqdm.auto import tqdm
    n_ticks = B * total * (chains if method != "vectorized" else 1)
    bar = tqdm(total=n_ticks - n_ticks % every if every > 1 else n_ticks, desc=f"NUTS {B}x{chains} chains",
               unit="it", disable=not progress, leave=False)
    seconds = {}
    try:
        _PROGRESS["bar"] = bar
        t = time.perf_counter()
        if method == "parallel":
            pm = jax.pmap(sampler.run_chain, in_axes=(0, 0, None))
            outs = [pm(jax.tree.map(lambda x: x[b], z0), keys[b], jax.tree.map(lambda x: x[b], stacked))
                    for b in range(B)]
            sites, stats = jax.tree.map(lambda *x: jnp.stack(x), *outs)
            jax.block_until_ready(stats)
            seconds["compile"] = 0.0                       # pmap compiles on the first call: inside "sampling"
            seconds["sampling"] = time.perf_counter() - t
        else:
            sig = repr(jax.tree.map(lambda x: (x.shape, str(x.dtype)), (z0, keys, stacked)))
            compiled = sampler.compiled.get(sig)
            if compiled is None:
                compiled = sampler.run.lower(z0, keys, stacked).compile()
                sampler.compiled[sig] = compiled
            seconds["compile"] = time.perf_counter() - t
            t = time.perf_counter()
            sites, stats = compiled(z0, keys, stacked)
            jax.block_until_ready(stats)
            seconds["sampling"] = time.perf_counter() - t
    finally:
        _PROGRESS["bar"] = None
        bar.close()

    sites = {k: np.asarray(v) for k, v in sites.items()}
    stats = {k: np.asarray(v) for k, v in stats.items()}
    warm_div = stats["diverging"][:, :, :warmup].sum(axis=-1)
    sites = {k: v[:, :, warmup:] for k, v in sites.items()}
    stats = {k: v[:, :, warmup:] for k, v in stats.items()}
    stats["tree_depth"] = np.ceil(np.log2(stats["n_steps"] + 1.0)).astype(np.int64)
    constrained = jax.jit(jax.vmap(lambda s, pr: jax.vmap(jax.vmap(lambda q: _constrain(pr, q, learn_df)))(s)))(
        jax.tree.map(jnp.asarray, sites), stacked)
    return NutsDraws(
        sites=sites, theta=np.asarray(constrained["theta"]), sigma=np.asarray(constrained["sigma"]),
        df=np.asarray(constrained["df"]) if learn_df else None, stats=stats, warmup_divergences=warm_div,
        seconds=seconds,
    )


# --------------------------------------------------------------------------- pointwise quantities


@functools.lru_cache(maxsize=16)
def _pointwise_fns(physics: PhysicsModel, family: str):
    def mu_of(theta, inputs):
        return physics.predict(theta, inputs)

    def loglik(theta, sigma, df, problem):
        mu = jax.vmap(mu_of, in_axes=(0, None))(theta, problem.inputs)
        return _obs_dist(family, mu, sigma[:, None], df[:, None]).log_prob(problem.y[None, :])

    def predictive(key, theta, sigma, df, problem):
        mu = jax.vmap(mu_of, in_axes=(0, None))(theta, problem.inputs)
        return _obs_dist(family, mu, sigma[:, None], df[:, None]).sample(key)

    return jax.jit(loglik), jax.jit(predictive)


def _thin_index(draws: int, keep_total: int, chains: int) -> np.ndarray:
    k = max(1, min(draws, keep_total // max(chains, 1)))
    return np.unique(np.round(np.linspace(0, draws - 1, k)).astype(np.int64))


def _pointwise(physics, family, problem, theta, sigma, df, idx, key, *, chunk: int = 256):
    """Log-likelihood and one posterior-predictive draw per kept draw: (C, K, n) each."""
    C = theta.shape[0]
    th = theta[:, idx].reshape((-1, theta.shape[-1]))
    sg = sigma[:, idx].reshape(-1)
    dfv = (np.broadcast_to(np.asarray(problem.df), sg.shape) if df is None else df[:, idx].reshape(-1))
    ll_fn, pp_fn = _pointwise_fns(physics, family)
    lls, pps = [], []
    keys = jax.random.split(key, max(1, -(-th.shape[0] // chunk)))
    for i, s in enumerate(range(0, th.shape[0], chunk)):
        sl = slice(s, s + chunk)
        args = (jnp.asarray(th[sl]), jnp.asarray(sg[sl]), jnp.asarray(dfv[sl]))
        lls.append(np.asarray(ll_fn(*args, problem)))
        pps.append(np.asarray(pp_fn(keys[i], *args, problem)))
    n = problem.y.shape[-1]
    return np.concatenate(lls).reshape(C, len(idx), n), np.concatenate(pps).reshape(C, len(idx), n)


# --------------------------------------------------------------------------- results


def _az():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz as az
    return az


@dataclasses.dataclass(frozen=True)
class NutsResult:
    """A NUTS run of a physics fit: InferenceData, summary table, cross-check, warnings, timings.

    Attributes:
      idata: ``arviz.InferenceData`` with groups posterior (``theta`` [axis, parameter],
        ``sigma`` [axis], ``df``), sample_stats, log_likelihood and posterior_predictive
        (``b_ref`` [row, axis], thinned to ``pointwise_draws`` / ``predictive_draws``),
        observed_data and constant_data (the LM estimate and covariance).
      summary: pandas DataFrame, one row per (axis, parameter): mean, sd, HDI, MCSE,
        bulk/tail ESS, R-hat, and the LM value/sd with the standardised differences.
      crosscheck: per axis, the NUTS-vs-LM comparison (:func:`crosscheck`).
      verdicts: per axis, one line.
      warnings: problems found, each naming the fix.
      seconds: ``compile``, ``sampling``, ``postprocess``, ``total``.
      settings: the sampler settings and prior description.
    """

    idata: Any
    summary: Any
    crosscheck: dict
    verdicts: dict
    warnings: tuple
    seconds: dict
    settings: dict
    fit: PhysicsFit | None = None
    _loo: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)

    @property
    def axes(self) -> tuple[str, ...]:
        return tuple(str(a) for a in self.idata.posterior.axis.values)

    def loo(self, axis: str | None = None):
        """PSIS-LOO of all sampled axes together, or of one ``axis`` (cached)."""
        if axis not in self._loo:
            self._loo[axis] = loo(self.idata, axis=axis)
        return self._loo[axis]

    def metrics(self) -> dict:
        """The ``"nuts"`` block of metrics.json."""
        out = {"settings": self.settings, "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
               "axes": {}, "warnings": list(self.warnings), "thresholds": {
                   "rhat_max": RHAT_MAX, "ess_min": ESS_MIN, "mean_diff_tol_lm_sd": MEAN_DIFF_TOL,
                   "sd_ratio_range": list(SD_RATIO_RANGE)}}
        elpd_total = 0.0
        for ax in self.axes:
            c = self.crosscheck[ax]
            block = {k: c[k] for k in ("max_rhat", "min_ess_bulk", "min_ess_tail", "divergences",
                                      "max_abs_mean_diff_lm_sd", "max_abs_mean_diff_parameter", "sd_ratio_min",
                                      "sd_ratio_max", "whitened_eigenvalue_range", "max_corr_diff", "ebfmi_min",
                                      "max_tree_depth_fraction", "verdict", "adequate")}
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    lo = self.loo(ax)
                block["elpd_loo"] = float(lo.elpd_loo)
                block["elpd_loo_se"] = float(lo.se)
                block["p_loo"] = float(lo.p_loo)
                block["pareto_k_above_0.7"] = int(np.sum(np.asarray(lo.pareto_k) > 0.7))
                elpd_total += float(lo.elpd_loo)
            except Exception as e:  # pragma: no cover - LOO is a by-product; never fail the job on it
                block["elpd_loo"] = None
                block["elpd_loo_error"] = str(e)
            out["axes"][ax] = block
        out["elpd_loo_total"] = elpd_total
        return out

    def write(self, folder: str | Path, *, figures: bool = True) -> list[Path]:
        return write_nuts_outputs(self, folder, figures=figures)


def _xr():
    import xarray as xr
    return xr


def _build_idata(draws: NutsDraws, problems, axes, names, physics, likelihood, pointwise, predictive,
                 lm_theta, lm_cov, attrs, seed):
    az, xr = _az(), _xr()
    B, C, D, p = draws.theta.shape
    coords = {"chain": np.arange(C), "draw": np.arange(D), "axis": list(axes), "parameter": list(names)}
    post = {
        "theta": (("chain", "draw", "axis", "parameter"), np.moveaxis(draws.theta, 0, 2)),
        "sigma": (("chain", "draw", "axis"), np.moveaxis(draws.sigma, 0, 2)),
    }
    if draws.df is not None:
        post["df"] = (("chain", "draw", "axis"), np.moveaxis(draws.df, 0, 2))
    posterior = xr.Dataset(post, coords={k: coords[k] for k in ("chain", "draw", "axis", "parameter")})
    stats = xr.Dataset({k: (("chain", "draw", "axis"), np.moveaxis(v, 0, 2)) for k, v in draws.stats.items()},
                       coords={k: coords[k] for k in ("chain", "draw", "axis")})
    idx_ll = _thin_index(D, pointwise, C)
    idx_pp = _thin_index(D, predictive, C)
    lls, pps = [], []
    key = jax.random.PRNGKey(seed + 7919)
    for b in range(B):
        ll, _ = _pointwise(physics, likelihood, problems[b], draws.theta[b], draws.sigma[b],
                           None if draws.df is None else draws.df[b], idx_ll, jax.random.fold_in(key, 2 * b))
        _, pp = _pointwise(physics, likelihood, problems[b], draws.theta[b], draws.sigma[b],
                           None if draws.df is None else draws.df[b], idx_pp, jax.random.fold_in(key, 2 * b + 1))
        lls.append(ll)
        pps.append(pp)
    n = problems[0].y.shape[-1]
    rows = np.arange(n)
    loglik = xr.Dataset({"b_ref": (("chain", "draw", "row", "axis"), np.stack(lls, axis=-1))},
                        coords={"chain": coords["chain"], "draw": idx_ll, "row": rows, "axis": coords["axis"]})
    ppc = xr.Dataset({"b_ref": (("chain", "draw", "row", "axis"), np.stack(pps, axis=-1))},
                     coords={"chain": coords["chain"], "draw": idx_pp, "row": rows, "axis": coords["axis"]})
    obs = xr.Dataset({"b_ref": (("row", "axis"), np.stack([np.asarray(pr.y) for pr in problems], axis=-1))},
                     coords={"row": rows, "axis": coords["axis"]})
    const = xr.Dataset({
        "lm_theta": (("axis", "parameter"), np.asarray(lm_theta)),
        "lm_cov": (("axis", "parameter", "parameter_bis"), np.asarray(lm_cov)),
        "b_meas": (("row", "component"), np.asarray(problems[0].inputs.b)),
        "temperature": (("row",), np.asarray(problems[0].inputs.t)),
    }, coords={"axis": coords["axis"], "parameter": coords["parameter"], "parameter_bis": coords["parameter"],
               "row": rows, "component": list(AXES)})
    idata = az.InferenceData(posterior=posterior, sample_stats=stats, log_likelihood=loglik,
                             posterior_predictive=ppc, observed_data=obs, constant_data=const)
    for g in idata.groups():
        idata[g].attrs.update(attrs)
    return idata


def _summary_frame(idata, lm_theta, lm_sd, hdi_prob=0.95):
    import pandas as pd
    az = _az()
    post = idata.posterior
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ess_b, ess_t = az.ess(post, method="bulk"), az.ess(post, method="tail")
        rhat = az.rhat(post)
        mc_m, mc_s = az.mcse(post, method="mean"), az.mcse(post, method="sd")
        hdi = az.hdi(post, hdi_prob=hdi_prob)
    lo_name, hi_name = f"hdi_{(1 - hdi_prob) / 2:.1%}", f"hdi_{1 - (1 - hdi_prob) / 2:.1%}"
    axes = [str(a) for a in post.axis.values]
    names = [str(p) for p in post.parameter.values]
    for ai, ax in enumerate(axes):
        for var in ("theta", "sigma", "df"):
            if var not in post:
                continue
            params = names if var == "theta" else [var]
            for j, name in enumerate(params):
                sel = {"axis": ax} if var != "theta" else {"axis": ax, "parameter": name}
                x = post[var].sel(sel).values
                row = {"axis": ax, "parameter": name, "mean": float(x.mean()), "sd": float(x.std(ddof=1)),
                       lo_name: float(hdi[var].sel(sel).sel(hdi="lower")),
                       hi_name: float(hdi[var].sel(sel).sel(hdi="higher")),
                       "mcse_mean": float(mc_m[var].sel(sel)), "mcse_sd": float(mc_s[var].sel(sel)),
                       "ess_bulk": float(ess_b[var].sel(sel)), "ess_tail": float(ess_t[var].sel(sel)),
                       "r_hat": float(rhat[var].sel(sel))}
                if var == "theta":
                    m, s = float(lm_theta[ai, j]), float(lm_sd[ai, j])
                    row.update(lm_value=m, lm_sd=s, mean_diff_lm_sd=(row["mean"] - m) / s, sd_ratio=row["sd"] / s)
                else:
                    row.update(lm_value=np.nan, lm_sd=np.nan, mean_diff_lm_sd=np.nan, sd_ratio=np.nan)
                rows.append(row)
    return pd.DataFrame(rows)


def crosscheck(idata, *, fit_cov: np.ndarray | None = None, high_corr: Mapping[str, list] | None = None,
               likelihood: str = "gaussian", summary=None) -> tuple[dict, dict, list[str]]:
    """Compare NUTS draws with the LM (Laplace) approximation stored in ``idata.constant_data``.

    Returns ``(per_axis, verdicts, warnings)``. Per axis: standardised mean differences and
    sd ratios per parameter, the largest absolute correlation differences, the eigenvalue
    range of the NUTS covariance in LM-whitened coordinates, sampler diagnostics (max R-hat,
    min bulk/tail ESS, divergences, E-BFMI, tree-depth saturation), a verdict and whether
    the Laplace approximation is adequate. ``fit_cov`` (axis, p, p), the fit's own
    covariance when it is not the white one, adds the sd ratios against it.
    """
    post, const, st = idata.posterior, idata.constant_data, idata.sample_stats
    names = [str(p) for p in post.parameter.values]
    if summary is None:
        summary = _summary_frame(idata, const.lm_theta.values, np.sqrt(np.diagonal(const.lm_cov.values, axis1=1,
                                                                                   axis2=2)))
    out, verdicts, warns = {}, {}, []
    max_depth = int(post.attrs.get("max_tree_depth", 10))
    for ai, ax in enumerate([str(a) for a in post.axis.values]):
        th = post.theta.sel(axis=ax).values                                  # (C, D, p)
        C, D, p = th.shape
        flat = th.reshape(-1, p)
        m_lm = const.lm_theta.sel(axis=ax).values
        cov_lm = const.lm_cov.sel(axis=ax).values
        sd_lm = np.sqrt(np.diag(cov_lm))
        mean, sd = flat.mean(0), flat.std(0, ddof=1)
        d = (mean - m_lm) / sd_lm
        ratio = sd / sd_lm
        corr_n = np.corrcoef(flat, rowvar=False)
        corr_l = cov_lm / np.outer(sd_lm, sd_lm)
        diff = corr_n - corr_l
        iu = np.triu_indices(p, 1)
        order = np.argsort(-np.abs(diff[iu]))[:3]
        top = [{"a": names[iu[0][k]], "b": names[iu[1][k]], "corr_nuts": float(corr_n[iu[0][k], iu[1][k]]),
                "corr_lm": float(corr_l[iu[0][k], iu[1][k]]), "diff": float(diff[iu[0][k], iu[1][k]])} for k in order]
        Lr = _chol_root(cov_lm)
        w = np.linalg.solve(Lr, (flat - m_lm).T).T
        eig = np.linalg.eigvalsh(np.cov(w, rowvar=False)) if p > 1 else np.array([np.var(w, ddof=1)])
        sub = summary[(summary.axis == ax) & (summary.parameter.isin(names))]
        subs = summary[summary.axis == ax]
        rh, eb, et = subs.r_hat.to_numpy(), subs.ess_bulk.to_numpy(), subs.ess_tail.to_numpy()
        div = int(st.diverging.sel(axis=ax).values.sum())
        E = st.energy.sel(axis=ax).values
        ebfmi = np.sum(np.diff(E, axis=1) ** 2, axis=1) / np.maximum(np.sum((E - E.mean(1, keepdims=True)) ** 2,
                                                                            axis=1), 1e-300)
        depth_frac = float(np.mean(st.tree_depth.sel(axis=ax).values >= max_depth))
        c = {
            "parameters": {n: {"mean_diff_lm_sd": float(d[j]), "sd_ratio": float(ratio[j]),
                               "mcse_mean_lm_sd": float(sub.mcse_mean.to_numpy()[j] / sd_lm[j])}
                           for j, n in enumerate(names)},
            "max_abs_mean_diff_lm_sd": float(np.max(np.abs(d))),
            "max_abs_mean_diff_parameter": names[int(np.argmax(np.abs(d)))],
            "sd_ratio_min": float(ratio.min()), "sd_ratio_max": float(ratio.max()),
            "largest_corr_differences": top, "max_corr_diff": float(np.max(np.abs(diff[iu]))) if p > 1 else 0.0,
            "whitened_eigenvalue_range": [float(eig.min()), float(eig.max())],
            "max_rhat": float(np.nanmax(rh)), "min_ess_bulk": float(np.nanmin(eb)),
            "min_ess_tail": float(np.nanmin(et)),
            "divergences": div, "ebfmi_min": float(ebfmi.min()), "max_tree_depth_fraction": depth_frac,
        }
        if fit_cov is not None:
            sd_fit = np.sqrt(np.diag(fit_cov[ai]))
            c["sd_ratio_vs_fit_covariance"] = {n: float(sd[j] / sd_fit[j]) for j, n in enumerate(names)}
        # sampler diagnostics
        hc = [f"{q['a']}-{q['b']}" for q in (high_corr or {}).get(ax, []) if abs(q["corr"]) > 0.999]
        t0_fix = (f" The LM correlations {', '.join(hc)} exceed 0.999: set [physics] t0 = \"mean\" to remove them."
                  if hc else "")
        problems = []
        n_warn = len(warns)
        if C >= 2 and np.nanmax(rh) > RHAT_MAX:
            worst = subs.parameter.to_numpy()[np.nanargmax(rh)]
            problems.append(f"R-hat {np.nanmax(rh):.3f} > {RHAT_MAX}")
            warns.append(f"NUTS axis {ax}: R-hat {np.nanmax(rh):.3f} for {worst} exceeds {RHAT_MAX}: the chains "
                         f"disagree. Raise [nuts] warmup and draws.{t0_fix}")
        if min(np.nanmin(eb), np.nanmin(et)) < ESS_MIN:
            k = "bulk" if np.nanmin(eb) <= np.nanmin(et) else "tail"
            v = min(np.nanmin(eb), np.nanmin(et))
            worst = subs.parameter.to_numpy()[np.nanargmin(eb if k == "bulk" else et)]
            problems.append(f"{k} ESS {v:.0f} < {ESS_MIN}")
            warns.append(f"NUTS axis {ax}: {k} ESS {v:.0f} for {worst} is below {ESS_MIN}: means and intervals are "
                         f"imprecise. Raise [nuts] draws (or chains).{t0_fix}")
        if div:
            problems.append(f"{div} divergences")
            warns.append(f"NUTS axis {ax}: {div} divergent transitions after warm-up: the sampler could not follow "
                         f"the posterior's curvature, so the draws may be biased. Raise [nuts] target_accept (e.g. "
                         f"0.95).{t0_fix}")
        if depth_frac > 0.01:
            fix = t0_fix or " Check the LM fit (whitening uses its covariance)."
            warns.append(f"NUTS axis {ax}: {depth_frac:.0%} of draws hit the maximum tree depth {max_depth}: the "
                         f"posterior is badly scaled for the sampler.{fix}")
        if ebfmi.min() < EBFMI_MIN:
            warns.append(f"NUTS axis {ax}: E-BFMI {ebfmi.min():.2f} < {EBFMI_MIN}: the noise scale or a heavy tail is "
                         f"poorly explored; raise [nuts] warmup or reconsider the observation model.")
        if t0_fix and len(warns) > n_warn + 1:      # say the t0 fix once per axis, on its first warning
            warns[n_warn + 1:] = [w.replace(t0_fix, "") for w in warns[n_warn + 1:]]
        # verdict
        bad = []
        for j in np.argsort(-np.abs(d)):
            if abs(d[j]) > MEAN_DIFF_TOL:
                bad.append(f"{names[j]} mean differs by {d[j]:+.2f} LM sd")
        for j in np.argsort(-np.abs(np.log(ratio))):
            if not SD_RATIO_RANGE[0] <= ratio[j] <= SD_RATIO_RANGE[1]:
                bad.append(f"{names[j]} sd ratio {ratio[j]:.2f} (NUTS {'wider' if ratio[j] > 1 else 'narrower'})")
        what = "NUTS" if likelihood == "gaussian" else f"NUTS ({likelihood} likelihood)"
        within = (f"{what} means within {np.max(np.abs(d)):.3f} LM sd of the LM estimate (tolerance "
                  f"{MEAN_DIFF_TOL}), sd ratios {ratio.min():.3f}-{ratio.max():.3f} (tolerance "
                  f"{SD_RATIO_RANGE[0]}-{SD_RATIO_RANGE[1]})")
        shown = "; ".join(bad[:4] + ([f"{len(bad) - 4} more"] if len(bad) > 4 else []))
        if problems:
            v = (f"Inconclusive: sampler diagnostics failed ({', '.join(problems)}), so the draws cannot judge the "
                 f"Laplace approximation; as sampled, " + (shown if bad else within))
        elif not bad:
            v = f"Laplace approximation adequate: {within}"
        else:
            v = f"Laplace approximation disagrees with {what}: {shown}"
        c["adequate"] = bool(not bad and not problems)
        c["verdict"] = v
        verdicts[ax] = v
        out[ax] = c
    return out, verdicts, warns


def run_nuts(data, fit: PhysicsFit, *, chains: int = 4, warmup: int = 1000, draws: int = 1000,
             target_accept: float = 0.8, chain_method: str = "vectorized", likelihood: str = "gaussian",
             priors: Mapping | NutsPriors | None = None, seed: int = 0, axes: Sequence[str] = AXES,
             progress: bool = False, pointwise_draws: int = 1000, predictive_draws: int = 200,
             parametrisation: str = "whitened", dense_mass: bool = False, max_tree_depth: int = 10) -> NutsResult:
    r"""Sample the physics posterior of ``fit`` with NUTS and cross-check it against the LM fit.

    Args:
      data: the :class:`~bayesmag.CalibrationData` ``fit`` was fitted on (with a reference).
      fit: a converged :class:`~bayesmag.PhysicsFit`; its model (extra terms included) is
        the likelihood's mean function, its estimate and covariance centre the priors and
        whiten the sampler.
      chains, warmup, draws, target_accept, chain_method, seed: NUTS settings (``[nuts]``).
      likelihood: ``"gaussian"``, ``"laplace"`` or ``"student_t"`` observation model.
      priors: ``[nuts] priors`` table (:func:`parse_priors`) or a :class:`NutsPriors`.
      axes: the output axes to sample (each independently).
      progress: show a progress bar.
      pointwise_draws, predictive_draws: draws kept (evenly thinned, all chains together) in
        the log_likelihood and posterior_predictive groups; they are (draws x rows x axes)
        arrays, so keeping all 4000 draws of 3000 rows would take ~300 MB.
      parametrisation: ``"whitened"`` (default, module docstring) or ``"scaled"``.
      dense_mass: adapt a dense mass matrix (useful with ``"scaled"``).
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
    axes = tuple(axes)
    for ax in axes:
        if ax not in AXES:
            raise ValueError(f"run_nuts: axis {ax!r} is not one of {list(AXES)}.")
    if pointwise_draws < 1 or predictive_draws < 1:
        raise ValueError("run_nuts: pointwise_draws and predictive_draws must be >= 1.")
    pri = priors if isinstance(priors, NutsPriors) else parse_priors(priors, fit.param_names, likelihood=likelihood)
    learn_df = likelihood == "student_t" and pri.df is None
    problems = [build_problem(data, fit, ax, likelihood=likelihood, priors=pri, parametrisation=parametrisation)
                for ax in axes]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", NutsWarning)
        dr = sample_nuts(problems, fit.model, likelihood=likelihood, learn_df=learn_df, chains=chains, warmup=warmup,
                         draws=draws, target_accept=target_accept, chain_method=chain_method, seed=seed,
                         progress=progress, max_tree_depth=max_tree_depth, dense_mass=dense_mass, names=axes)
    setting_warnings = [str(w.message) for w in caught if issubclass(w.category, NutsWarning)]
    for w in caught:                                   # re-issue everything, now that it is recorded
        warnings.warn(w.message, w.category, stacklevel=2)
    t_post = time.perf_counter()
    a_idx = [AXES.index(a) for a in axes]
    lm_cov = np.stack([np.asarray(pr.root) @ np.asarray(pr.root).T if parametrisation == "whitened"
                       else _white_cov(data, fit, a) for pr, a in zip(problems, a_idx)])
    lm_theta = np.asarray(fit.theta)[a_idx]
    settings = {"chains": chains, "warmup": warmup, "draws": draws, "target_accept": target_accept,
                "chain_method": chain_method, "likelihood": likelihood, "seed": seed, "axes": list(axes),
                "parametrisation": parametrisation, "dense_mass": bool(dense_mass), "max_tree_depth": max_tree_depth,
                "pointwise_draws": pointwise_draws, "predictive_draws": predictive_draws,
                "priors": pri.describe(), "n_rows": data.n, "model": fit.model.describe()}
    attrs = {"created_by": "bayesmag.run_nuts", "likelihood": likelihood, "parametrisation": parametrisation,
             "max_tree_depth": max_tree_depth, "priors": json.dumps(pri.describe()),
             "settings": json.dumps({k: v for k, v in settings.items() if k not in ("priors", "model")})}
    idata = _build_idata(dr, problems, axes, fit.param_names, fit.model, likelihood, pointwise_draws,
                         predictive_draws, lm_theta, lm_cov, attrs, seed)
    summary = _summary_frame(idata, lm_theta, np.sqrt(np.diagonal(lm_cov, axis1=1, axis2=2)))
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


# --------------------------------------------------------------------------- model comparison


def loo(result, *, axis: str | None = None, pointwise: bool = True):
    """PSIS-LOO (Vehtari et al. 2017) of a :class:`NutsResult` or its InferenceData via ArviZ.

    ``axis`` restricts it to one output axis; by default all sampled axes' rows count as
    observations. The relative efficiency is computed from the posterior draws that the
    (thinned) log-likelihood was evaluated at.

    Returns:
      ``arviz.ELPDData`` (elpd_loo, se, p_loo, pareto_k, ...).
    """
    az = _az()
    idata = result.idata if isinstance(result, NutsResult) else result
    ll = idata.log_likelihood
    post = idata.posterior
    if axis is not None:
        if axis not in [str(a) for a in ll.axis.values]:
            raise ValueError(f"loo: axis {axis!r} was not sampled; sampled axes: {[str(a) for a in ll.axis.values]}.")
        ll, post = ll.sel(axis=[axis]), post.sel(axis=[axis])
    kept = post.sel(draw=ll.draw.values)
    n_samples = ll.sizes["chain"] * ll.sizes["draw"]
    if ll.sizes["chain"] > 1:
        ess = az.ess(kept, method="mean")
        reff = float(np.hstack([ess[v].values.ravel() for v in ess.data_vars]).mean() / n_samples)
    else:
        reff = 1.0
    sub = az.InferenceData(posterior=kept, log_likelihood=ll)
    return az.loo(sub, pointwise=pointwise, reff=reff)


def compare_models(models: Mapping[str, Any], *, axis: str | None = None, method: str = "stacking"):
    """Compare physics models fitted to the same rows by PSIS-LOO ELPD (``arviz.compare``).

    Args:
      models: ``{name: NutsResult or InferenceData}``, at least two, with identical observed data.
      axis: compare on one output axis only (default: all sampled axes together).
    Returns:
      the ``arviz.compare`` DataFrame (rank, elpd_loo, p_loo, elpd_diff, weight, se, dse, ...).
    Raises:
      ValueError: fewer than two models, or models observed on different data.
    """
    az = _az()
    if len(models) < 2:
        raise ValueError(f"compare_models needs at least two models; got {list(models)}.")
    ref_name, ref = None, None
    for name, m in models.items():
        idata = m.idata if isinstance(m, NutsResult) else m
        obs = idata.observed_data.b_ref
        if axis is not None:
            obs = obs.sel(axis=axis)
        if ref is None:
            ref_name, ref = name, obs
        elif obs.shape != ref.shape or not np.array_equal(obs.values, ref.values):
            raise ValueError(f"compare_models: {name!r} and {ref_name!r} were fitted to different data "
                             f"(observed shapes {obs.shape} vs {ref.shape}); LOO/ELPD compares models on the "
                             f"same rows.")
    elpds = {name: loo(m, axis=axis) for name, m in models.items()}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)       # arviz internals vs pandas 3 deprecations
        warnings.simplefilter("ignore", DeprecationWarning)
        return az.compare(elpds, method=method)


# --------------------------------------------------------------------------- outputs


def _write_netcdf(idata, path: Path) -> None:
    """All groups to one netCDF-4 file; pointwise groups in float32 (halves the largest arrays)."""
    path = Path(path)
    if path.exists():
        path.unlink()
    mode = "w"
    for g in idata.groups():
        ds = idata[g]
        enc = {}
        for v in ds.data_vars:
            e = {"zlib": True, "complevel": 1, "shuffle": True}
            if g in ("log_likelihood", "posterior_predictive") and ds[v].dtype == np.float64:
                e["dtype"] = "float32"
            enc[v] = e
        ds.to_netcdf(path, mode=mode, group=g, engine="h5netcdf", encoding=enc)
        mode = "a"


def _fmt(v) -> str:
    if isinstance(v, str):
        return v
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return ""
    if isinstance(v, (int, np.integer)):
        return str(v)
    a = abs(v)
    return f"{v:.4g}" if a == 0 or 1e-3 <= a < 1e5 else f"{v:.4e}"


def _markdown(res: NutsResult) -> str:
    df = res.summary
    cols = list(df.columns)
    lines = ["# NUTS cross-check of the physics posterior", ""]
    s = res.settings
    lines.append(f"{s['chains']} chains x {s['draws']} draws (warm-up {s['warmup']}, target_accept "
                 f"{s['target_accept']}, {s['chain_method']}, {s['parametrisation']} parametrisation), "
                 f"{s['likelihood']} likelihood, {s['n_rows']} rows; "
                 f"{res.seconds.get('total', float('nan')):.1f} s in total "
                 f"({res.seconds.get('sampling', float('nan')):.1f} s sampling, "
                 f"{res.seconds.get('compile', float('nan')):.1f} s compiling).")
    lines += ["", "## Verdicts", ""]
    for ax, v in res.verdicts.items():
        lines.append(f"- **{ax}**: {v}")
    if res.warnings:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in res.warnings]
    lines += ["", "## Largest correlation differences (NUTS - LM)", ""]
    for ax in res.axes:
        top = res.crosscheck[ax]["largest_corr_differences"]
        ev = res.crosscheck[ax]["whitened_eigenvalue_range"]
        items = ", ".join(f"{t['a']}-{t['b']} {t['corr_nuts']:.6f} vs {t['corr_lm']:.6f}" for t in top)
        lines.append(f"- **{ax}**: {items}; whitened covariance eigenvalues {ev[0]:.3f}-{ev[1]:.3f} (1 = LM exact)")
    lines += ["", "## Summary", "", "mean_diff_lm_sd = (mean_NUTS - theta_LM) / sd_LM; sd_ratio = sd_NUTS / sd_LM.",
              "", "| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for _, r in df.iterrows():
        cells = []
        for c in cols:
            v = r[c]
            if c == "r_hat" and isinstance(v, float) and np.isfinite(v):
                cells.append(f"{v:.4f}")
            elif c.startswith("ess_") and isinstance(v, float) and np.isfinite(v):
                cells.append(f"{v:.0f}")
            else:
                cells.append(_fmt(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_nuts_outputs(res: NutsResult, folder: str | Path, *, figures: bool = True) -> list[Path]:
    """Write ``nuts.nc``, ``nuts_summary.csv``, ``nuts_summary.md`` (and figures) into ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = [folder / "nuts.nc", folder / "nuts_summary.csv", folder / "nuts_summary.md"]
    _write_netcdf(res.idata, out[0])
    res.summary.to_csv(out[1], index=False, float_format="%.10g")
    out[2].write_text(_markdown(res))
    if figures:
        from . import nuts_plots
        out += nuts_plots.nuts_figures(folder, res)
    return out


def run_nuts_stage(cfg, result: dict, train, timings: dict, *, progress: bool = False) -> NutsResult:
    """The job's NUTS stage (``[nuts] enabled = true``): sample, add ``metrics["nuts"]``, register the writer."""
    n = cfg.nuts
    fit = result["fit"]
    t = time.perf_counter()
    priors = parse_priors(n.priors, fit.param_names, likelihood=n.likelihood)
    try:       # impossible settings are config errors; too-small ones become warnings in run_nuts
        check_settings(chains=n.chains, warmup=n.warmup, draws=n.draws, target_accept=n.target_accept,
                       chain_method=n.chain_method)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    res = run_nuts(train, fit, chains=n.chains, warmup=n.warmup, draws=n.draws, target_accept=n.target_accept,
                   chain_method=n.chain_method, likelihood=n.likelihood, priors=priors, seed=n.seed,
                   progress=progress)
    timings["nuts"] = time.perf_counter() - t
    result["nuts"] = res
    result["metrics"]["nuts"] = res.metrics()
    if res.warnings:
        result["metrics"].setdefault("warnings", []).extend(res.warnings)
    figures = cfg.output.figures
    result.setdefault("writers", []).append(lambda staging: write_nuts_outputs(res, staging, figures=figures))
    return res
