"""NUTS cross-check of a field fit's Laplace posterior (NumPyro), same likelihood and priors.

Likelihood: the fit's normalised residuals ~ N(0, s^2 c) (s^2 and the AR(1) factor c held at the fit's
values), priors the fit's Gaussian priors. Compares posterior means and sds parameter by parameter.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from bayesmag._src.core.field import FieldFit

__all__ = ["field_nuts"]


def field_nuts(fit: FieldFit, u, t, target, *, chains: int = 2, warmup: int = 300, draws: int = 300,
               seed: int = 0) -> dict:
    """Run NUTS on the field posterior; returns summary numbers and the per-parameter comparison."""
    from numpyro.diagnostics import effective_sample_size, split_gelman_rubin
    from numpyro.infer import MCMC, NUTS

    model = fit.model
    u, t, y = (jnp.asarray(a, jnp.float64) for a in (u, t, target))
    sig2 = fit.s2 * fit.inflation
    mu, sd = jnp.asarray(fit.prior_mean), jnp.asarray(fit.prior_sd)
    scale = jnp.asarray(np.sqrt(np.diag(fit.cov)))
    centre = jnp.asarray(fit.theta)

    def potential(z):                       # z: standardised around the Laplace mode
        th = centre + scale * z
        r = model.residual(th, u, t, y)
        return 0.5 * jnp.sum(r * r) / sig2 + 0.5 * jnp.sum(((th - mu) / sd) ** 2)

    kernel = NUTS(potential_fn=potential, dense_mass=True)
    mc = MCMC(kernel, num_warmup=warmup, num_samples=draws, num_chains=chains, chain_method="vectorized",
              progress_bar=False)
    init = jnp.zeros((chains, model.n_params)) + 0.1 * jax.random.normal(jax.random.PRNGKey(seed + 1),
                                                                          (chains, model.n_params))
    mc.run(jax.random.PRNGKey(seed), init_params=init)
    z = np.asarray(mc.get_samples(group_by_chain=True))              # (chains, draws, p)
    th = np.asarray(centre) + np.asarray(scale) * z
    flat = th.reshape(-1, th.shape[-1])
    m, s = flat.mean(0), flat.std(0)
    rhat = np.asarray(split_gelman_rubin(th)) if chains > 1 else np.full(th.shape[-1], np.nan)
    ess = np.asarray(effective_sample_size(th))
    shift = np.abs(fit.theta - m) / s
    ratio = fit.std / s
    return {"chains": chains, "draws": draws, "max_rhat": float(np.nanmax(rhat)), "min_ess": float(ess.min()),
            "max_mean_shift_sd": float(shift.max()), "sd_ratio_min": float(ratio.min()),
            "sd_ratio_max": float(ratio.max()),
            "params": {n: {"laplace_mean": float(a), "nuts_mean": float(b), "laplace_sd": float(c), "nuts_sd": float(d)}
                       for n, a, b, c, d in zip(fit.param_names, fit.theta, m, fit.std, s)}}
