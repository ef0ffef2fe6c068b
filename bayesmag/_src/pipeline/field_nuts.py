"""NUTS cross-check of a field fit's Laplace posterior (NumPyro), same likelihood and priors.

Likelihood: the fit's normalised residuals ~ N(0, s^2 c) (s^2 and the AR(1) factor c held at the fit's
values), priors the fit's Gaussian priors. Compares posterior means and sds parameter by parameter and on
the 18 gauge-free invariants, with the same thresholds as the vector cross-check
(:mod:`bayesmag._src.pipeline.nuts.constants`): R-hat, ESS, |mean shift| / Laplace sd, sd ratio.

The job runs it when a field config has ``[nuts] enabled = true`` and writes ``nuts_summary.csv``,
``nuts_summary.md`` and ``nuts.nc`` (:func:`write_field_nuts_outputs`).
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bayesmag._src.core.field import INVARIANT_NAMES, FieldFit, invariants
from bayesmag._src.pipeline.nuts.constants import ESS_MIN, MEAN_DIFF_TOL, RHAT_MAX, SD_RATIO_RANGE

__all__ = ["field_nuts", "write_field_nuts_outputs", "SUMMARY_COLUMNS"]

SUMMARY_COLUMNS = ("name", "kind", "laplace_mean", "laplace_sd", "nuts_mean", "nuts_sd", "mean_diff_laplace_sd",
                   "sd_ratio", "r_hat", "ess_bulk")


def _verdict(rows, problems) -> tuple[str, bool]:
    bad = []
    for r in sorted(rows, key=lambda r: -abs(r["mean_diff_laplace_sd"])):
        if abs(r["mean_diff_laplace_sd"]) > MEAN_DIFF_TOL:
            bad.append(f"{r['name']} mean differs by {r['mean_diff_laplace_sd']:+.2f} Laplace sd")
    for r in sorted(rows, key=lambda r: -abs(np.log(r["sd_ratio"]))):
        if not SD_RATIO_RANGE[0] <= r["sd_ratio"] <= SD_RATIO_RANGE[1]:
            bad.append(f"{r['name']} sd ratio NUTS/Laplace {r['sd_ratio']:.2f} "
                       f"(NUTS {'wider' if r['sd_ratio'] > 1 else 'narrower'})")
    d = np.array([abs(r["mean_diff_laplace_sd"]) for r in rows])
    q = np.array([r["sd_ratio"] for r in rows])
    within = (f"NUTS means within {d.max():.3f} Laplace sd (tolerance {MEAN_DIFF_TOL}), sd ratios "
              f"{q.min():.3f}-{q.max():.3f} (tolerance {SD_RATIO_RANGE[0]}-{SD_RATIO_RANGE[1]})")
    shown = "; ".join(bad[:4] + ([f"{len(bad) - 4} more"] if len(bad) > 4 else []))
    if problems:
        return (f"Inconclusive: sampler diagnostics failed ({', '.join(problems)}); as sampled, "
                + (shown if bad else within)), False
    if not bad:
        return f"Laplace approximation adequate: {within}", True
    return f"Laplace approximation disagrees with NUTS: {shown}", False


def field_nuts(fit: FieldFit, u, t, target, *, chains: int = 2, warmup: int = 300, draws: int = 300,
               seed: int = 0, target_accept: float = 0.8, chain_method: str = "vectorized") -> dict:
    """Run NUTS on the field posterior; returns summary numbers, per-quantity rows, a verdict and the draws.

    Returned keys: ``chains, draws, warmup, max_rhat, min_ess, divergences, max_mean_shift_sd, sd_ratio_min,
    sd_ratio_max`` (over the parameters), ``params`` (per parameter), ``rows`` (parameters and identified
    invariants, :data:`SUMMARY_COLUMNS`), ``verdict``, ``adequate``, ``warnings`` and ``samples``
    ((chains, draws, p) parameter draws, not JSON).
    """
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
        r = model.residual(th, u, t, y, fit.kappa2)      # the fit's own weight (kappa: reference noise)
        return 0.5 * jnp.sum(r * r) / sig2 + 0.5 * jnp.sum(((th - mu) / sd) ** 2)

    kernel = NUTS(potential_fn=potential, dense_mass=True, target_accept_prob=target_accept)
    mc = MCMC(kernel, num_warmup=warmup, num_samples=draws, num_chains=chains, chain_method=chain_method,
              progress_bar=False)
    init = jnp.zeros((chains, model.n_params)) + 0.1 * jax.random.normal(jax.random.PRNGKey(seed + 1),
                                                                          (chains, model.n_params))
    mc.run(jax.random.PRNGKey(seed), init_params=init[0] if chains == 1 else init,   # one chain: (p,)
           extra_fields=("diverging",))
    z = np.asarray(mc.get_samples(group_by_chain=True))              # (chains, draws, p)
    div = int(np.sum(np.asarray(mc.get_extra_fields()["diverging"])))
    th = np.asarray(centre) + np.asarray(scale) * z

    def diag(x):
        rh = np.asarray(split_gelman_rubin(x)) if chains > 1 else np.full(x.shape[-1], np.nan)
        return rh, np.asarray(effective_sample_size(x))

    rhat, ess = diag(th)
    flat = th.reshape(-1, th.shape[-1])
    m, s = flat.mean(0), flat.std(0)
    rows = [{"name": n, "kind": "parameter", "laplace_mean": float(a), "laplace_sd": float(b), "nuts_mean": float(c),
             "nuts_sd": float(d), "mean_diff_laplace_sd": float((c - a) / b), "sd_ratio": float(d / b),
             "r_hat": float(r), "ess_bulk": float(e)}
            for n, a, b, c, d, r, e in zip(fit.param_names, fit.theta, fit.std, m, s, rhat, ess)]
    inv = fit.invariants()                  # the gauge-free quantities the report states, identified ones only
    g = jax.jit(jax.vmap(lambda v: invariants(*model.unpack(v)[:4])))
    ith = np.asarray(g(jnp.asarray(flat))).reshape(th.shape[0], th.shape[1], -1)
    irh, iess = diag(ith)
    iflat = ith.reshape(-1, ith.shape[-1])
    for k, name in enumerate(INVARIANT_NAMES):
        if not inv["identified"][k]:
            continue
        a, b, c, d = inv["value"][k], inv["sd"][k], iflat[:, k].mean(), iflat[:, k].std()
        rows.append({"name": name, "kind": "invariant", "laplace_mean": float(a), "laplace_sd": float(b),
                     "nuts_mean": float(c), "nuts_sd": float(d), "mean_diff_laplace_sd": float((c - a) / b),
                     "sd_ratio": float(d / b), "r_hat": float(irh[k]), "ess_bulk": float(iess[k])})
    warns, problems = [], []
    max_rhat = float(np.nanmax([r["r_hat"] for r in rows])) if chains > 1 else float("nan")
    min_ess = float(min(r["ess_bulk"] for r in rows))
    if chains > 1 and max_rhat > RHAT_MAX:
        problems.append(f"max R-hat {max_rhat:.3f} > {RHAT_MAX}")
        warns.append(f"field NUTS: max R-hat {max_rhat:.3f} > {RHAT_MAX}: the chains disagree; raise nuts.warmup "
                     "and nuts.draws.")
    if min_ess < ESS_MIN:
        problems.append(f"min ESS {min_ess:.0f} < {ESS_MIN}")
        warns.append(f"field NUTS: min ESS {min_ess:.0f} < {ESS_MIN}: too few effective draws to judge the Laplace "
                     "posterior; raise nuts.draws (or nuts.chains).")
    if div:
        problems.append(f"{div} divergences")
        warns.append(f"field NUTS: {div} divergent transitions; raise nuts.target_accept (e.g. 0.95).")
    verdict, adequate = _verdict(rows, problems)
    if not adequate and not problems:
        warns.append(f"field NUTS: {verdict}")
    shift = np.abs(fit.theta - m) / s
    ratio = fit.std / s
    return {"chains": chains, "draws": draws, "warmup": warmup, "seed": seed, "target_accept": target_accept,
            "max_rhat": max_rhat, "min_ess": min_ess, "divergences": div,
            "max_mean_shift_sd": float(shift.max()), "sd_ratio_min": float(ratio.min()),
            "sd_ratio_max": float(ratio.max()), "n_rows": int(u.shape[0]),
            "params": {n: {"laplace_mean": float(a), "nuts_mean": float(b), "laplace_sd": float(c), "nuts_sd": float(d)}
                       for n, a, b, c, d in zip(fit.param_names, fit.theta, m, fit.std, s)},
            "rows": rows, "verdict": verdict, "adequate": adequate, "warnings": warns, "samples": th}


def write_field_nuts_outputs(res: dict, folder: str | Path, param_names) -> list[Path]:
    """``nuts_summary.csv`` (:data:`SUMMARY_COLUMNS`), ``nuts_summary.md`` and ``nuts.nc`` (the parameter draws)."""
    import csv
    import warnings

    folder = Path(folder)
    out = [folder / "nuts_summary.csv", folder / "nuts_summary.md", folder / "nuts.nc"]
    with open(out[0], "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(SUMMARY_COLUMNS)
        for r in res["rows"]:
            w.writerow([r[c] if isinstance(r[c], str) else f"{r[c]:.10g}" for c in SUMMARY_COLUMNS])
    L = ["# NUTS cross-check of the field posterior", "",
         f"{res['chains']} chains x {res['draws']} draws (warm-up {res['warmup']}, target_accept "
         f"{res['target_accept']}), same likelihood and priors as the Laplace posterior, {res['n_rows']} training rows; "
         f"max R-hat {res['max_rhat']:.4f}, min bulk ESS {res['min_ess']:.0f}, {res['divergences']} divergences.", "",
         f"**Verdict**: {res['verdict']}", ""]
    if res["warnings"]:
        L += ["## Warnings", ""] + [f"- {w}" for w in res["warnings"]] + [""]
    L += ["## Summary", "", "mean_diff_laplace_sd = (mean_NUTS - Laplace mean) / Laplace sd; sd_ratio = sd_NUTS / "
          "Laplace sd. Parameters are in the gauge frame; invariants are the identified gauge-free quantities.", "",
          "| " + " | ".join(SUMMARY_COLUMNS) + " |", "|" + "|".join("---" for _ in SUMMARY_COLUMNS) + "|"]
    for r in res["rows"]:
        L.append("| " + " | ".join(r[c] if isinstance(r[c], str) else f"{r[c]:.5g}" for c in SUMMARY_COLUMNS) + " |")
    out[1].write_text("\n".join(L) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz as az
        idata = az.from_dict(posterior={"theta": res["samples"]}, coords={"parameter": list(param_names)},
                             dims={"theta": ["parameter"]})
    idata.posterior.to_netcdf(out[2], group="posterior", engine="h5netcdf")
    return out
