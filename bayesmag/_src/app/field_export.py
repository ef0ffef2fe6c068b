r"""Firmware exports of a field calibration: the same targets as a vector calibration (docs/export.md).

A field fit is the thermo-affine model, so every target of :mod:`bayesmag._src.app.export` applies:
the fit is wrapped as a calibration-like object and the same writers render it.

A magnitude fit (constant or scalar measurement model) determines M(T) and o(T) only up to a left rotation:
abs(R B) = abs(B). Its coefficients are in the gauge frame (S and Ks upper-triangular), the frame of
``bayesmag apply``. The exports use another member of the same family, the **symmetric frame**: with the polar
decomposition S = R P at T0 (R a rotation, P symmetric), every coefficient is left-multiplied by R^T,

.. math::  S' = R^\top S = P,\quad K_s' = R^\top K_s,\quad O' = R^\top O,\quad K_o' = R^\top K_o,

so B' = R^T B_gauge and abs(B') = abs(B_gauge) at every reading and temperature. In that frame S is
symmetric, which is what PX4's and ArduPilot's soft-iron matrix holds: they lose only what they lack
(temperature terms), not the gauge rotation the least-squares fit of a symmetric matrix could not follow.
R is in the JSON exports (``field_frame``) and in a comment line of the others. A vector fit observes the
rotation, so its coefficients are exported as fitted.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from bayesmag._src.app.export import FORMATS, build_export, render
from bayesmag._src.core.data import CalibrationData
from bayesmag._src.core.field import FieldFit, gauge_text
from bayesmag._src.core.physics import PhysicsModel

__all__ = ["FieldCalibration", "field_export_texts", "field_uncertainty_doc", "symmetric_frame"]

#: what export.py's generic "cannot hold" line (_CANNOT_HOLD) says of PX4 and ArduPilot; in the symmetric frame S is held
_ROTATION_PART = "the rotation (antisymmetric) part of S"


@dataclasses.dataclass(frozen=True)
class _Box:
    low: np.ndarray
    high: np.ndarray
    rate_high: None = None        # rates are not checked for a field calibration's export
    out_low: None = None          # nor the calibrated output's range (there is no vector reference)
    out_high: None = None


def symmetric_frame(S, Ks, O, Ko) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """``(R, (S', Ks', O', Ko'))``: R the rotation (det +1) of the polar decomposition ``S = R S'`` and every
    coefficient left-multiplied by ``R^T``, so that ``S'`` is symmetric and ``|M'(T) u + o'(T)| = |M(T) u + o(T)|``.

    From the SVD ``S = U diag(s) V^T``: ``R = U E V^T``, ``S' = V E diag(s) V^T``, E = diag(1, 1, det(U V^T)):
    positive definite when det S > 0 (the polar decomposition, scipy.linalg.polar), else symmetric with one
    negative eigenvalue (R stays a rotation rather than a reflection).

    Example:
      >>> th = np.deg2rad(10.0); Rz = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
      >>> R, (Sp, _, _, _) = symmetric_frame(Rz @ np.diag([1.1, 0.9, 1.0]), np.zeros((3, 3)), np.zeros(3), np.zeros(3))
      >>> bool(np.allclose(R, Rz)), bool(np.allclose(Sp, np.diag([1.1, 0.9, 1.0])))
      (True, True)
    """
    S, Ks, O, Ko = (np.asarray(a, np.float64) for a in (S, Ks, O, Ko))
    U, _, Vt = np.linalg.svd(S)
    E = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ E @ Vt
    Sp = R.T @ S
    return R, (0.5 * (Sp + Sp.T), R.T @ Ks, R.T @ O, R.T @ Ko)


@dataclasses.dataclass(frozen=True)
class FieldCalibration:
    """The parts of a :class:`~bayesmag.Calibration` the exporters read, from a :class:`FieldFit`.

    ``frame``: the rotation R (3, 3) from the fit's gauge frame to the exported one (``B_export = R^T B_gauge``);
    None when the coefficients are the fit's own (a vector fit, or ``symmetric=False``).
    """

    model: PhysicsModel
    theta: np.ndarray
    domain: _Box
    network: None = None
    frame: np.ndarray | None = None

    @classmethod
    def from_fit(cls, fit: FieldFit, train: CalibrationData, *, symmetric: bool = True) -> "FieldCalibration":
        S, Ks, O, Ko, _ = fit.matrices()
        R = None
        if symmetric and fit.model.measurement.gauge == "upper":       # a magnitude fit: the rotation is free
            R, (S, Ks, O, Ko) = symmetric_frame(S, Ks, O, Ko)
        theta = np.column_stack([S, Ks, O, Ko])                       # (3, 8): paper order per axis
        x = np.column_stack([train.b_meas, train.temperature])
        return cls(PhysicsModel.paper(t0=fit.model.t0, temperature=True), theta, _Box(x.min(0), x.max(0)),
                   frame=R)


def _note(fit: FieldFit, R: np.ndarray | None) -> str:
    meas = fit.model.measurement
    head = f"Field calibration ({meas.name} measurement model)"
    if R is None:
        return (f"{head}; gauge: {gauge_text(meas)}. The coefficients are in the reference's frame, which a vector "
                f"fit determines; a symmetric PX4/ArduPilot matrix cannot hold the rotation part of S.")
    thermal = ("the temperature terms they cannot hold, through their least-squares fit to the training rows: PX4 "
               "the thermal gain Ks (approximated by its offset polynomial, which holds Ko), ArduPilot both Ks and Ko "
               "(it has no temperature terms)" if fit.model.temperature else
               "nothing of this model (no temperature terms were fitted): they hold it exactly")
    scale = (" The field magnitude was fitted too, so magnitudes are relative (trace(S) = 3 in the gauge frame)."
             if meas.scale_gauge else "")
    return (f"{head}. Frame: the symmetric frame, i.e. the fit's gauge frame (S and Ks upper-triangular; the frame of "
            f"`bayesmag apply`'s x/y/z_calibrated) rotated by R^T, R the rotation of the polar decomposition S = R P "
            f"at T0 = {fit.model.t0:.6g} C (R: field_frame in the JSON exports, the 'Frame rotation R' line in the others): every "
            f"coefficient here (S, Ks, O, Ko, magcal A and b, PX4, ArduPilot) is in it, B_export = R^T B_gauge. A "
            f"magnitude fit leaves that rotation free (|R B| = |B|), so |B| is unchanged at every reading and "
            f"temperature, and in this frame S is symmetric (S = P): PX4's and ArduPilot's symmetric matrix holds "
            f"it. What PX4/ArduPilot still lose: {thermal}. The RMSE of each form against the full model is per "
            f"component in this frame; the |B| figure is what a magnitude calibration is judged by.{scale}")


_C_NO_U = "/* Expanded uncertainty U: not known (the run folder has no metrics.json). */"


def field_uncertainty_doc(transfer: dict | None, level: float, relative: bool = False) -> dict | None:
    """The JSON exports' ``expanded_uncertainty`` of a field calibration: U of |B| at the median held-out row, same
    session and new session (None with the reason where no between-session term was estimated), from metrics.json's
    ``field.transfer`` block (``transfer``; None: not known)."""
    if not transfer or transfer.get("U_same_session") is None:
        return None
    new = transfer.get("U_new_session")
    why = ("[uq] transfer = \"off\"" if transfer.get("method") == "off" else
           (transfer.get("warning") or "too few usable runs"))
    return {"quantity": "|B| (field magnitude)", "unit": "1 (relative, trace(S) = 3)" if relative else "uT",
            "level": level, "k": transfer.get("k"), "at": "the median held-out row",
            "same_session": transfer["U_same_session"], "new_session": new,
            "applies": "same_session: rows of the sessions (runs, flights) the calibration was fitted on; new_session: "
                       "any later flight or campaign (what `bayesmag apply` gives, column magnitude_transfer). Of the "
                       "magnitude only: a field calibration does not establish the vector's direction. Inside the "
                       "training domain only." + ("" if new is not None else
                                                  f" No new_session U: the between-session term was not estimated "
                                                  f"({why}); a later session can be off by more.")}


def field_export_texts(fit: FieldFit, train: CalibrationData, formats=tuple(FORMATS),
                       held_out: CalibrationData | None = None, uncertainty: dict | None = None) -> dict[str, str]:
    """``{format: file text}`` for a field calibration (no vector reference: the accuracy table is against the full
    model, on ``held_out`` (the run's held-out rows) where given, else on the training rows, said so). A magnitude
    fit is exported in its symmetric frame (:func:`symmetric_frame`, the same R for every format).
    ``uncertainty``: :func:`field_uncertainty_doc` of the run, the JSON exports' ``expanded_uncertainty``."""
    cal = FieldCalibration.from_fit(fit, train)
    R = cal.frame
    strip = lambda d, what: CalibrationData(d.b_meas, d.temperature, None, d.time, d.run, source=what,
                                                       time_given=d.time_given)  # noqa: E731
    rows = strip(train, "training rows")
    test = strip(held_out, "held-out rows") if held_out is not None and held_out.n > 0 else None
    ex = build_export(cal, rows, held_out=test)
    note = _note(fit, R)
    r_line = None if R is None else ("Frame rotation R (rows; B_gauge = R B_export): "
                                     + "; ".join(" ".join(f"{v:.12g}" for v in row) for row in R))
    u = uncertainty
    u_line = ("Expanded uncertainty U of |B|: not known (the run's metrics were not given)" if u is None else
              f"Expanded uncertainty U of |B| ({u['unit']}, coverage {u['level']:.0%}, k = {u['k']:.3g}, at the median "
              f"held-out row): same session {u['same_session']:.3g}; new session "
              + ("not stated (no between-session term)" if u["new_session"] is None else f"{u['new_session']:.3g}")
              + "; of the magnitude only, inside the training domain")
    out = {}
    for fmt in formats:
        text = render(fmt, ex)
        if R is not None and fmt in ("px4", "ardupilot"):
            text = text.replace(_ROTATION_PART, "nothing of S (symmetric at T0 in this frame)")
        if fmt in ("json", "magcal"):
            doc = json.loads(text)
            doc["field_calibration"] = note
            doc["expanded_uncertainty"] = uncertainty
            if R is not None:
                doc["field_frame"] = {"name": "symmetric", "R": R.tolist(), "t0": fit.model.t0,
                                      "relation": "B_export = R^T B_gauge; B_gauge = R B_export (B_gauge: the "
                                                  "x/y/z_calibrated of `bayesmag apply`); |B| is the same in both"}
            text = json.dumps(doc, indent=2) + "\n"
        elif fmt == "c-header":
            c_u = [f"/* {u_line}. */"]
            if u is not None:
                c_u += [f"static const double BAYESMAG_LEVEL = {u['level']:.6g};",
                        f"static const double BAYESMAG_U_MAGNITUDE_SAME_SESSION = {u['same_session']:.6g};"]
                c_u += ([f"static const double BAYESMAG_U_MAGNITUDE_NEW_SESSION = {u['new_session']:.6g};"]
                        if u["new_session"] is not None else
                        ["/* No BAYESMAG_U_MAGNITUDE_NEW_SESSION: the between-session term was not estimated. */"])
            text = text.replace(_C_NO_U, "\n".join(c_u))
            text = f"/* {note} */\n" + (f"/* {r_line} */\n" if r_line else "") + text
        else:
            text = f"# {note}\n" + (f"# {r_line}\n" if r_line else "") + f"# {u_line}.\n" + text
        out[fmt] = text
    return out
