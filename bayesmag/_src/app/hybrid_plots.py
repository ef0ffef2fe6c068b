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
from typing import TYPE_CHECKING

import numpy as np

from bayesmag._src.app.figure_layout import fixed_layout, plt  # pyplot (Agg) imported at the first figure
from bayesmag._src.core.data import AXES

if TYPE_CHECKING:                       # the figure process imports this module without JAX: metrics and
    from bayesmag._src.core.likelihoods import Likelihood      # likelihoods only where PIT values are computed

__all__ = ["uncertainty_vs_temperature", "calibration_curves", "pit_histograms",
           "hybrid_figures", "hybrid_figure_tasks"]


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
    fixed_layout(fig)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def calibration_curves(path: Path, dists: dict[str, Likelihood], y: np.ndarray,
                       title: str = "Calibration of central intervals (test rows)") -> None:
    """Per axis: observed against nominal coverage, one line per predictive distribution."""
    from bayesmag._src.app.plots import draw_calibration_curves
    from bayesmag._src.core import metrics as M
    draw_calibration_curves(path, {name: M.calibration_curve(d, y) for name, d in dists.items()}, title)


def pit_histograms(path: Path, dists: dict[str, Likelihood], y: np.ndarray, bins: int = 10,
                   title: str = "PIT histograms (flat = calibrated)") -> None:
    """Rows: predictive distributions; columns: axes; dashed line: the uniform density."""
    from bayesmag._src.app.plots import pit_figure
    from bayesmag._src.core import metrics as M
    pit_figure(path, {name: np.asarray(M.pit(d, y)) for name, d in dists.items()}, bins, title, pad=0.0)


def hybrid_figure_tasks(columns: dict[str, np.ndarray], temperature: np.ndarray,
                        dists: dict[str, Likelihood], *, level: float = 0.95) -> list:
    """The figures of :func:`hybrid_figures` as tasks ``(draw, args, kwargs)``: the calibration curves and
    PIT values are computed here, so that drawing needs plain arrays only (no JAX in a figure process)."""
    from bayesmag._src.app.plots import draw_calibration_curves, draw_file, pit_figure, residual_interval_figure
    from bayesmag._src.core import metrics as M
    c = {k: np.asarray(v) for k, v in columns.items() if k in (
        "reference", "hybrid_predicted", "hybrid_lower", "hybrid_upper", "aleatoric_physics", "epistemic_physics",
        "aleatoric_nn", "epistemic_nn", "hybrid_total")}
    y = c["reference"]
    curves = {name: tuple(np.asarray(v) for v in M.calibration_curve(d, y)) for name, d in dists.items()}
    pits = {name: np.asarray(M.pit(d, y)) for name, d in dists.items()}
    return [
        (draw_file, ("hybrid_residuals_vs_reference.png", residual_interval_figure, y, c["hybrid_predicted"],
                     c["hybrid_lower"], c["hybrid_upper"]),
         {"level": level, "title": "Hybrid: calibrated - reference, with the prediction interval"}),
        (draw_file, ("hybrid_uncertainty_vs_temperature.png", uncertainty_vs_temperature, np.asarray(temperature), {
            "physics aleatoric": c["aleatoric_physics"], "physics epistemic": c["epistemic_physics"],
            "NN aleatoric": c["aleatoric_nn"], "NN epistemic": c["epistemic_nn"], "total": c["hybrid_total"]}), {}),
        (draw_file, ("hybrid_calibration.png", draw_calibration_curves, curves,
                     "Calibration of central intervals (test rows)"), {}),
        (draw_file, ("hybrid_pit.png", pit_figure, pits, 10, "PIT histograms (flat = calibrated)"), {"pad": 0.0}),
    ]


def hybrid_figures(out: Path, columns: dict[str, np.ndarray], temperature: np.ndarray,
                   dists: dict[str, Likelihood], *, level: float = 0.95) -> None:
    """All hybrid-stage figures into ``out`` (columns of the primary likelihood, all ``dists``)."""
    from bayesmag._src.app.plots import run_tasks
    run_tasks(out, hybrid_figure_tasks(columns, temperature, dists, level=level))
