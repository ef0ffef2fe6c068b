"""Figures of a discovery run (matplotlib, Agg backend, PNG files; style of :mod:`bayesmag._src.app.plots`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from bayesmag._src.core.data import AXES  # noqa: E402

__all__ = ["discovery_figures", "residual_before_after", "fitted_effect", "rmse_bars"]


def _binned(x, r, n_bins=15, categorical=False):
    if categorical:
        cats = np.unique(x)
        m = np.array([r[x == c].mean() for c in cats])
        se = np.array([r[x == c].std() / np.sqrt(max((x == c).sum(), 1)) for c in cats])
        return cats, m, se
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
                          title: str, categorical: bool = False) -> None:
    """Residual against the variable it depends on, before and after (``categorical``: one group per value)."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), sharey=True)
    sel = _thin(x.size)
    for ax, r, lab in ((axes[0], before, "before"), (axes[1], after, "after")):
        ax.scatter(x[sel], r[sel], s=3, alpha=0.25, color="0.5")
        c, m, se = _binned(x, r, categorical=categorical)
        if categorical:
            ax.set_xticks(c, [f"{v:g}" for v in c])
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


def fitted_effect(path: Path, x: np.ndarray, effect: np.ndarray, before: np.ndarray, outputs, *, xlabel: str,
                  title: str, categorical: bool = False) -> None:
    """One panel per calibrated output the effect shows in: the residual without the effect
    (binned means +- 2 se) and the fitted effect's binned means, against the variable it depends on."""
    fig, axes = plt.subplots(1, len(outputs), figsize=(4.2 * len(outputs), 3.8), squeeze=False)
    sel = _thin(x.size)
    for ax, o in zip(axes[0], outputs):
        a = AXES.index(o)
        ax.scatter(x[sel], before[sel, a], s=3, alpha=0.2, color="0.6")
        c, m, se = _binned(x, before[:, a], categorical=categorical)
        ax.errorbar(c, m, yerr=2 * se, color="C3", marker="o", ms=4, lw=1.2, label="residual without it")
        c, m, _ = _binned(x, effect[:, a], categorical=categorical)
        ax.plot(c, m, "s-", color="C0", ms=4, label="fitted effect")
        if categorical:
            ax.set_xticks(c, [f"{v:g}" for v in c])
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel(xlabel)
        ax.set_title(f"{o} output")
    axes[0][0].set_ylabel("uT")
    axes[0][0].legend(fontsize=8)
    fig.suptitle(title)
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
    """Write all figures of a :class:`~bayesmag._src.pipeline.discover.DiscoveryResult`; returns their file names.

    Each finding is drawn against the variable its effect depends on (run and direction of
    travel as categories); unexplained structure per sensor channel against its located variable."""
    out = Path(out)
    files = []
    variables = {v.name: v for v in res.arrays["variables"]}
    rmse_bars(out / "rmse_before_after.png", res.baseline["rmse"], res.final["rmse"])
    files.append("rmse_before_after.png")
    for i, (f, e) in enumerate(zip(res.findings, res.arrays["effects"]), 1):
        v = variables.get(e["depends_on"]) or variables["time"]
        xl = f"{v.label} ({v.unit})" if v.unit else v.label
        where = f["channel"] if f["frame"] != "output" else f"output{f['axis']}"
        name = f"finding{i}_{f['effect']}_{where}.png"
        fitted_effect(out / name, v.values, e["effect"], e["before"], f["outputs"] or ["x", "y", "z"], xlabel=xl,
                      title=f"{f['effect']}: {f['description']}", categorical=v.categorical)
        files.append(name)
    for j, u in enumerate(res.unexplained, 1):
        v = variables.get(u["variable"]) or variables["time"]
        a = AXES.index(u["channel"])
        name = f"unexplained{j}_{u['channel']}_{v.name.replace('/', '').replace('|', '')}.png"
        residual_before_after(out / name, v.values, res.arrays["base_resid"][:, a], res.arrays["final_resid"][:, a],
                              xlabel=f"{v.label} ({v.unit})" if v.unit else v.label,
                              title=f"unexplained on the {u['channel']} sensor channel (residual in sensor units)",
                              categorical=v.categorical)
        files.append(name)
    return files
