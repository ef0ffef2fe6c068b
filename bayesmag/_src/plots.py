"""Figures a user would rather look at than read (matplotlib, Agg backend, PNG files)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .data import AXES  # noqa: E402

__all__ = ["calibration_scatter", "residual_histograms", "job_figures"]


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
        ax.set_title(f"{AXES[a]} axis")
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def job_figures(out: Path, result, columns: dict) -> None:
    """The standard figures of a calibration job."""
    calibration_scatter(out / "calibration.png", columns["measured"], columns["predicted"], columns["reference"])
    res = {"physics": columns["reference"] - result["uq"].mean}
    if "hybrid_predicted" in columns:
        res["hybrid"] = columns["reference"] - columns["hybrid_predicted"]
    residual_histograms(out / "residual_histograms.png", res)
