"""Firmware exports of a field calibration: the same targets as a vector calibration (docs/export.md).

A field fit is the thermo-affine model, so every target of :mod:`bayesmag._src.app.export` applies:
the fit is wrapped as a calibration-like object and the same writers render it. A magnitude fit's
coefficients are in its gauge frame (M upper-triangular): each file says so, because the rotation
between that frame and the vehicle's body frame is not in the data.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from bayesmag._src.app.export import FORMATS, build_export, render
from bayesmag._src.core.data import CalibrationData
from bayesmag._src.core.field import FieldFit, gauge_text
from bayesmag._src.core.physics import PhysicsModel

__all__ = ["FieldCalibration", "field_export_texts"]


@dataclasses.dataclass(frozen=True)
class _Box:
    low: np.ndarray
    high: np.ndarray
    rate_high: None = None        # rates are not checked for a field calibration's export
    out_low: None = None          # nor the calibrated output's range (there is no vector reference)
    out_high: None = None


@dataclasses.dataclass(frozen=True)
class FieldCalibration:
    """The parts of a :class:`~bayesmag.Calibration` the exporters read, from a :class:`FieldFit`."""

    model: PhysicsModel
    theta: np.ndarray
    domain: _Box
    network: None = None

    @classmethod
    def from_fit(cls, fit: FieldFit, train: CalibrationData) -> "FieldCalibration":
        S, Ks, O, Ko, _ = fit.matrices()
        theta = np.column_stack([S, Ks, O, Ko])                       # (3, 8): paper order per axis
        x = np.column_stack([train.b_meas, train.temperature])
        return cls(PhysicsModel.paper(t0=fit.model.t0, temperature=True), theta, _Box(x.min(0), x.max(0)))


def field_export_texts(fit: FieldFit, train: CalibrationData, formats=tuple(FORMATS),
                       held_out: CalibrationData | None = None) -> dict[str, str]:
    """``{format: file text}`` for a field calibration (no vector reference: the accuracy table is against the full
    model, on ``held_out`` (the run's held-out rows) where given, else on the training rows, said so). The component
    figures include the gauge rotation a magnitude fit does not determine; the |B| figure does not."""
    cal = FieldCalibration.from_fit(fit, train)
    strip = lambda d, what: CalibrationData(d.b_meas, d.temperature, None, d.time, d.run, source=what,
                                                       time_given=d.time_given)  # noqa: E731
    rows = strip(train, "training rows")
    test = strip(held_out, "held-out rows") if held_out is not None and held_out.n > 0 else None
    ex = build_export(cal, rows, held_out=test)
    note = (f"Field calibration ({fit.model.measurement.name} measurement model); gauge: "
            f"{gauge_text(fit.model.measurement)}. The RMSE of each form against the full model is per component in "
            f"that frame (a symmetric PX4/ArduPilot matrix cannot hold its rotation, which no magnitude fit "
            f"determines); the |B| figure is what a magnitude calibration is judged by.")
    out = {}
    for fmt in formats:
        text = render(fmt, ex)
        if fmt in ("json", "magcal"):
            doc = json.loads(text)
            doc["field_calibration"] = note
            text = json.dumps(doc, indent=2) + "\n"
        elif fmt == "c-header":
            text = f"/* {note} */\n" + text
        else:
            text = f"# {note}\n" + text
        out[fmt] = text
    return out
