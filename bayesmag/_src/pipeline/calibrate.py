"""``calibrate(data, settings) -> CalibrationRun``: the whole calibration as one pure function.

The stages (:mod:`~bayesmag._src.pipeline.stages`) in order -- physics, then the hybrid stage when
``settings.network`` is set, then NUTS when ``settings.nuts`` is set -- on the training rows, each
predicting the optional ``test`` rows. Nothing is written and nothing is drawn: the command line's
job (``bayesmag._src.app.job``) is load, split, :func:`calibrate`, write; :class:`~bayesmag.Calibrator`
calls it directly; a saved calibration is :attr:`CalibrationRun.predictor` serialised.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable

import numpy as np

from bayesmag._src.core.data import CalibrationData, DataError
from bayesmag._src.core.predictor import Prediction, Predictor
from bayesmag._src.pipeline.settings import CalibrationSettings
from bayesmag._src.pipeline import stages
from bayesmag._src.pipeline.stages import HybridStage, PhysicsStage

__all__ = ["CalibrationRun", "calibrate"]


@dataclasses.dataclass(frozen=True)
class CalibrationRun:
    """What :func:`calibrate` computed: frozen, written by nobody.

    ``physics``: the :class:`PhysicsStage`; ``hybrid``: the :class:`HybridStage` or None; ``nuts``: the
    :class:`~bayesmag.NutsResult` or None; ``predictor``: the calibration (the primary likelihood's
    hybrid predictor, else the physics one); ``domain``: the training rows' value domain;
    ``timings``: seconds per stage.
    """

    settings: CalibrationSettings
    physics: PhysicsStage
    predictor: Predictor
    domain: Any
    hybrid: HybridStage | None = None
    nuts: Any = None
    timings: dict = dataclasses.field(default_factory=dict)

    @property
    def fit(self):
        """The physics fit (:class:`~bayesmag.PhysicsFit`)."""
        return self.physics.fit

    @property
    def warnings(self) -> tuple[str, ...]:
        """What limits trust in this calibration (too few rows, a tiny temperature span, no between-session
        term, a network stopped while improving or by a NaN loss, NUTS diagnostics): each is also raised once as a
        :class:`~bayesmag.CalibrationWarning` by :func:`calibrate`."""
        found = (*self.physics.fit.design_warnings, self.physics.transfer.warning,
                 *(self.hybrid.nan_messages if self.hybrid is not None else ()),
                 *(self.nuts.warnings if self.nuts is not None else ()))
        return tuple(dict.fromkeys(w for w in found if w))

    @property
    def prediction(self) -> Prediction | None:
        """The calibration's prediction of the test rows (None without test rows)."""
        if self.hybrid is not None:
            return self.hybrid.predictions.get(self.hybrid.primary)
        return self.physics.prediction

    def __repr__(self) -> str:
        stages = "physics" + (" + hybrid" if self.hybrid is not None else "") + (" + nuts" if self.nuts is not None else "")
        return f"CalibrationRun({stages}, {self.fit.model.n_params} parameters per axis)"


