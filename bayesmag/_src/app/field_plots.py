"""Figures of a field calibration: held-out magnitudes with intervals, direction coverage, heading error."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["field_figures"]


def field_figures(out: Path, fs) -> list[str]:
    """Draw the field figures into ``out``; returns their file names."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    p, y = fs.prediction, fs.target_test
    fig, ax = plt.subplots(figsize=(8, 3.2))
    k = np.arange(len(y))
    ax.fill_between(k, -1.96 * p["total"], 1.96 * p["total"], color="C0", alpha=0.3, label="95 % interval")
    ax.plot(k, y - p["mean"], ".", ms=2, color="k", label="reference - predicted")
    ax.set_xlabel("held-out row"); ax.set_ylabel("magnitude residual (uT)"); ax.legend(fontsize=8)
    fig.tight_layout(); fig.savefig(out / "field_magnitude.png", dpi=90); plt.close(fig)
    names.append("field_magnitude.png")

    B = fs.fit.calibrate(fs.train.b_meas, fs.train.temperature)
    n = B / np.linalg.norm(B, axis=1, keepdims=True)
    fig, axs = plt.subplots(1, 3, figsize=(9, 3))
    for a, (i, j) in zip(axs, [(0, 1), (0, 2), (1, 2)]):
        sc = a.scatter(n[:, i], n[:, j], c=fs.train.temperature, s=2, cmap="viridis")
        a.set_xlim(-1.05, 1.05); a.set_ylim(-1.05, 1.05); a.set_aspect("equal")
        a.set_xlabel("xyz"[i]); a.set_ylabel("xyz"[j])
    fig.colorbar(sc, ax=axs, label="temperature (C)", shrink=0.8)
    fig.suptitle("field directions visited (gauge frame)", fontsize=9)
    fig.savefig(out / "field_directions.png", dpi=90); plt.close(fig)
    names.append("field_directions.png")

    if fs.heading is not None:
        e, sd = fs.heading["error"], fs.heading["sd"]
        fig, ax = plt.subplots(figsize=(8, 3))
        k = np.arange(len(e))
        ax.fill_between(k, -1.96 * sd, 1.96 * sd, color="C1", alpha=0.3, label="95 % interval")
        ax.plot(k, e, ".", ms=2, color="k", label="heading error")
        ax.set_xlabel("level held-out row"); ax.set_ylabel("degrees"); ax.legend(fontsize=8)
        fig.tight_layout(); fig.savefig(out / "field_heading.png", dpi=90); plt.close(fig)
        names.append("field_heading.png")
    return names
