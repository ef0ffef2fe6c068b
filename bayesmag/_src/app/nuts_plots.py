"""Figures of the NUTS cross-check (matplotlib, Agg backend, PNG files).

* ``nuts_trace.png`` -- trace and rank plots of the parameters with the largest R-hat (the
  ones that decide an "inconclusive" verdict; ties by the lowest bulk ESS), plus the noise
  scales, in LM-standardised units :math:`(\\theta - \\hat\\theta)/\\hat s`.
* ``nuts_pair.png`` -- per axis, the most correlated parameter pair: NUTS draws with the LM
  1/2/3-sigma ellipses, in raw units (top) and in the LM-whitened coordinates of the pair
  (bottom; the LM ellipses become circles, so a shape mismatch is visible).
* ``nuts_forest.png`` -- all parameters, NUTS 95% HDI and mean vs the LM 95% interval, in
  LM-standardised units.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ["trace_parameters", "trace_rank_plot", "pair_plot", "forest_plot", "nuts_figures"]


def _standardised(res, ax: str, name: str) -> np.ndarray:
    const = res.idata.constant_data
    m = float(const.lm_theta.sel(axis=ax, parameter=name))
    s = float(np.sqrt(const.lm_cov.sel(axis=ax, parameter=name, parameter_bis=name)))
    return (res.idata.posterior.theta.sel(axis=ax, parameter=name).values - m) / s


def trace_parameters(summary, n_params: int = 6):
    """The ``n_params`` physics parameters (rows of the NUTS summary) with the largest R-hat, ties broken by
    the lowest bulk ESS: the ones a verdict of "inconclusive" is about."""
    theta = summary[summary.lm_sd.notna()]
    return theta.sort_values(["r_hat", "ess_bulk"], ascending=[False, True], na_position="first").head(n_params)


def trace_rank_plot(path: Path, res, *, n_params: int = 6) -> None:
    """Traces (left) and per-chain rank histograms (right) of the parameters with the largest R-hat."""
    df = res.summary
    theta = trace_parameters(df, n_params)
    rows = [(r.axis, r.parameter, True) for r in theta.itertuples()]
    rows += [(ax, "sigma", False) for ax in res.axes]
    post = res.idata.posterior
    fig, axs = plt.subplots(len(rows), 2, figsize=(12, 1.7 * len(rows) + 0.6), squeeze=False,
                            gridspec_kw={"width_ratios": [3, 1]})
    for k, (ax, name, is_theta) in enumerate(rows):
        x = _standardised(res, ax, name) if is_theta else post.sigma.sel(axis=ax).values
        C, D = x.shape
        step = max(1, D // 500)                       # draw at most ~500 points per chain
        for c in range(C):
            axs[k, 0].plot(np.arange(0, D, step), x[c, ::step], lw=0.5, alpha=0.8)
        s = df[(df.axis == ax) & (df.parameter == name)].iloc[0]
        label = f"{ax}: {name}" + (" (LM sd)" if is_theta else " (uT)")
        axs[k, 0].set_ylabel(label, fontsize=8)
        axs[k, 0].text(0.01, 0.95, f"R-hat {s.r_hat:.3f}  ESS bulk {s.ess_bulk:.0f} tail {s.ess_tail:.0f}",
                       transform=axs[k, 0].transAxes, fontsize=7, va="top")
        ranks = np.argsort(np.argsort(x.ravel())).reshape(C, D)
        bins = np.linspace(0, C * D, 21)
        for c in range(C):
            h, _ = np.histogram(ranks[c], bins=bins)
            axs[k, 1].step(bins[:-1], h, where="post", lw=0.8)
        axs[k, 1].axhline(D / 20, color="k", lw=0.6, ls="--")
        axs[k, 1].set_yticks([])
    axs[0, 0].set_title("largest R-hat first; traces (one colour per chain"
                        + (f", every {max(1, D // 500)}th draw)" if D > 500 else ")"))
    axs[0, 1].set_title("rank histograms (flat = mixed)")
    axs[-1, 0].set_xlabel("draw")
    axs[-1, 1].set_xlabel("rank")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _ellipse(cov2: np.ndarray, k: float, n: int = 200) -> np.ndarray:
    w, V = np.linalg.eigh(cov2)
    t = np.linspace(0, 2 * np.pi, n)
    return (V * np.sqrt(np.clip(w, 0, None))) @ np.vstack([np.cos(t), np.sin(t)]) * k


def pair_plot(path: Path, res) -> None:
    """The most correlated (LM) pair of each axis: NUTS draws over the LM ellipses."""
    const, post = res.idata.constant_data, res.idata.posterior
    names = [str(p) for p in post.parameter.values]
    axes = res.axes
    fig, axs = plt.subplots(2, len(axes), figsize=(4.6 * len(axes), 8.4), squeeze=False)
    for col, ax in enumerate(axes):
        cov = const.lm_cov.sel(axis=ax).values
        m = const.lm_theta.sel(axis=ax).values
        sd = np.sqrt(np.diag(cov))
        corr = cov / np.outer(sd, sd)
        np.fill_diagonal(corr, 0)
        i, j = np.unravel_index(np.argmax(np.abs(corr)), corr.shape)
        i, j = min(i, j), max(i, j)
        th = post.theta.sel(axis=ax).values.reshape(-1, len(names))
        sub = th[:, [i, j]]
        c2 = cov[np.ix_([i, j], [i, j])]
        a = axs[0, col]
        a.scatter(sub[:, 0], sub[:, 1], s=2, alpha=0.25, color="C0", label="NUTS draws", rasterized=True)
        for k, ls in zip((1, 2, 3), ("-", "--", ":")):
            e = _ellipse(c2, k) + m[[i, j], None]
            a.plot(e[0], e[1], color="C3", lw=1, ls=ls, label=f"LM {k}-sigma" if k == 1 else None)
        a.set_xlabel(names[i])
        a.set_ylabel(names[j])
        a.set_title(f"{ax} axis: {names[i]}-{names[j]} (LM corr {corr[i, j]:.6f})", fontsize=9)
        a.ticklabel_format(style="sci", scilimits=(-3, 4))
        L = np.linalg.cholesky(c2)
        w = np.linalg.solve(L, (sub - m[[i, j]]).T)
        b = axs[1, col]
        b.scatter(w[0], w[1], s=2, alpha=0.25, color="C0", rasterized=True)
        for k, ls in zip((1, 2, 3), ("-", "--", ":")):
            t = np.linspace(0, 2 * np.pi, 200)
            b.plot(k * np.cos(t), k * np.sin(t), color="C3", lw=1, ls=ls)
        b.set_aspect("equal")
        b.set_xlabel(f"whitened {names[i]}")
        b.set_ylabel(f"whitened {names[j]} | {names[i]}")
        b.set_title("LM-whitened: circles = LM ellipses", fontsize=9)
    axs[0, 0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def forest_plot(path: Path, res) -> None:
    """All parameters: NUTS mean and 95% HDI vs the LM estimate and 95% interval, in LM sd."""
    df = res.summary
    d = df[df.lm_sd.notna()].reset_index(drop=True)
    lo_col = [c for c in d.columns if c.startswith("hdi_")][0]
    hi_col = [c for c in d.columns if c.startswith("hdi_")][1]
    y = np.arange(len(d))[::-1]
    fig, a = plt.subplots(figsize=(7.5, 0.28 * len(d) + 1.2))
    a.errorbar(np.zeros(len(d)), y + 0.15, xerr=1.96, fmt="s", ms=3, color="C3", lw=1, label="LM (95%)")
    mean = (d["mean"] - d.lm_value) / d.lm_sd
    lo = (d[lo_col] - d.lm_value) / d.lm_sd
    hi = (d[hi_col] - d.lm_value) / d.lm_sd
    a.errorbar(mean, y - 0.15, xerr=[mean - lo, hi - mean], fmt="o", ms=3, color="C0", lw=1,
               label="NUTS (95% HDI)")
    a.set_yticks(y)
    a.set_yticklabels([f"{r.axis}: {r.parameter}" for r in d.itertuples()], fontsize=7)
    a.axvline(0, color="0.6", lw=0.8)
    a.set_xlabel("(theta - theta_LM) / sd_LM")
    a.set_title("NUTS vs LM, all parameters")
    a.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def nuts_figures(folder: Path, res) -> list[Path]:
    """Write the three NUTS figures into ``folder``; returns their paths."""
    folder = Path(folder)
    out = [folder / "nuts_trace.png", folder / "nuts_pair.png", folder / "nuts_forest.png"]
    trace_rank_plot(out[0], res)
    pair_plot(out[1], res)
    forest_plot(out[2], res)
    return out