def calibrate(data: CalibrationData, settings: CalibrationSettings | None = None, *,
              test: CalibrationData | None = None, progress: bool = False,
              on_physics: Callable[[PhysicsStage], None] | None = None, series=None) -> CalibrationRun:
    """Calibrate on the rows ``data`` (with a reference) and, when given, predict the ``test`` rows.

    Args:
      data: the training rows (:class:`~bayesmag.CalibrationData` with ``b_ref``).
      settings: library settings (:class:`~bayesmag.CalibrationSettings`; default: physics only, the physics
        uncertainty by ``UQSettings.method = "auto"`` (exact moments where the model allows, else PS-QMC), T0 the
        training mean).
      test: held-out rows to predict (their predictions are in the stages and :attr:`CalibrationRun.prediction`).
      progress: progress bars.
      series: ``(recording, train_index, test_index)`` when ``data`` and ``test`` were cut from one recording (a
        split): a model whose rows depend on their neighbours (thermal lag, timing offset, hysteresis) is fitted
        on the training rows within it and predicts the test rows within it, not each part as a recording of its
        own (the lag would run across every held-out block as if the temperature had stopped there, and each
        test block would restart it as at a run start).
      on_physics: called with the :class:`PhysicsStage` as soon as it is done, before the hybrid stage (whose
        networks may still be training): e.g. the command line draws the physics figures meanwhile. What it
        does cannot change the result.

    Returns:
      a frozen :class:`CalibrationRun`.

    Raises:
      DataError: no reference, a non-finite value, a field not in uT or a temperature not in C, fewer rows than
        parameters, or constant temperature with temperature terms.
      ValueError: settings that do not fit the data (e.g. a network too large for the rows).
      CalibrationError: the physics fit did not converge.

    Example:
      >>> import bayesmag
      >>> d = bayesmag.simulate.simulate(400, design="campaign", seed=0)
      >>> run = bayesmag.calibrate(d, bayesmag.CalibrationSettings(uq=bayesmag.UQSettings(method="analytic")))
      >>> run.predictor.predict(d).mean.shape
      (400, 3)
    """
    from bayesmag._src.core.cache import ensure_compile_cache, release_compiled_if_crowded
    from bayesmag._src.core.domain import Domain
    from bayesmag._src.pipeline.prefetch import start_training

    ensure_compile_cache()
    release_compiled_if_crowded()           # a long-lived process must not pass the kernel's mapping limit
    s = settings if settings is not None else CalibrationSettings()
    if data.b_ref is None:
        raise DataError("calibrate needs the reference field (bx_ref, by_ref, bz_ref).")
    from bayesmag._src.core.data import check_units, check_values
    origin = data.source or "the rows given to calibrate"
    check_values(data, origin=origin)       # the command line's checks (it ran them on the whole recording)
    check_units(data, origin=origin, fix="Convert the field columns to uT",
                declare="CalibrationData(..., field_unit='uT')", temperature_fix="Subtract 273.15")
    if s.physics.temperature_terms and np.ptp(data.temperature) < 1e-6:
        raise DataError("The training rows have constant temperature: Ks and Ko are not identifiable. "
                        "Set temperature_terms = false or use a split that keeps temperature variation.")
    if series is not None:
        recording, tr, te = series
        tr, te = np.asarray(tr), np.asarray(te)
        if (len(tr) != data.n or (test is not None and len(te) != test.n)
                or not np.array_equal(recording.b_meas[tr], data.b_meas, equal_nan=True)):
            raise ValueError("series = (recording, train_index, test_index) must give the training rows "
                             "(recording.subset(train_index) is data) and the test rows; it does not.")
    timings: dict[str, float] = {}
    model = s.physics.model(data)
    if data.n < model.n_params + 1:
        raise DataError(f"{origin} holds {data.n} rows but the physics model has {model.n_params} parameters per axis: "
                        f"at least {model.n_params + 1} are needed (many more for a useful calibration).")
    domain = Domain.from_data(data)
    training = []                   # the networks train while the physics stage's uncertainty parts are computed

    def after_fit(fit):
        if s.network is not None and s.uq.transfer_networks == "none":
            training.append(start_training(s.network, fit, data, progress=progress,
                                           series=None if series is None else series[:2]))

    try:
        ps = stages.run_physics_stage(s.uq, data, test, model, domain, timings, covariance=s.physics.covariance,
                                      progress=progress, after_fit=after_fit, series=series)
        if on_physics is not None:
            on_physics(ps)
        predictor, hs, nuts = ps.predictor, None, None
        if s.network is not None:
            hs = stages.run_hybrid_stage(s.network, ps.predictor, ps.uq, data, test, timings, level=s.uq.level,
                                         conformal=s.conformal,
                                         new_session=ps.new_session if test is not None else False, progress=progress,
                                         transfer_networks=s.uq.transfer_networks, uq_settings=s.uq,
                                         pretrained=training[0] if training else None, series=series)
            predictor = hs.predictors[hs.primary]
    finally:                        # an error or interrupt meanwhile: stop the training (a no-op once it finished)
        for t in training:
            if t is not None:
                t.cancel()
    if s.nuts is not None:
        t = time.perf_counter()
        nuts = stages.run_nuts_stage(s.nuts, ps.fit, data, progress=progress,
                                     series=None if series is None else series[:2])
        timings["nuts"] = time.perf_counter() - t
    run = CalibrationRun(s, ps, predictor, domain, hs, nuts, timings)
    import warnings

    from bayesmag._src.core.data import CalibrationWarning, user_stacklevel
    for w in run.warnings:
        warnings.warn(w, CalibrationWarning, stacklevel=user_stacklevel())
    return run
