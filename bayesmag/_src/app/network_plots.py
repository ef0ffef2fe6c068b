"""Figure of residual-network training: training and validation loss per epoch and axis."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from bayesmag._src.app.figure_layout import fixed_layout, plt  # pyplot (Agg) imported at the first figure
from bayesmag._src.core.data import AXES

__all__ = ["loss_curves", "loss_curve_task"]


def loss_curves(path: Path, networks: Mapping[str, object], axes: tuple[str, ...] = AXES) -> Path:
    """One panel per axis: training (dashed) and validation (solid) loss of every network per epoch,
    with the epoch whose weights were kept marked. ``networks``: ``{likelihood: ResidualNetwork}``."""
    fig, panels = plt.subplots(1, len(axes), figsize=(4.2 * len(axes), 3.4), squeeze=False)
    for name, net in networks.items():
        info = net.info
        for a, (ax, p) in enumerate(zip(axes, panels[0])):
            n = int(np.asarray(info.epochs_run)[a])
            ep = np.arange(1, n + 1)
            line, = p.plot(ep, np.asarray(info.val_loss)[a, :n], lw=1.2, label=f"{name} validation")
            p.plot(ep, np.asarray(info.train_loss)[a, :n], lw=0.8, ls="--", color=line.get_color(),
                   label=f"{name} training")
            best = int(np.asarray(info.best_epoch)[a])
            if best >= 0:
                p.plot([best + 1], [float(np.asarray(info.best_val_loss)[a])], "o", ms=4, color=line.get_color())
            p.set_title(f"axis {ax}")
            p.set_xlabel("epoch")
    panels[0][0].set_ylabel("regularised NLL (standardised residual)")
    panels[0][-1].legend(fontsize=7)
    fig.suptitle("Residual network training (dot: epoch of the kept weights)", fontsize=10)
    fixed_layout(fig)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def loss_curve_task(networks: Mapping[str, object], name: str = "network_loss.png") -> tuple:
    """:func:`loss_curves` of ``networks`` as a figure task ``(draw, args, kwargs)``: the training record only,
    as NumPy arrays (the figure process never needs the network or JAX)."""
    from types import SimpleNamespace

    from bayesmag._src.app.plots import draw_file
    keep = ("epochs_run", "val_loss", "train_loss", "best_epoch", "best_val_loss")
    nets = {k: SimpleNamespace(info=SimpleNamespace(**{f: np.asarray(getattr(net.info, f)) for f in keep}))
            for k, net in networks.items()}
    return (draw_file, (name, loss_curves, nets), {})
