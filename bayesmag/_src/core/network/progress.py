"""Training progress: :class:`TrainProgress` reports, a tqdm bar, and merging the reports of several trainings."""

from __future__ import annotations

import threading
from typing import Any, Callable, NamedTuple
import numpy as np

__all__ = ['TrainProgress', 'progress_bar', 'merged_reporter', 'merge_progress']


class TrainProgress(NamedTuple):
    """Where training stands after a chunk of epochs, per axis: ``epochs``, ``best_val_loss``,
    ``val_loss`` (of the last epoch run), ``done`` (stopped), and ``max_epochs``."""

    epochs: np.ndarray
    best_val_loss: np.ndarray
    val_loss: np.ndarray
    done: np.ndarray
    max_epochs: int



def progress_bar(max_epochs: int, n_axes: int = 1, *,
                 desc: str = "network training") -> tuple[Callable[[TrainProgress], None], Any]:
    """A ``tqdm`` bar over ``n_axes`` trainings of at most ``max_epochs`` epochs each, fed by
    :class:`TrainProgress`: the epochs run, a stopped training counted as all its epochs (early
    stopping makes the rest unknown until it happens); the best validation loss per axis (up to 3
    axes) or how many have stopped."""
    from tqdm.auto import tqdm
    bar = tqdm(total=n_axes * max_epochs, desc=desc, unit="epoch", leave=False)

    def update(p: TrainProgress) -> None:
        bar.update(max(0, int(np.where(p.done, p.max_epochs, p.epochs).sum()) - bar.n))
        if p.done.size <= 3:
            bar.set_postfix_str("best val loss " + " ".join("-" if not np.isfinite(v) else f"{v:.4g}"
                                                             for v in p.best_val_loss))
        else:
            bar.set_postfix_str(f"{int(p.done.sum())} of {p.done.size} stopped")

    return update, bar



def merged_reporter(n_parts: int, n_axes: int, sink: Callable[[TrainProgress], None]) -> Callable[[int, TrainProgress], None]:
    """``report(k, p)`` for ``n_parts`` trainings of ``n_axes`` axes running on threads: keeps each one's
    latest :class:`TrainProgress` and passes ``sink`` all of them merged (:func:`merge_progress`), under a lock."""
    latest: list = [None] * n_parts
    lock = threading.Lock()

    def report(k: int, p: TrainProgress) -> None:
        with lock:
            latest[k] = p
            sink(merge_progress(latest, n_axes, p.max_epochs))

    return report



def merge_progress(parts: list, n_axes: int, max_epochs: int) -> TrainProgress:
    """One :class:`TrainProgress` of several trainings (``parts``: each one's latest, or None when it has
    not reported yet: counted as ``n_axes`` axes at epoch 0, not stopped)."""
    idle = TrainProgress(np.zeros(n_axes, int), np.full(n_axes, np.nan), np.full(n_axes, np.nan),
                         np.zeros(n_axes, bool), max_epochs)
    parts = [idle if q is None else q for q in parts]
    return TrainProgress(*(np.concatenate([getattr(q, f) for q in parts])
                           for f in ("epochs", "best_val_loss", "val_loss", "done")), max_epochs)

