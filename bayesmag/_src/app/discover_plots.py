"""Figures of a discovery run (matplotlib, Agg backend, PNG files; style of :mod:`bayesmag._src.app.plots`)."""

from __future__ import annotations

import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from bayesmag._src.core.data import AXES  # noqa: E402

__all__ = ["discovery_figures", "residual_before_after", "fitted_effect", "rmse_bars", "dominant_variable",
           "without_linear_part"]


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
    _title(fig, title, 2)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def fitted_effect(path: Path, x: np.ndarray, effect: np.ndarray, before: np.ndarray, outputs, *, xlabel: str,
                  title: str, categorical: bool = False) -> None:
    """One panel per calibrated output the effect shows in: the residual without the effect
    (binned means +- 2 se) and the fitted effect's binned means, against the variable that
    dominates it; both with their linear part removed (:func:`without_linear_part`), so the
    fitted curve and the residual it explains are on the same scale."""
    fig, axes = plt.subplots(1, len(outputs), figsize=(4.2 * len(outputs), 3.8), squeeze=False)
    sel = _thin(x.size)
    for ax, o in zip(axes[0], outputs):
        a = AXES.index(o)
        ax.scatter(x[sel], before[sel, a], s=3, alpha=0.2, color="0.6")
        c, m, se = _binned(x, before[:, a], categorical=categorical)
        ax.errorbar(c, m, yerr=2 * se, color="C3", marker="o", ms=4, lw=1.2, label="residual without it (binned)")
        c, m, _ = _binned(x, effect[:, a], categorical=categorical)
        ax.plot(c, m, "s-", color="C0", ms=4, label="fitted effect (binned)")
        lim = np.nanmax(np.abs(np.concatenate([m, np.quantile(before[:, a], [0.01, 0.99])])))
        ax.set_ylim(-1.3 * lim, 1.3 * lim)
        if categorical:
            ax.set_xticks(c, [f"{v:g}" for v in c])
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel(xlabel)
        ax.set_title(f"{o} output")
    axes[0][0].set_ylabel("uT, linear part removed")
    axes[0][0].legend(fontsize=7)
    _title(fig, title, len(outputs))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def without_linear_part(X0: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``y`` (n, 3) less its least-squares projection on the thermo-affine design ``X0`` (n, k):
    the part of an effect that the calibration's own coefficients cannot take up."""
    beta = np.linalg.lstsq(X0, y, rcond=None)[0]
    return y - X0 @ beta


def dominant_variable(variables: list, effect: np.ndarray, default: str, n_bins: int = 15):
    """The variable whose binned means explain the largest share of the effect's variance
    (summed over the columns of ``effect``); ties keep ``default`` (the entry's own)."""
    total = float(((effect - effect.mean(0)) ** 2).sum())
    best, best_r2 = None, -1.0
    for v in variables:
        if total <= 0:
            break
        x = v.values
        if v.categorical:
            idx = np.unique(x, return_inverse=True)[1].reshape(-1)
        else:
            edges = np.unique(np.quantile(x, np.linspace(0, 1, n_bins + 1)))
            if edges.size < 3:
                continue
            idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
        cnt = np.bincount(idx)
        means = np.stack([np.bincount(idx, weights=effect[:, a]) / np.maximum(cnt, 1) for a in range(effect.shape[1])], 1)
        r2 = 1.0 - float(((effect - means[idx]) ** 2).sum()) / total
        r2 += 1e-3 if v.name == default else 0.0
        if r2 > best_r2:
            best, best_r2 = v, r2
    return best, best_r2


def _title(fig, text: str, panels: int) -> None:
    fig.suptitle("\n".join(textwrap.wrap(text, width=int(48 * panels))), fontsize=10)


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

    Each finding is drawn against the variable that dominates its fitted effect (the input of its
    largest column, chosen by discovery; else the variable whose binned means explain most of the
    effect's variance; run and direction of travel as categories), with the linear part removed;
    unexplained structure per sensor channel against its located variable (none for an output's)."""
    out = Path(out)
    files = []
    variables = {v.name: v for v in res.arrays["variables"]}
    rmse_bars(out / "rmse_before_after.png", res.baseline["rmse"], res.final["rmse"])
    files.append("rmse_before_after.png")
    X0 = res.arrays.get("X0")
    for i, (f, e) in enumerate(zip(res.findings, res.arrays["effects"]), 1):
        eff, before = e["effect"], e["before"]
        if X0 is not None:
            eff, before = without_linear_part(X0, eff), without_linear_part(X0, before)
        outs = f["outputs"] or ["x", "y", "z"]
        cols = [AXES.index(o) for o in outs]
        v = variables.get(e["depends_on"])
        if v is None:
            v, _ = dominant_variable(list(variables.values()), eff[:, cols], e["depends_on"])
        v = v or variables["time"]
        xl = f"{v.label} ({v.unit})" if v.unit else v.label
        where = f["channel"] if f["frame"] != "output" else f"output{f['axis']}"
        name = f"finding{i}_{f['effect']}_{where}.png"
        place = (f"{f['channel']} channel" if f["frame"] == "sensor" else
                 "whole sensor" if f["frame"] == "whole" else f"{f['axis']} output")
        fitted_effect(out / name, v.values, eff, before, outs, xlabel=xl,
                      title=f"{f['effect']} ({place}): {f['description']}", categorical=v.categorical)
        files.append(name)
    for j, u in enumerate(res.unexplained, 1):
        if u.get("frame") == "output":
            continue            # structure of a calibrated output (a per-run term that wandered): no channel residual
        v = variables.get(u["variable"]) or variables["time"]
        a = AXES.index(u["channel"])
        name = f"unexplained{j}_{u['channel']}_{v.name.replace('/', '').replace('|', '')}.png"
        residual_before_after(out / name, v.values, res.arrays["base_resid"][:, a], res.arrays["final_resid"][:, a],
                              xlabel=f"{v.label} ({v.unit})" if v.unit else v.label,
                              title=f"unexplained on the {u['channel']} sensor channel (residual in sensor units)",
                              categorical=v.categorical)
        files.append(name)
    return files
