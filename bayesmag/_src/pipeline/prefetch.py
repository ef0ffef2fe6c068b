"""The hybrid stage's networks trained in the background while the physics stage finishes.

The residual networks need only the physics fit (their target is its residual); the physics stage's
uncertainty and transfer parts, which need a second or less, need nothing of the networks. :func:`start_training`
starts the training as soon as the fit is there, on a background thread; the hybrid stage then takes the
trained networks (:meth:`Training.network`). The programs are compiled on the calling thread before the
thread starts (:func:`~bayesmag._src.core.network.start_residual_network`): that thread only runs them.
Each network is the one :func:`~bayesmag._src.pipeline.hybrid.train_network` gives (the same rows, seed and
compiled programs), so nothing computed depends on it. Only for the plain stage: one network per likelihood,
no cross-conformal folds and no by-run transfer folds (those train together on one pool of threads).
"""

from __future__ import annotations

import threading
import time
from typing import Callable

from bayesmag._src.core.data import CalibrationData
from bayesmag._src.core.network import NetworkSpec, ResidualNetwork, start_residual_network
from bayesmag._src.core.predictor import network_inputs
from bayesmag._src.pipeline.hybrid import check_network_config, recalibrated
from bayesmag._src.pipeline.settings import NetworkSettings

__all__ = ["Training", "start_training"]


class _Cancelled(Exception):
    """Raised inside the training threads after :meth:`Training.cancel`."""


class Training:
    """Networks training on a background thread: :meth:`network` waits for one, :meth:`cancel` stops them all
    at their next chunk of epochs (an error or interrupt before the hybrid stage took them)."""

    def __init__(self, starts: list[tuple[NetworkSpec, Callable[..., ResidualNetwork]]], settings: NetworkSettings,
                 x, r, progress: bool):
        self._settings, self._x, self._r = settings, x, r
        self._cancel = threading.Event()
        self._done = {spec.likelihood: threading.Event() for spec, _ in starts}
        self._result: dict[str, tuple] = {}
        self._thread = threading.Thread(target=self._run, args=(starts, progress), name="bayesmag-prefetch",
                                        daemon=True)
        self._thread.start()

    def _run(self, starts, progress: bool) -> None:
        for spec, train in starts:
            name = spec.likelihood
            t = time.perf_counter()
            try:
                if self._cancel.is_set():
                    raise _Cancelled()
                bar_update, bar = None, None
                if progress:
                    from bayesmag._src.core.network import progress_bar
                    bar_update, bar = progress_bar(spec.max_epochs, self._r.shape[1],
                                                   desc=f"network training ({spec.likelihood}, {self._r.shape[1]} axes)")

                def report(p, bar_update=bar_update):
                    if self._cancel.is_set():
                        raise _Cancelled()
                    if bar_update is not None:
                        bar_update(p)
                try:
                    self._result[name] = (train(progress=report), None, time.perf_counter() - t)
                finally:
                    if bar is not None:
                        bar.close()
            except BaseException as e:     # handed to network(); a cancelled training is never asked for
                self._result[name] = (None, e, time.perf_counter() - t)
            self._done[name].set()

    def network(self, name: str) -> tuple[ResidualNetwork, float]:
        """The trained network of likelihood ``name`` (recalibrated as the settings say, on this thread) and its
        training time (s); re-raises what the training raised."""
        self._done[name].wait()
        net, err, seconds = self._result[name]
        if err is not None:
            raise err
        return recalibrated(net, self._x, self._r, self._settings), seconds

    def __contains__(self, name: str) -> bool:
        return name in self._done

    def cancel(self) -> None:
        """Stop the training (within one chunk of epochs) and wait for its thread."""
        self._cancel.set()
        self._thread.join()


def start_training(settings: NetworkSettings, fit, train: CalibrationData, *, progress: bool = False,
                   series=None) -> Training | None:
    """Start the plain hybrid stage's networks (one per likelihood) on a background thread, or None where the
    stage trains other networks too (cross-conformal or by-run folds) or where the settings or data would fail
    (the hybrid stage then reports it as before)."""
    if settings.interval_calibration == "conformal":
        return None
    try:
        specs = check_network_config(settings)
        x = network_inputs(train)
        r = fit.residuals(train, series)          # series: (recording, train rows), as the hybrid stage
        starts = []
        for spec in specs:
            starts.append((spec, start_residual_network(x, r, spec, validation_fraction=settings.validation_fraction,
                                                        seed=settings.seed, validation=settings.validation,
                                                        groups=train.run)))
    except Exception:
        return None
    return Training(starts, settings, x, r, progress)
