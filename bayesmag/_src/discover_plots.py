"""Figures of a discovery run (matplotlib, Agg backend, PNG files; style of :mod:`bayesmag._src.plots`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .data import AXES  # noqa: E402

__all__ = ["discovery_figures", "residual_before_after", "fitted_effect", "rmse_bars"]


def _binned(x, r, n_bins=15):
    edges = np.unique(np.quantile(x, np.linspace(0, 1, n_bins + 1)))
    if edges.size < 3:
        return np.array([x.mean()]), np.array([r.mean()]), np.array([r.std()])
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    c = np.array([x[idx == k].mean() for k in range(edges.size - 1)])
    m = np.array([r[idx == k].mean() for k in range(edges.size - 1)])
    se = np.array([r[idx == k].std() / np.sqrt(max((idx == k).sum(), 1)) for k in range(edges.size - 1)])
    return c, m, se


def _thin(n, k=3000, seed=0):
    return np.sort(np.random.default_rng(seed).choice(n, size=min(n, k), replace=False))


def residual_before_after(path: Path, x: np.ndarray, before: np.ndarray, after: np.ndarray, *, xlabel: str,
                          title: str) -> None:
    """Residual against the variable that revealed a mismatch, before and after the extension."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), sharey=True)
    sel = _thin(x.size)
    for ax, r, lab in ((axes[0], before, "before"), (axes[1], after, "after")):
        ax.scatter(x[sel], r[sel], s=3, alpha=0.25, color="0.5")
        c, m, se = _binned(x, r)
        ax.errorbar(c, m, yerr=2 * se, color="C3", marker="o", ms=4, lw=1.5, label="binned mean +- 2 se")
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel(xlabel)
        ax.set_title(f"{lab} (rms {np.sqrt(np.mean(r**2)):.3g} uT)")
    axes[0].set_ylabel("residual (uT)")
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def fitted_effect(path: Path, x: np.ndarray, effect: np.ndarray, sd: np.ndarray, r_before: np.ndarray, *,
                  xlabel: str, title: str) -> None:
    """The fitted effect (uT) against ``x`` with its 95% band, over the residual it explains."""
    fig, ax = plt.subplots(figsize=(6.5, 4))
    sel = _thin(x.size)
    ax.scatter(x[sel], r_before[sel], s=3, alpha=0.2, color="0.6", label="residual before")
    o = np.argsort(x)
    ax.fill_between(x[o], (effect - 1.96 * sd)[o], (effect + 1.96 * sd)[o], color="C0", alpha=0.3, lw=0,
                    label="95% band")
    ax.plot(x[o], effect[o], ".", ms=1.5, color="C0", label="fitted effect")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("uT")
    ax.set_title(title)
    ax.legend(fontsize=8, markerscale=4)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def rmse_bars(path: Path, before: dict, after: dict) -> None:
    """Out-of-sample RMSE per axis before and after discovery."""
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    x = np.arange(3)
    ax.bar(x - 0.2, [before[a] for a in AXES], 0.4, label="before")
    ax.bar(x + 0.2, [after[a] for a in AXES], 0.4, label="after")
    ax.set_xticks(x, [f"{a} axis" for a in AXES])
    ax.set_ylabel("out-of-sample RMSE (uT)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def discovery_figures(out: Path, res) -> list[str]:
    """Write all figures of a :class:`~bayesmag._src.discover.DiscoveryResult`; returns their file names."""
    out = Path(out)
    files = []
    variables = {v.name: v for v in res.arrays["variables"]}
    rmse_bars(out / "rmse_before_after.png", res.baseline["rmse"], res.final["rmse"])
    files.append("rmse_before_after.png")
    for i, f in enumerate(res.findings, 1):
        e = res.arrays["effects"].get((f["axis"], f["effect"]))
        if e is None:
            continue
        v = variables.get(e["revealed_by"]) or variables["time"]
        xl = f"{v.label} ({v.unit})" if v.unit else v.label
        name = f"finding{i}_{f['axis']}_{f['effect']}"
        residual_before_after(out / f"{name}_residuals.png", v.values, e["r_before"], e["r_after"], xlabel=xl,
                              title=f"{f['axis']} axis residual vs {v.label}, before/after {f['effect']}")
        fitted_effect(out / f"{name}_effect.png", v.values, e["effect"], e["sd"], e["r_before"], xlabel=xl,
                      title=f"fitted {f['effect']} on {f['axis']} ({f['setting']})")
        files += [f"{name}_residuals.png", f"{name}_effect.png"]
    for j, u in enumerate(res.unexplained, 1):
        v = variables.get(u["variable"])
        if v is None:
            v = variables["time"]
        a = AXES.index(u["axis"])
        name = f"unexplained{j}_{u['axis']}_{u['variable'].replace('/', '').replace('|', '')}.png"
        residual_before_after(out / name, v.values, res.arrays["base_resid"][:, a], res.arrays["final_resid"][:, a],
                              xlabel=f"{v.label} ({v.unit})" if v.unit else v.label,
                              title=f"unexplained on {u['axis']}: {u['where']}")
        files.append(name)
    return files
