"""ArviZ InferenceData of a NUTS run: pointwise log-likelihood, posterior predictive, summary table."""

from __future__ import annotations

import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from bayesmag._src.core.physics import AXES, PhysicsModel
from bayesmag._src.pipeline.nuts.model import mean_of, obs_dist
from bayesmag._src.pipeline.nuts.sampler import NutsDraws

__all__ = ["build_idata", "summary_frame", "JOINT_STATS", "arviz"]


def arviz():
    """``import arviz`` without its refactor announcement (a FutureWarning)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz as az
    return az


@functools.lru_cache(maxsize=16)
def _pointwise_fns(physics: PhysicsModel, family: str):
    def loglik(theta, sigma, shape, problem):
        mu = jax.vmap(lambda th: mean_of(physics, th, problem))(theta)
        sh = {k: v[:, None] for k, v in shape.items()}
        return obs_dist(family, mu, sigma[:, None], sh).log_prob(problem.y[None, :])

    def predictive(key, theta, sigma, shape, problem):
        mu = jax.vmap(lambda th: mean_of(physics, th, problem))(theta)
        sh = {k: v[:, None] for k, v in shape.items()}
        return obs_dist(family, mu, sigma[:, None], sh).sample(key)

    return jax.jit(loglik), jax.jit(predictive)


def _thin_index(draws: int, keep_total: int, chains: int) -> np.ndarray:
    k = max(1, min(draws, keep_total // max(chains, 1)))
    return np.unique(np.round(np.linspace(0, draws - 1, k)).astype(np.int64))


def _pointwise(physics, family, problem, theta, sigma, learned, idx, key, *, chunk: int = 256):
    """Log-likelihood and one posterior-predictive draw per kept draw: (C, K, n) each.

    ``learned``: ``{field: (C, D)}`` draws of the learned shape fields; the others are the problem's.
    """
    C = theta.shape[0]
    th = theta[:, idx].reshape((-1, theta.shape[-1]))
    sg = sigma[:, idx].reshape(-1)
    shape = {f: (learned[f][:, idx].reshape(-1) if f in learned else np.broadcast_to(np.asarray(v), sg.shape))
             for f, v in problem.shape.items()}
    ll_fn, pp_fn = _pointwise_fns(physics, family)
    lls, pps = [], []
    keys = jax.random.split(key, max(1, -(-th.shape[0] // chunk)))
    for i, s in enumerate(range(0, th.shape[0], chunk)):
        sl = slice(s, s + chunk)
        args = (jnp.asarray(th[sl]), jnp.asarray(sg[sl]), {f: jnp.asarray(v[sl]) for f, v in shape.items()})
        lls.append(np.asarray(ll_fn(*args, problem)))
        pps.append(np.asarray(pp_fn(keys[i], *args, problem)))
    n = problem.y.shape[-1]
    return np.concatenate(lls).reshape(C, len(idx), n), np.concatenate(pps).reshape(C, len(idx), n)



def _xr():
    import xarray as xr
    return xr



#: ``sample_stats`` of the joint sampler over the axes (ArviZ's layout, dims chain x draw):
#: how each per-axis statistic combines. The axes are independent posteriors sampled by
#: independent NUTS kernels; their product is one Markov chain on the joint space whose
#: Hamiltonian is the sum of the axes' (so ``energy`` and ``lp`` add). The per-axis values
#: are kept as ``<name>_axis`` (chain x draw x axis).
JOINT_STATS = {"energy": "sum", "lp": "sum", "diverging": "any", "n_steps": "sum", "tree_depth": "max",
               "acceptance_rate": "min", "step_size": "min"}


def build_idata(draws: NutsDraws, problems, axes, names, physics, likelihood, pointwise, predictive,
                lm_theta, lm_cov, attrs, seed):
    """ArviZ InferenceData of a run (see :class:`~bayesmag._src.pipeline.nuts.result.NutsResult`).

    ``log_likelihood`` and ``posterior_predictive`` hold the same thinned draws
    (``max(pointwise, predictive)`` of them, all chains together), so ``az.loo_pit`` /
    ``az.plot_loo_pit`` pair them; ``sample_stats`` has ArviZ's (chain, draw) layout
    (:data:`JOINT_STATS`) so ``az.bfmi`` and ``az.plot_energy`` work on it.
    """
    az, xr = arviz(), _xr()
    B, C, D, p = draws.theta.shape
    coords = {"chain": np.arange(C), "draw": np.arange(D), "axis": list(axes), "parameter": list(names)}
    post = {
        "theta": (("chain", "draw", "axis", "parameter"), np.moveaxis(draws.theta, 0, 2)),
        "sigma": (("chain", "draw", "axis"), np.moveaxis(draws.sigma, 0, 2)),
    }
    for f, v in draws.shape.items():
        post[f] = (("chain", "draw", "axis"), np.moveaxis(v, 0, 2))
    posterior = xr.Dataset(post, coords={k: coords[k] for k in ("chain", "draw", "axis", "parameter")})
    reduce = {"sum": np.sum, "any": np.any, "max": np.max, "min": np.min}
    stat_vars = {}
    for k, v in draws.stats.items():
        per_axis = np.moveaxis(v, 0, 2)                                   # (C, D, axis)
        stat_vars[k + "_axis"] = (("chain", "draw", "axis"), per_axis)
        if k in JOINT_STATS:
            stat_vars[k] = (("chain", "draw"), reduce[JOINT_STATS[k]](per_axis, axis=-1))
    stats = xr.Dataset(stat_vars, coords={k: coords[k] for k in ("chain", "draw", "axis")})
    idx = _thin_index(D, max(pointwise, predictive), C)
    lls, pps = [], []
    key = jax.random.PRNGKey(seed + 7919)
    for b in range(B):
        learned = {f: v[b] for f, v in draws.shape.items()}
        ll, pp = _pointwise(physics, likelihood, problems[b], draws.theta[b], draws.sigma[b], learned, idx,
                            jax.random.fold_in(key, 2 * b + 1))
        lls.append(ll)
        pps.append(pp)
    n = problems[0].y.shape[-1]
    rows = np.arange(n)
    loglik = xr.Dataset({"b_ref": (("chain", "draw", "row", "axis"), np.stack(lls, axis=-1))},
                        coords={"chain": coords["chain"], "draw": idx, "row": rows, "axis": coords["axis"]})
    ppc = xr.Dataset({"b_ref": (("chain", "draw", "row", "axis"), np.stack(pps, axis=-1))},
                     coords={"chain": coords["chain"], "draw": idx, "row": rows, "axis": coords["axis"]})
    obs = xr.Dataset({"b_ref": (("row", "axis"), np.stack([np.asarray(pr.y) for pr in problems], axis=-1))},
                     coords={"row": rows, "axis": coords["axis"]})
    const = xr.Dataset({
        "lm_theta": (("axis", "parameter"), np.asarray(lm_theta)),
        "lm_cov": (("axis", "parameter", "parameter_bis"), np.asarray(lm_cov)),
        "b_meas": (("row", "component"), np.asarray(problems[0].inputs.b)[np.asarray(problems[0].rows)]),
        "temperature": (("row",), np.asarray(problems[0].inputs.t)[np.asarray(problems[0].rows)]),
    }, coords={"axis": coords["axis"], "parameter": coords["parameter"], "parameter_bis": coords["parameter"],
               "row": rows, "component": list(AXES)})
    idata = az.InferenceData(posterior=posterior, sample_stats=stats, log_likelihood=loglik,
                             posterior_predictive=ppc, observed_data=obs, constant_data=const)
    for g in idata.groups():
        idata[g].attrs.update(attrs)
    return idata



def summary_frame(idata, lm_theta, lm_sd, hdi_prob=0.95):
    import pandas as pd
    az = arviz()
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
        for var in ["theta", "sigma"] + [v for v in post.data_vars if v not in ("theta", "sigma")]:
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

