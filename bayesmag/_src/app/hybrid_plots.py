"""Figures of the hybrid stage (matplotlib, Agg backend, PNG files).

* ``hybrid_residuals_vs_reference.png``: hybrid error (calibrated - reference) against the
  reference, each row with its prediction interval as a bar (the paper's Fig. 3 plots the
  prediction itself, on axes where 0.03 uT errors cannot be seen);
* ``hybrid_uncertainty_vs_temperature.png``: physics aleatoric, physics epistemic, NN
  aleatoric, NN epistemic and total sd against temperature (Fig. 4);
* ``hybrid_calibration.png``: observed against nominal coverage of central intervals, per
  axis, one line per likelihood;
* ``hybrid_pit.png``: PIT histograms, one row per likelihood, one column per axis (flat when
  the predictive distribution is calibrated).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from bayesmag._src.core import metrics as M  # noqa: E402
from bayesmag._src.core.data import AXES  # noqa: E402
from bayesmag._src.core.likelihoods import Likelihood  # noqa: E402

__all__ = ["uncertainty_vs_temperature", "calibration_curves", "pit_histograms",
           "hybrid_figures"]


def uncertainty_vs_temperature(path: Path, temperature: np.ndarray, components: dict[str, np.ndarray],
                               title: str = "Uncertainty components vs temperature") -> None:
    """Per axis: each named sd component ``(n, 3)`` against temperature."""
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.0))
    for a, ax in enumerate(axes):
        for name, v in components.items():
            ax.scatter(temperature, v[:, a], s=5, alpha=0.6, label=name)
        ax.set_xlabel("temperature (C)")
        ax.set_ylabel("sd (uT)")
        ax.set_yscale("log")
        ax.set_title(f"{AXES[a]} axis")
    axes[0].legend(fontsize=7, markerscale=2)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def calibration_curves(path: Path, dists: dict[str, Likelihood], y: np.ndarray,
                       title: str = "Calibration of central intervals (test rows)") -> None:
    """Per axis: observed against nominal coverage, one line per predictive distribution."""
    from bayesmag._src.app.plots import draw_calibration_curves
    draw_calibration_curves(path, {name: M.calibration_curve(d, y) for name, d in dists.items()}, title)


def pit_histograms(path: Path, dists: dict[str, Likelihood], y: np.ndarray, bins: int = 10,
                   title: str = "PIT histograms (flat = calibrated)") -> None:
    """Rows: predictive distributions; columns: axes; dashed line: the uniform density."""
    names = list(dists)
    fig, axes = plt.subplots(len(names), 3, figsize=(12, 2.8 * len(names)), squeeze=False)
    for i, name in enumerate(names):
        u = M.pit(dists[name], y)
        for a in range(3):
            ax = axes[i, a]
            ax.hist(u[:, a], bins=bins, range=(0, 1), density=True, alpha=0.8)
            ax.axhline(1.0, color="k", ls="--", lw=0.8)
            ax.set_title(f"{name}, {AXES[a]} axis", fontsize=9)
            ax.set_xlim(0, 1)
            ax.set_xlabel("PIT value F(y)")
            ax.set_ylabel("density")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def hybrid_figures(out: Path, columns: dict[str, np.ndarray], temperature: np.ndarray,
                   dists: dict[str, Likelihood], *, level: float = 0.95) -> None:
    """All hybrid-stage figures into ``out`` (columns of the primary likelihood, all ``dists``)."""
    out = Path(out)
    y = columns["reference"]
    from bayesmag._src.app.plots import residual_interval_figure
    residual_interval_figure(out / "hybrid_residuals_vs_reference.png", y, columns["hybrid_predicted"],
                             columns["hybrid_lower"], columns["hybrid_upper"], level=level,
                             title="Hybrid: calibrated - reference, with the prediction interval")
    uncertainty_vs_temperature(out / "hybrid_uncertainty_vs_temperature.png", temperature, {
        "physics aleatoric": columns["aleatoric_physics"], "physics epistemic": columns["epistemic_physics"],
        "NN aleatoric": columns["aleatoric_nn"], "NN epistemic": columns["epistemic_nn"],
        "total": columns["hybrid_total"],
    })
    calibration_curves(out / "hybrid_calibration.png", dists, y)
    pit_histograms(out / "hybrid_pit.png", dists, y)
