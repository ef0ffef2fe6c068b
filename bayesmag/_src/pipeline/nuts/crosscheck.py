"""Cross-check of the NUTS draws against the Levenberg-Marquardt (Laplace) approximation."""

from __future__ import annotations

from typing import Mapping

import numpy as np

from bayesmag._src.pipeline.nuts.constants import EBFMI_MIN, ESS_MIN, MEAN_DIFF_TOL, RHAT_MAX, SD_RATIO_RANGE
from bayesmag._src.pipeline.nuts.idata import summary_frame
from bayesmag._src.pipeline.nuts.model import chol_root

__all__ = ["crosscheck"]


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
        summary = summary_frame(idata, const.lm_theta.values, np.sqrt(np.diagonal(const.lm_cov.values, axis1=1,
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
        Lr = chol_root(cov_lm)
        w = np.linalg.solve(Lr, (flat - m_lm).T).T
        eig = np.linalg.eigvalsh(np.cov(w, rowvar=False)) if p > 1 else np.array([np.var(w, ddof=1)])
        sub = summary[(summary.axis == ax) & (summary.parameter.isin(names))]
        subs = summary[summary.axis == ax]
        rh, eb, et = subs.r_hat.to_numpy(), subs.ess_bulk.to_numpy(), subs.ess_tail.to_numpy()
        div = int(st.diverging_axis.sel(axis=ax).values.sum())
        E = st.energy_axis.sel(axis=ax).values
        ebfmi = np.sum(np.diff(E, axis=1) ** 2, axis=1) / np.maximum(np.sum((E - E.mean(1, keepdims=True)) ** 2,
                                                                            axis=1), 1e-300)
        depth_frac = float(np.mean(st.tree_depth_axis.sel(axis=ax).values >= max_depth))
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
                         f"disagree. Raise warmup and draws.{t0_fix}")
        if min(np.nanmin(eb), np.nanmin(et)) < ESS_MIN:
            k = "bulk" if np.nanmin(eb) <= np.nanmin(et) else "tail"
            v = min(np.nanmin(eb), np.nanmin(et))
            worst = subs.parameter.to_numpy()[np.nanargmin(eb if k == "bulk" else et)]
            problems.append(f"{k} ESS {v:.0f} < {ESS_MIN}")
            warns.append(f"NUTS axis {ax}: {k} ESS {v:.0f} for {worst} is below {ESS_MIN}: means and intervals are "
                         f"imprecise. Raise draws (or chains).{t0_fix}")
        if div:
            problems.append(f"{div} divergences")
            warns.append(f"NUTS axis {ax}: {div} divergent transitions after warm-up: the sampler could not follow "
                         f"the posterior's curvature, so the draws may be biased. Raise target_accept (e.g. "
                         f"0.95).{t0_fix}")
        if depth_frac > 0.01:
            fix = t0_fix or " Check the LM fit (whitening uses its covariance)."
            warns.append(f"NUTS axis {ax}: {depth_frac:.0%} of draws hit the maximum tree depth {max_depth}: the "
                         f"posterior is badly scaled for the sampler.{fix}")
        if ebfmi.min() < EBFMI_MIN:
            warns.append(f"NUTS axis {ax}: E-BFMI {ebfmi.min():.2f} < {EBFMI_MIN}: the noise scale or a heavy tail is "
                         f"poorly explored; raise warmup or reconsider the observation model.")
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

