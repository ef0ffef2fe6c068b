"""Figures a user would rather look at than read (matplotlib, Agg backend, PNG files)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .data import AXES  # noqa: E402

__all__ = ["calibration_scatter", "residual_histograms", "residuals_vs", "residuals_vs_time", "residual_figures",
           "physics_figures", "residual_histogram_figure", "FigureWorker", "InlineFigures"]


def calibration_scatter(path: Path, measured: np.ndarray, calibrated: np.ndarray, reference: np.ndarray,
                        title: str = "Measured and calibrated vs reference") -> None:
    """Per axis: measured and calibrated field against the reference, with the identity line."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    for a, ax in enumerate(axes):
        r = reference[:, a]
        lim = [float(min(r.min(), measured[:, a].min())), float(max(r.max(), measured[:, a].max()))]
        ax.plot(lim, lim, color="0.6", lw=1, zorder=0, label="identity")
        ax.scatter(r, measured[:, a], s=6, alpha=0.5, label="measured (raw)")
        ax.scatter(r, calibrated[:, a], s=6, alpha=0.7, label="calibrated")
        ax.set_xlabel(f"reference B{AXES[a]} (uT)")
        ax.set_ylabel(f"B{AXES[a]} (uT)")
        ax.set_title(f"{AXES[a]} axis")
    axes[0].legend(loc="upper left", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def residual_histograms(path: Path, residuals: dict[str, np.ndarray], title: str = "Test residuals") -> None:
    """Per axis: histograms of residuals (reference - prediction) for each named stage."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for a, ax in enumerate(axes):
        for name, r in residuals.items():
            ra = r[:, a]
            ax.hist(ra, bins=40, alpha=0.55, label=f"{name} (sd {ra.std():.3g})")
        ax.axvline(0, color="k", lw=0.8)
        ax.set_xlabel(f"residual B{AXES[a]} (uT)")
        ax.set_ylabel("count")
        ax.set_title(f"{AXES[a]} axis")
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _band_panel(ax, x, r, sd, k: float = 2.0) -> float:
    """Residuals against x with the +-k sd band (sorted by x); returns the fraction inside the band."""
    order = np.argsort(x)
    ax.scatter(x, r, s=4, alpha=0.6, color="C0", label="residual", zorder=2)
    ax.fill_between(x[order], -k * sd[order], k * sd[order], color="C1", alpha=0.25, lw=0, label=f"+-{k:g} sd", zorder=0)
    ax.axhline(0, color="k", lw=0.6)
    return float(np.mean(np.abs(r) <= k * sd))


def residuals_vs(x: np.ndarray, residual: np.ndarray, sd: np.ndarray, *, xlabels, title: str):
    """Residual (reference - physics, uT) of each axis against each column of ``x`` (n, m), +-2 sd band.

    Rows: output axes; columns: the variables in ``x`` (labelled ``xlabels``). Returns the figure;
    each panel's title gives the share of rows inside the band (about 95% when sd is right).
    """
    x = np.asarray(x, dtype=np.float64).reshape(len(residual), -1)
    m = x.shape[1]
    fig, axes = plt.subplots(3, m, figsize=(4.2 * m + 0.5, 8.4), squeeze=False)
    for a in range(3):
        for j in range(m):
            ax = axes[a, j]
            inside = _band_panel(ax, x[:, j], residual[:, a], sd[:, a])
            ax.set_title(f"{AXES[a]} axis: {inside:.1%} inside +-2 sd", fontsize=9)
            ax.set_xlabel(xlabels[j])
            ax.set_ylabel(f"residual B{AXES[a]} (uT)")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def residuals_vs_time(time: np.ndarray, run: np.ndarray, residual: np.ndarray, sd: np.ndarray, *,
                      max_runs: int = 8, title: str = "Physics residuals vs time, per run"):
    """Residual against time since the start of each run: rows axes, columns runs (first ``max_runs``)."""
    runs = np.unique(run)[:max_runs]
    fig, axes = plt.subplots(3, len(runs), figsize=(3.2 * len(runs) + 0.8, 8.4), squeeze=False, sharey="row")
    for j, r in enumerate(runs):
        sel = run == r
        t = time[sel] - time[sel].min()
        for a in range(3):
            ax = axes[a, j]
            inside = _band_panel(ax, t, residual[sel, a], sd[sel, a])
            ax.set_title(f"run {int(r)}, {AXES[a]}: {inside:.0%} in band", fontsize=8)
            ax.set_xlabel("time since run start (s)")
            if j == 0:
                ax.set_ylabel(f"residual B{AXES[a]} (uT)")
    fig.suptitle(title + ("" if len(np.unique(run)) <= max_runs else f" (first {max_runs} runs)"))
    fig.tight_layout()
    return fig


def _save(fig, path: Path) -> None:
    fig.savefig(path, dpi=100)
    plt.close(fig)


def residual_figures(out: Path, data, predicted: np.ndarray, sd: np.ndarray, *, stage: str = "physics") -> list[str]:
    """Belsten-style residual diagnostics of the rows in ``data`` (with reference): vs temperature, vs time per
    run, vs each reference field component, each with the +-2 sd band of the predictive uncertainty."""
    r = data.b_ref - predicted
    files = [f"{stage}_residuals_vs_temperature.png", f"{stage}_residuals_vs_time.png",
             f"{stage}_residuals_vs_reference.png"]
    _save(residuals_vs(data.temperature, r, sd, xlabels=["temperature (C)"],
                       title=f"{stage.capitalize()} residuals vs temperature (test rows)"), out / files[0])
    _save(residuals_vs_time(data.time, data.run, r, sd, title=f"{stage.capitalize()} residuals vs time, per run"),
          out / files[1])
    _save(residuals_vs(data.b_ref, r, sd, xlabels=[f"reference B{a} (uT)" for a in AXES],
                       title=f"{stage.capitalize()} residuals vs the reference field (test rows)"), out / files[2])
    return files


def physics_figures(out: Path, test, columns: dict) -> None:
    """The physics stage's figures of a job: calibration scatter and residual diagnostics of the test rows."""
    calibration_scatter(out / "calibration.png", columns["measured"], columns["predicted"], columns["reference"])
    residual_figures(out, test, columns["predicted"], columns["total"])


def residual_histogram_figure(out: Path, result, columns: dict) -> None:
    """Histograms of the test residuals of the physics and (when there) hybrid predictions."""
    res = {"physics": columns["reference"] - result["uq"].mean}
    if "hybrid_predicted" in columns:
        res["hybrid"] = columns["reference"] - columns["hybrid_predicted"]
    residual_histograms(out / "residual_histograms.png", res)


from .figure_worker import FigureWorker, InlineFigures  # noqa: E402  (moved there; kept importable here)
