r"""Firmware export: a saved calibration as the coefficients other tools and autopilots take.

The physics model (paper eq. 1-2) at temperature :math:`T` is affine in the measured field,

.. math::  B_{\mathrm{cal}} = M(T)\,B + o(T), \quad M = S + K_s (T - T_0), \quad o = O + K_o (T - T_0),

with row ``i`` of ``M`` the gains of output axis ``i``. The targets:

* ``json``: every physics coefficient (S, Ks, O, Ko, T0, extra terms by name), units, their
  covariance per axis, the expanded uncertainty U (same session and new session), the training
  domain and the hard/soft-iron form below. Exact for the physics stage.
* ``c-header``: the thermo-affine coefficients and C99 ``static inline`` functions that apply
  them in double and in float precision (a Cortex-M4F has no double FPU), U constants, a domain
  check (training ranges of field, temperature and their rates) and a test vector with a
  self-test. Exact for the thermo-affine model; extra terms are not written.
* ``magcal``: the hard/soft-iron form :math:`B_{\mathrm{cal}} = (B - b)\,A` (row vectors, as
  MATLAB's ``magcal``) at one reference temperature :math:`T_r` (default: the median training
  temperature): :math:`A = M(T_r)^\top`,
  :math:`b = -M(T_r)^{-1} o(T_r)`. Exact at :math:`T_r`; the temperature terms are dropped.
* ``px4``: PX4's ``CAL_MAG0_*`` (symmetric 3x3 scale, offsets, gauss) and ``TC_M0_*`` thermal
  offset polynomial (cubic in :math:`T - T_{\mathrm{ref}}`, reference and range from the
  training domain): :math:`B_{\mathrm{cal}} = D\,(B - c(T))`, :math:`c(T) = c_{\mathrm{cal}} + \sum_k X_k \Delta T^k`.
  A symmetric D cannot hold the rotation part of S and an offset polynomial cannot hold the
  temperature-dependent gain Ks: fitted by least squares to the physics prediction on the
  training rows.
* ``ardupilot``: ``COMPASS_OFS_*``, ``COMPASS_DIA_*``, ``COMPASS_ODI_*`` (milligauss),
  :math:`B_{\mathrm{cal}} = D\,(B + \mathrm{ofs})` with D symmetric and no temperature terms:
  least squares as for PX4.

No target holds the residual network (it is a 4x64 MLP with MC-DropConnect): its correction is
dropped, and :func:`accuracy_loss` measures on the run's held-out (test) rows how far each
exported form is from the full model (physics + network) and from the reference. Sources for the
firmware formulas are in docs/export.md.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from bayesmag._src.core.data import AXES, CalibrationData

__all__ = ["FORMATS", "ExportError", "affine_at", "hard_soft_iron", "fit_symmetric_affine", "px4_params",
           "ardupilot_params", "apply_magcal", "apply_px4", "apply_ardupilot", "exported_prediction",
           "accuracy_loss", "render", "export_run", "thermo_affine_coefficients", "split_rows", "test_vector",
           "c_domain_code"]

#: File suffix per format (never plain ".json": calibration.json is the artifact itself).
FORMATS = {"json": ".export.json", "c-header": ".h", "magcal": ".magcal.json", "px4": ".params", "ardupilot": ".parm"}
UT_PER_GAUSS = 100.0
UT_PER_MILLIGAUSS = 0.1
PX4_POLY_DEGREE = 3


class ExportError(ValueError):
    """The calibration cannot be written in the requested format; the message says why."""


# --------------------------------------------------------------------------- coefficients


def thermo_affine_coefficients(cal) -> dict:
    """``S`` (3, 3), ``Ks`` (3, 3), ``O`` (3,), ``Ko`` (3,), ``t0`` of the base term; Ks, Ko zero without temperature."""
    base = cal.model.terms[0]
    if base.name != "thermo_affine":
        raise ExportError(f"the calibration's first term is {base.name!r}, not the thermo-affine base model; "
                          "only models built on it can be exported.")
    k = len(base.param_names())
    th = np.asarray(cal.theta, dtype=np.float64)[:, :k]
    if base.temperature:
        return {"S": th[:, 0:3], "Ks": th[:, 3:6], "O": th[:, 6], "Ko": th[:, 7], "t0": float(base.t0)}
    return {"S": th[:, 0:3], "Ks": np.zeros((3, 3)), "O": th[:, 3], "Ko": np.zeros(3), "t0": float(base.t0)}


def dropped_components(cal) -> list[str]:
    """Names of physics components beyond the thermo-affine base (no firmware target holds them)."""
    return [c.name for c in cal.model.components[1:]]


def affine_at(coef: dict, temperature: float) -> tuple[np.ndarray, np.ndarray]:
    """``M(T)`` (3, 3) and ``o(T)`` (3,) of the thermo-affine model: ``B_cal = M B + o``."""
    tc = float(temperature) - coef["t0"]
    return coef["S"] + coef["Ks"] * tc, coef["O"] + coef["Ko"] * tc


def hard_soft_iron(M: np.ndarray, o: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Soft-iron matrix ``A`` and hard-iron offset ``b`` with ``(B - b) A == M B + o`` for row vectors B."""
    try:
        b = -np.linalg.solve(M, o)
    except np.linalg.LinAlgError:
        raise ExportError(f"the gain matrix M = {M.tolist()} is singular: no hard-iron offset exists.") from None
    return M.T.copy(), b


def fit_symmetric_affine(b_meas: np.ndarray, y: np.ndarray, t_poly: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    r"""Least squares ``y ≈ D B - e(T)`` with D symmetric (3, 3) and ``e = t_poly @ E`` (E: (k, 3)).

    ``t_poly`` (n, k) are the offset's regressors (a column of ones for a constant offset,
    powers of :math:`\Delta T` for PX4's polynomial). All three output axes are one stacked
    linear problem because D couples them. Returns ``(D, E)``.
    """
    b_meas = np.asarray(b_meas, np.float64)
    y = np.asarray(y, np.float64)
    n = b_meas.shape[0]
    t_poly = np.ones((n, 1)) if t_poly is None else np.asarray(t_poly, np.float64)
    k = t_poly.shape[1]
    pairs = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]         # d11 d22 d33 d12 d13 d23
    X = np.zeros((3 * n, 6 + 3 * k))
    for col, (i, j) in enumerate(pairs):
        X[i * n:(i + 1) * n, col] += b_meas[:, j]
        if i != j:
            X[j * n:(j + 1) * n, col] += b_meas[:, i]
    for i in range(3):
        X[i * n:(i + 1) * n, 6 + i * k:6 + (i + 1) * k] = -t_poly
    sol, *_ = np.linalg.lstsq(X, y.T.reshape(-1), rcond=None)
    D = np.zeros((3, 3))
    for v, (i, j) in zip(sol[:6], pairs):
        D[i, j] = D[j, i] = v
    E = sol[6:].reshape(3, k).T
    return D, E


def _px4_dt(temperature, tref, tmin, tmax):
    return np.clip(np.asarray(temperature, np.float64), tmin, tmax) - tref


def px4_params(b_meas, temperature, y, *, tref: float, tmin: float, tmax: float) -> dict:
    """PX4 ``CAL_MAG0_*`` and ``TC_M0_*`` values (gauss) fitted to ``y`` (uT) from inputs in uT."""
    dt = _px4_dt(temperature, tref, tmin, tmax)
    poly = np.column_stack([dt**k for k in range(PX4_POLY_DEGREE + 1)])
    D, E = fit_symmetric_affine(b_meas, y, poly)
    C = np.linalg.solve(D, E.T).T / UT_PER_GAUSS                      # c_k = D^-1 e_k, in gauss
    p = {"CAL_MAG0_XOFF": C[0, 0], "CAL_MAG0_YOFF": C[0, 1], "CAL_MAG0_ZOFF": C[0, 2],
         "CAL_MAG0_XSCALE": D[0, 0], "CAL_MAG0_YSCALE": D[1, 1], "CAL_MAG0_ZSCALE": D[2, 2],
         "CAL_MAG0_XODIAG": D[0, 1], "CAL_MAG0_YODIAG": D[0, 2], "CAL_MAG0_ZODIAG": D[1, 2],
         "TC_M_ENABLE": 1, "TC_M0_TREF": tref, "TC_M0_TMIN": tmin, "TC_M0_TMAX": tmax}
    for k in range(PX4_POLY_DEGREE + 1):
        for a in range(3):
            p[f"TC_M0_X{k}_{a}"] = 0.0 if k == 0 else C[k, a]        # the constant part is the CAL offset
    return {key: float(v) if not isinstance(v, int) else v for key, v in p.items()}


def apply_px4(p: dict, b_meas, temperature) -> np.ndarray:
    """PX4's correction ``D (B - thermal(T) - offset)`` in uT, from the parameters alone (a reference implementation)."""
    g = np.asarray(b_meas, np.float64) / UT_PER_GAUSS
    dt = _px4_dt(temperature, p["TC_M0_TREF"], p["TC_M0_TMIN"], p["TC_M0_TMAX"])
    thermal = np.stack([sum(p[f"TC_M0_X{k}_{a}"] * dt**k for k in range(PX4_POLY_DEGREE + 1)) for a in range(3)], 1)
    off = np.array([p["CAL_MAG0_XOFF"], p["CAL_MAG0_YOFF"], p["CAL_MAG0_ZOFF"]])
    D = np.array([[p["CAL_MAG0_XSCALE"], p["CAL_MAG0_XODIAG"], p["CAL_MAG0_YODIAG"]],
                  [p["CAL_MAG0_XODIAG"], p["CAL_MAG0_YSCALE"], p["CAL_MAG0_ZODIAG"]],
                  [p["CAL_MAG0_YODIAG"], p["CAL_MAG0_ZODIAG"], p["CAL_MAG0_ZSCALE"]]])
    return (g - thermal - off) @ D.T * UT_PER_GAUSS


def ardupilot_params(b_meas, y) -> dict:
    """ArduPilot ``COMPASS_OFS_*`` (milligauss), ``COMPASS_DIA_*``, ``COMPASS_ODI_*`` fitted to ``y`` (uT)."""
    D, E = fit_symmetric_affine(b_meas, y)
    ofs = -np.linalg.solve(D, E[0]) / UT_PER_MILLIGAUSS             # D (B + ofs) = D B - e  =>  ofs = -D^-1 e
    return {"COMPASS_OFS_X": ofs[0], "COMPASS_OFS_Y": ofs[1], "COMPASS_OFS_Z": ofs[2],
            "COMPASS_DIA_X": D[0, 0], "COMPASS_DIA_Y": D[1, 1], "COMPASS_DIA_Z": D[2, 2],
            "COMPASS_ODI_X": D[0, 1], "COMPASS_ODI_Y": D[0, 2], "COMPASS_ODI_Z": D[1, 2],
            "COMPASS_SCALE": 1.0}


def apply_ardupilot(p: dict, b_meas) -> np.ndarray:
    """ArduPilot's ``correct_field``: ``mat * SCALE * (mag + offsets)`` in uT, from the parameters alone."""
    mg = np.asarray(b_meas, np.float64) / UT_PER_MILLIGAUSS
    ofs = np.array([p["COMPASS_OFS_X"], p["COMPASS_OFS_Y"], p["COMPASS_OFS_Z"]])
    mat = np.array([[p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
                    [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
                    [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]]])
    return ((mg + ofs) * p["COMPASS_SCALE"]) @ mat.T * UT_PER_MILLIGAUSS


def apply_magcal(A: np.ndarray, b: np.ndarray, b_meas) -> np.ndarray:
    """``(B - b) A`` for row vectors B (uT)."""
    return (np.asarray(b_meas, np.float64) - np.asarray(b)) @ np.asarray(A)


def apply_thermo_affine(coef: dict, b_meas, temperature) -> np.ndarray:
    """The thermo-affine base model alone (what ``json`` and ``c-header`` hold)."""
    b = np.asarray(b_meas, np.float64)
    tc = np.asarray(temperature, np.float64)[:, None] - coef["t0"]
    return b @ coef["S"].T + tc * (b @ coef["Ks"].T) + coef["O"] + tc * coef["Ko"]


# --------------------------------------------------------------------------- one export


@dataclasses.dataclass(frozen=True)
class Export:
    """Everything the writers need: coefficients of every target and where they came from."""

    coef: dict
    t_ref: float
    t_range: tuple[float, float]
    A: np.ndarray
    b: np.ndarray
    px4: dict | None
    ardupilot: dict | None
    dropped: tuple[str, ...]
    has_network: bool
    accuracy: dict | None
    source: str
    param_names: tuple[str, ...] = ()       # the thermo-affine parameters of one axis, in cov order
    cov: np.ndarray | None = None           # (3, k, k) their covariance per output axis
    uncertainty: dict | None = None         # report.expanded_uncertainties of the run (None: not known)
    domain: object = None                   # the training Domain (ranges of field, temperature, rates)


def exported_prediction(fmt: str, ex: Export, b_meas, temperature) -> np.ndarray:
    """What the firmware/tool computes from the exported coefficients (uT)."""
    if fmt in ("json", "c-header"):
        return apply_thermo_affine(ex.coef, b_meas, temperature)
    if fmt == "magcal":
        return apply_magcal(ex.A, ex.b, b_meas)
    if fmt == "px4":
        return apply_px4(ex.px4, b_meas, temperature)
    if fmt == "ardupilot":
        return apply_ardupilot(ex.ardupilot, b_meas)
    raise ExportError(f"export format {fmt!r} is not known; it must be one of {list(FORMATS)}.")


def _rmse(a, b) -> dict:
    r = np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2, axis=0))
    return {ax: float(v) for ax, v in zip(AXES, r)}


def accuracy_loss(ex: Export, rows: CalibrationData, full: np.ndarray, *, which: str = "held-out (test) rows") -> dict:
    """Per format, on ``rows`` (the run's held-out rows): RMSE (uT) of the exported form against the full
    model's prediction ``full`` of those rows and against their reference."""
    out = {"n_rows": int(rows.n), "rows": which,
           "full_model_vs_reference": _rmse(full, rows.b_ref) if rows.has_reference else None, "formats": {}}
    for fmt in FORMATS:
        pred = exported_prediction(fmt, ex, rows.b_meas, rows.temperature)
        out["formats"][fmt] = {"vs_full_model": _rmse(pred, full),
                               "vs_reference": _rmse(pred, rows.b_ref) if rows.has_reference else None}
    return out


def build_export(cal, train: CalibrationData | None = None, *, t_ref: float | None = None,
                 held_out: CalibrationData | None = None, uncertainty: dict | None = None) -> Export:
    """Coefficients of every target from a :class:`~bayesmag.Calibration`; least-squares targets need ``train``.

    PX4 and ArduPilot are fitted on ``train``; the accuracy lost is measured on ``held_out`` (the
    run's test rows; the training rows, said so, when there are none). Without ``train`` (the rows
    cannot be reloaded), the fits use a grid over the training domain and no accuracy is measured.
    ``uncertainty``: :func:`~bayesmag._src.app.report.expanded_uncertainties` of the run, for the
    U constants of ``json`` and ``c-header``.
    """
    from bayesmag._src.core.physics import inputs_from_data
    import jax.numpy as jnp

    coef = thermo_affine_coefficients(cal)
    lo, hi = cal.domain.low, cal.domain.high
    t_range = (float(lo[3]), float(hi[3]))
    if t_ref is None:                    # where most training rows are; the domain's middle without them
        t_ref = float(np.median(train.temperature)) if train is not None else 0.5 * (t_range[0] + t_range[1])
    t_ref = float(t_ref)
    A, b = hard_soft_iron(*affine_at(coef, t_ref))
    rows, source = train, "training rows"
    if rows is None:                     # a 9^4 grid over the domain box stands in for the data
        g = [np.linspace(lo[j], hi[j], 9) for j in range(4)]
        mesh = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 4)
        rows = CalibrationData(mesh[:, :3], mesh[:, 3], None, source="domain grid")
        source = "a 9x9x9x9 grid over the training domain (training rows unavailable)"
    phys = np.asarray(cal.model.predict_all(jnp.asarray(cal.theta), inputs_from_data(rows)))
    px4 = px4_params(rows.b_meas, rows.temperature, phys, tref=t_ref, tmin=t_range[0], tmax=t_range[1])
    ap = ardupilot_params(rows.b_meas, phys)
    k = len(cal.model.terms[0].param_names())
    names = tuple(cal.model.param_names[:k])
    cal_cov = getattr(cal, "cov", None)      # a field calibration has its covariance in another parametrisation
    cov = None if cal_cov is None else np.asarray(cal_cov, np.float64)[:, :k, :k]
    ex = Export(coef, t_ref, t_range, A, b, px4, ap, tuple(dropped_components(cal)), cal.network is not None, None,
                source, names, cov, uncertainty, cal.domain)
    if train is not None:
        scored, which = ((held_out, "held-out (test) rows") if held_out is not None and held_out.n > 0
                         else (train, "training rows (the run has no held-out rows)"))
        full = (cal.predict(scored)["calibrated"] if cal.network is not None else
                np.asarray(cal.model.predict_all(jnp.asarray(cal.theta), inputs_from_data(scored))))
        ex = dataclasses.replace(ex, accuracy=accuracy_loss(ex, scored, full, which=which))
    return ex


def test_vector(ex: Export) -> tuple[np.ndarray, np.ndarray]:
    """Inputs ``(4, 4)`` (Bx, By, Bz in uT, T in C) inside the training domain and the thermo-affine output
    ``(4, 3)`` for them: the test vector of the C header."""
    lo, hi = np.asarray(ex.domain.low, np.float64), np.asarray(ex.domain.high, np.float64)
    frac = np.array([[0.5, 0.5, 0.5, 0.5], [0.2, 0.7, 0.4, 0.1], [0.9, 0.1, 0.8, 0.9], [0.35, 0.95, 0.05, 0.6]])
    x = lo + frac * (hi - lo)
    return x, apply_thermo_affine(ex.coef, x[:, :3], x[:, 3])


# --------------------------------------------------------------------------- writers


_CANNOT_HOLD = {
    "json": (),
    "c-header": (),
    "magcal": ("the temperature terms (Ks, Ko: evaluated at T_ref)",),
    "px4": ("the rotation (antisymmetric) part of S",
            "the temperature-dependent gain Ks (approximated by the offset polynomial)"),
    "ardupilot": ("the rotation (antisymmetric) part of S", "all temperature terms"),
}


def limitations(fmt: str, ex: Export) -> list[str]:
    """Plain statements of what the target cannot hold and the accuracy that costs."""
    parts = list(_CANNOT_HOLD[fmt]) + [f"physics extra terms {list(ex.dropped)}"] * bool(ex.dropped) \
        + ["the residual network"] * ex.has_network
    lines = [f"{fmt} cannot hold: " + ("; ".join(parts) if parts else "nothing of this model (exact)") + "."]
    acc = ex.accuracy
    if acc is None:
        lines.append("Accuracy loss not measured: the run's rows could not be reloaded.")
    else:
        f = acc["formats"][fmt]
        fmt3 = lambda d: ", ".join(f"{a} {d[a]:.4g}" for a in AXES)  # noqa: E731
        lines.append(f"On the {acc['n_rows']} {acc.get('rows', 'training rows')}, RMSE (uT) vs the full model: "
                     f"{fmt3(f['vs_full_model'])}"
                     + (f"; vs the reference: {fmt3(f['vs_reference'])} (full model: "
                        f"{fmt3(acc['full_model_vs_reference'])})" if f["vs_reference"] else "") + ".")
    return lines


def _u_doc(ex: Export) -> dict | None:
    u = ex.uncertainty
    if not u:
        return None
    return {"unit": "uT", "level": u["level"], "k_same_session": {a: u["same_session"][a]["k"] for a in AXES},
            "same_session": {a: u["same_session"][a]["U"] for a in AXES},
            "new_session": {a: u["new_session"][a]["U"] for a in AXES},
            "applies": "same_session: rows of the recording session the calibration was fitted on; new_session: "
                       "any later recording (in the field). Inside the training domain only."}


def _json_doc(ex: Export) -> dict:
    c = ex.coef
    d = ex.domain
    return {
        "format": "bayesmag.export", "model": "B_cal[i] = sum_j (S[i][j] + Ks[i][j] (T - t0)) B[j] + O[i] + Ko[i] (T - t0)",
        "units": {"field": "uT", "temperature": "C", "S": "1", "Ks": "1/C", "O": "uT", "Ko": "uT/C", "t0": "C"},
        "t0": c["t0"], "S": c["S"].tolist(), "Ks": c["Ks"].tolist(), "O": c["O"].tolist(), "Ko": c["Ko"].tolist(),
        "covariance": {"parameters": list(ex.param_names),
                       "per_axis": {a: ex.cov[i].tolist() for i, a in enumerate(AXES)} if ex.cov is not None else None,
                       "note": "covariance of one output axis's parameters (row i of S and Ks, O[i], Ko[i]) in the "
                               "order of 'parameters', in their units; the axes are fitted independently"},
        "expanded_uncertainty": _u_doc(ex),
        "hard_soft_iron": {"form": "B_cal = (B - b) A (row vectors)", "temperature": ex.t_ref, "A": ex.A.tolist(),
                           "b": ex.b.tolist()},
        "domain": {"temperature": list(ex.t_range),
                   **({"field_low": list(d.low[:3]), "field_high": list(d.high[:3]),
                       "rate_high": dict(zip(("dbx_dt", "dby_dt", "dbz_dt", "dT_dt"), d.rate_high))
                       if d.rate_high is not None else None} if d is not None else {})},
        "dropped_components": list(ex.dropped),
        "residual_network_dropped": ex.has_network, "accuracy": ex.accuracy,
    }


_PX4_HEAD = [
    "# BEFORE LOADING, set the device-specific parameters (placeholders, commented out below so that nothing wrong",
    "# is loaded): PX4 applies CAL_MAG0_* (and TC_M0_*) only to the magnetometer whose device id equals CAL_MAG0_ID",
    "# (TC_M0_ID). Read the id of the sensor you calibrated (QGroundControl > Parameters: the current CAL_MAG0_ID, or",
    "# `listener sensor_mag` on the console: device_id), put it in place of <DEVICE_ID> and remove the leading '# '.",
    "# 1\t1\tCAL_MAG0_ID\t<DEVICE_ID>\t6",
    "# 1\t1\tTC_M0_ID\t<DEVICE_ID>\t6",
    "# CAL_MAG0_ROT: rotation of the sensor to the vehicle frame; PX4 applies it after this calibration, which is in",
    "# the sensor's own axes (those of bx_meas, by_meas, bz_meas). Keep the vehicle's value (-1 = internal sensor,",
    "# board rotation), or set the rotation enum of an external sensor's mounting:",
    "# 1\t1\tCAL_MAG0_ROT\t<ROTATION>\t6",
    "# CAL_MAG0_PRIO: priority among magnetometers (0 disabled, 1 min, 25 low, 50 default, 75 high, 100 max):",
    "# 1\t1\tCAL_MAG0_PRIO\t50\t6",
]

_ARDUPILOT_HEAD = [
    "# Frame: ArduPilot applies OFS/DIA/ODI in the body frame, after it has rotated the driver's reading by the",
    "# driver's orientation, AHRS_ORIENTATION (internal compass) or COMPASS_ORIENT (external compass)",
    "# (AP_Compass_Backend: rotate_field, then correct_field). So this calibration holds only if the field it was",
    "# fitted on (bx_meas, by_meas, bz_meas, uT) is that rotated reading: the driver's raw body-frame field in",
    "# milligauss must equal bx_meas x 10 (1 uT = 10 mG). Set COMPASS_ORIENT before recording, or rotate a",
    "# sensor-frame recording into the body frame before `bayesmag run`.",
    "# COMPASS_DEV_ID: ArduPilot applies these to the compass whose id equals COMPASS_DEV_ID; check that it is the",
    "# sensor you calibrated (the vehicle's COMPASS_DEV_ID, or the id in MAVLink MAG_CAL_REPORT / the boot log);",
    "# only if not, put its id in place of <DEVICE_ID> and remove the leading '# ':",
    "# COMPASS_DEV_ID,<DEVICE_ID>",
]


def _c_num(x: float, spec: str) -> str:
    t = format(float(x), spec)
    return t if any(ch in t for ch in ".en") else t + ".0"     # a float literal needs a point for the f suffix


def _c_arr(v, suffix: str = "", spec: str = ".17g") -> str:
    v = np.asarray(v)
    if v.ndim == 1:
        return "{" + ", ".join(_c_num(x, spec) + suffix for x in v) + "}"
    return "{" + ", ".join(_c_arr(r, suffix, spec) for r in v) + "}"


def c_domain_code(ex: Export) -> list[str]:
    """C lines of the domain check: constants and ``bayesmag_in_domain`` (bit codes as ``apply``'s reason column)."""
    d = ex.domain
    lines = ["/* Training domain (with the job's margin). bayesmag_in_domain returns 0 inside, else the sum of",
             " * 1 (field out of range), 2 (temperature), 4 (field rate), 8 (temperature rate): the codes of the",
             " * in_domain_reason column of `bayesmag apply`. Pass db_dt = NULL to skip the rate checks; rates are",
             " * |d/dt| of the measured inputs in uT/s and C/s (e.g. the larger difference quotient to the two time",
             " * neighbours). Outside the domain the output is extrapolation and U does not hold. */",
             f"static const double BAYESMAG_B_MIN[3] = {_c_arr(d.low[:3])};",
             f"static const double BAYESMAG_B_MAX[3] = {_c_arr(d.high[:3])};"]
    has_rates = d.rate_high is not None
    if has_rates:
        lines += [f"static const double BAYESMAG_DB_DT_MAX[3] = {_c_arr(d.rate_high[:3])};",
                  f"static const double BAYESMAG_DT_DT_MAX = {_c_num(d.rate_high[3], '.17g')};"]
    lines += ["",
              "static inline int bayesmag_in_domain(const double b[3], double t, const double db_dt[3], double dt_dt)",
              "{",
              "    int code = 0;",
              "    for (int i = 0; i < 3; ++i)",
              "        if (!(b[i] >= BAYESMAG_B_MIN[i] && b[i] <= BAYESMAG_B_MAX[i])) code |= 1;",
              "    if (!(t >= BAYESMAG_TMIN && t <= BAYESMAG_TMAX)) code |= 2;"]
    if has_rates:
        lines += ["    if (db_dt != NULL) {",
                  "        for (int i = 0; i < 3; ++i)",
                  "            if (!(db_dt[i] <= BAYESMAG_DB_DT_MAX[i])) code |= 4;",
                  "        if (!(dt_dt <= BAYESMAG_DT_DT_MAX)) code |= 8;",
                  "    }"]
    else:
        lines += ["    (void)db_dt; (void)dt_dt;             /* no rate limits in this calibration */"]
    return lines + ["    return code;", "}"]


#: Tolerances of the C header's self-test (uT): double arithmetic, and float (24-bit mantissa: ~1e-5 uT
#: rounding on a 100 uT field, far below any sensor's noise).
TEST_TOL, TEST_TOL_F = 1e-9, 1e-3


def _c_header(ex: Export, notes: list[str]) -> str:
    c = ex.coef
    x_in, y_out = test_vector(ex)
    u = ex.uncertainty
    lines = ["/* bayesmag calibration (generated by `bayesmag export --format c-header`).",
             " * B_cal[i] = sum_j (S[i][j] + KS[i][j] (T - T0)) B[j] + O[i] + KO[i] (T - T0)",
             " * Units: field uT, temperature C. Valid inside the training domain: check it with bayesmag_in_domain.",
             " * bayesmag_calibrate (double) and bayesmag_calibrate_f (float: no double arithmetic, for an FPU",
             " * without double precision such as the Cortex-M4F); bayesmag_self_test runs the test vector."]
    lines += [f" * {n}" for n in notes] + [" */",
              "#ifndef BAYESMAG_CALIBRATION_H", "#define BAYESMAG_CALIBRATION_H", "", "#include <stddef.h>", "",
              f"static const double BAYESMAG_T0 = {_c_num(c['t0'], '.17g')};",
              f"static const double BAYESMAG_TMIN = {_c_num(ex.t_range[0], '.17g')};",
              f"static const double BAYESMAG_TMAX = {_c_num(ex.t_range[1], '.17g')};",
              f"static const double BAYESMAG_S[3][3] = {_c_arr(c['S'])};",
              f"static const double BAYESMAG_KS[3][3] = {_c_arr(c['Ks'])};",
              f"static const double BAYESMAG_O[3] = {_c_arr(c['O'])};",
              f"static const double BAYESMAG_KO[3] = {_c_arr(c['Ko'])};", "",
              "/* The same coefficients in single precision. */",
              f"static const float BAYESMAG_T0_F = {_c_num(c['t0'], '.9g')}f;",
              f"static const float BAYESMAG_S_F[3][3] = {_c_arr(c['S'], 'f', '.9g')};",
              f"static const float BAYESMAG_KS_F[3][3] = {_c_arr(c['Ks'], 'f', '.9g')};",
              f"static const float BAYESMAG_O_F[3] = {_c_arr(c['O'], 'f', '.9g')};",
              f"static const float BAYESMAG_KO_F[3] = {_c_arr(c['Ko'], 'f', '.9g')};", ""]
    if u:
        lines += [f"/* Expanded uncertainty U (uT, coverage {u['level']:.0%}, per axis x, y, z): SAME_SESSION for rows of",
                  " * the recording session the calibration was fitted on, NEW_SESSION for any later recording",
                  " * (in the field). Inside the training domain only. */",
                  f"static const double BAYESMAG_LEVEL = {_c_num(u['level'], '.6g')};",
                  "static const double BAYESMAG_U_SAME_SESSION[3] = "
                  f"{_c_arr([u['same_session'][a]['U'] for a in AXES], '', '.6g')};",
                  "static const double BAYESMAG_U_NEW_SESSION[3] = "
                  f"{_c_arr([u['new_session'][a]['U'] for a in AXES], '', '.6g')};", ""]
    else:
        lines += ["/* Expanded uncertainty U: not known (the run folder has no metrics.json). */", ""]
    lines += ["/* Hard/soft-iron form at T = BAYESMAG_TREF: out = (B - b) A, row vectors. */",
              f"static const double BAYESMAG_TREF = {_c_num(ex.t_ref, '.17g')};",
              f"static const double BAYESMAG_A[3][3] = {_c_arr(ex.A)};",
              f"static const double BAYESMAG_B[3] = {_c_arr(ex.b)};", ""]
    lines += c_domain_code(ex) + [""]
    lines += ["static inline void bayesmag_calibrate(const double b[3], double t, double out[3])",
              "{",
              "    const double tc = t - BAYESMAG_T0;",
              "    for (int i = 0; i < 3; ++i) {",
              "        double acc = BAYESMAG_O[i] + BAYESMAG_KO[i] * tc;",
              "        for (int j = 0; j < 3; ++j) acc += (BAYESMAG_S[i][j] + BAYESMAG_KS[i][j] * tc) * b[j];",
              "        out[i] = acc;",
              "    }",
              "}", "",
              "static inline void bayesmag_calibrate_f(const float b[3], float t, float out[3])",
              "{",
              "    const float tc = t - BAYESMAG_T0_F;",
              "    for (int i = 0; i < 3; ++i) {",
              "        float acc = BAYESMAG_O_F[i] + BAYESMAG_KO_F[i] * tc;",
              "        for (int j = 0; j < 3; ++j) acc += (BAYESMAG_S_F[i][j] + BAYESMAG_KS_F[i][j] * tc) * b[j];",
              "        out[i] = acc;",
              "    }",
              "}", "",
              "/* Test vector: inputs (Bx, By, Bz in uT, T in C) inside the domain and the expected output (uT). */",
              f"#define BAYESMAG_N_TEST {len(x_in)}",
              f"static const double BAYESMAG_TEST_IN[BAYESMAG_N_TEST][4] = {_c_arr(x_in)};",
              f"static const double BAYESMAG_TEST_OUT[BAYESMAG_N_TEST][3] = {_c_arr(y_out)};",
              f"#define BAYESMAG_TEST_TOL {TEST_TOL:g}     /* uT, double precision */",
              f"#define BAYESMAG_TEST_TOL_F {TEST_TOL_F:g}f     /* uT, float precision */", "",
              "/* 0 when both variants reproduce the test vector and its rows are inside the domain; else the",
              " * number of failed checks. */",
              "static inline int bayesmag_self_test(void)",
              "{",
              "    int fails = 0;",
              "    for (int k = 0; k < BAYESMAG_N_TEST; ++k) {",
              "        const double *x = BAYESMAG_TEST_IN[k];",
              "        const float xf[3] = {(float)x[0], (float)x[1], (float)x[2]};",
              "        double out[3];",
              "        float outf[3];",
              "        bayesmag_calibrate(x, x[3], out);",
              "        bayesmag_calibrate_f(xf, (float)x[3], outf);",
              "        if (bayesmag_in_domain(x, x[3], NULL, 0.0) != 0) ++fails;",
              "        for (int i = 0; i < 3; ++i) {",
              "            const double d = out[i] - BAYESMAG_TEST_OUT[k][i];",
              "            const float df = outf[i] - (float)BAYESMAG_TEST_OUT[k][i];",
              "            if (!(d <= BAYESMAG_TEST_TOL && -d <= BAYESMAG_TEST_TOL)) ++fails;",
              "            if (!(df <= BAYESMAG_TEST_TOL_F && -df <= BAYESMAG_TEST_TOL_F)) ++fails;",
              "        }",
              "    }",
              "    return fails;",
              "}", "", "#endif /* BAYESMAG_CALIBRATION_H */"]
    return "\n".join(lines) + "\n"


def render(fmt: str, ex: Export) -> str:
    """The file text of format ``fmt``."""
    notes = limitations(fmt, ex)
    if fmt == "json":
        return json.dumps({**_json_doc(ex), "notes": notes}, indent=2) + "\n"
    if fmt == "magcal":
        return json.dumps({"form": "B_cal = (B - b) * A  (row vectors, MATLAB magcal convention)", "units": "uT",
                           "temperature_C": ex.t_ref, "A": ex.A.tolist(), "b": ex.b.tolist(), "notes": notes},
                          indent=2) + "\n"
    if fmt == "px4":
        head = ["# PX4 parameters (QGroundControl .params: vehicle-id component-id name value type)",
                "# B_cal = D (B - thermal(T) - CAL_MAG0_OFF), gauss; thermal(T) = sum_k TC_M0_Xk * (T - TC_M0_TREF)^k,",
                "# T clamped to [TC_M0_TMIN, TC_M0_TMAX].", f"# Fitted by least squares on {ex.source}."]
        head += _PX4_HEAD + [f"# {n}" for n in notes]
        body = [f"1\t1\t{k}\t{v:.9g}\t{6 if isinstance(v, int) else 9}" for k, v in ex.px4.items()]
        return "\n".join(head + body) + "\n"
    if fmt == "ardupilot":
        head = ["# ArduPilot compass parameters (.parm): B_cal = [DIA/ODI] * SCALE * (B + OFS), milligauss",
                f"# Fitted by least squares on {ex.source}."] + _ARDUPILOT_HEAD + [f"# {n}" for n in notes]
        return "\n".join(head + [f"{k},{v:.9g}" for k, v in ex.ardupilot.items()]) + "\n"
    if fmt == "c-header":
        return _c_header(ex, notes)
    raise ExportError(f"export format {fmt!r} is not known; it must be one of {list(FORMATS)}.")


def split_rows(cal) -> tuple[CalibrationData, CalibrationData]:
    """The run's training and held-out (test) rows, reloaded through its saved config (data source and split)."""
    from bayesmag._src.app.config import config_from_dict
    from bayesmag._src.core.data import make_split
    from bayesmag._src.app.job import load_data

    if "sensor_id" in cal.config:                  # a sensor folder of `bayesmag fleet`
        from bayesmag._src.app.fleet import sensor_split_rows
        return sensor_split_rows(cal.config)
    raw = {k: v for k, v in cal.config.items() if v is not None}
    cfg = config_from_dict(_drop_none(raw))
    data = load_data(cfg)
    s = cfg.split
    split = make_split(data, kind=s.kind, test_fraction=s.test_fraction, seed=s.seed, test_runs=s.test_runs,
                       n_blocks=s.n_blocks)
    return data.subset(split.train), data.subset(split.test)


def training_rows(cal) -> CalibrationData:
    """The run's training rows, reloaded through its saved config (data source and split)."""
    return split_rows(cal)[0]


def run_uncertainty(run_dir: str | Path) -> dict | None:
    """The run's expanded uncertainties (same / new session) from its metrics.json and params.json, or None."""
    from bayesmag._src.app.report import expanded_uncertainties, run_reference_sd
    run_dir = Path(run_dir)
    try:
        m = json.loads((run_dir / "metrics.json").read_text())
        params = json.loads((run_dir / "params.json").read_text())
        return expanded_uncertainties(m, params, run_reference_sd(run_dir))
    except (OSError, ValueError, KeyError):
        return None


def _drop_none(d):
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    return d


def export_run(run_dir: str | Path, fmt: str, out: str | Path | None = None, *, t_ref: float | None = None,
               measure: bool = True) -> tuple[Path, Export]:
    """Write the calibration in ``run_dir`` as format ``fmt``; returns the file and the :class:`Export`."""
    from bayesmag._src.app.artifact import load

    if fmt not in FORMATS:
        raise ExportError(f"export format {fmt!r} is not known; it must be one of {list(FORMATS)}.")
    cal = load(run_dir)
    train = test = None
    if measure:
        try:
            train, test = split_rows(cal)
        except Exception as e:  # noqa: BLE001 -- the export is still useful without the accuracy table
            import warnings
            warnings.warn(f"the run's rows could not be reloaded ({e}); accuracy loss not measured.", stacklevel=2)
    ex = build_export(cal, train, t_ref=t_ref, held_out=test, uncertainty=run_uncertainty(run_dir))
    out = Path(out) if out else Path(run_dir) / f"calibration{FORMATS[fmt]}"
    out.write_text(render(fmt, ex))
    _register(Path(run_dir), out)
    return out, ex


def _register(run_dir: Path, path: Path) -> None:
    """List an export written inside a run folder in its marker, so a later run may still replace the folder."""
    import os

    from bayesmag._src.app.outdir import MARKER, marker_status

    for owner in (run_dir, *Path(run_dir).resolve().parents[:2]):    # a fleet's sensors/<id>: the fleet folder's
        if marker_status(owner) is not None:
            run_dir = Path(owner)
            break
    mark = marker_status(run_dir)
    try:
        rel = path.resolve().relative_to(run_dir.resolve()).as_posix()
    except ValueError:
        return
    if not mark or "files" not in mark or rel in mark["files"]:
        return
    mark["files"] = sorted(set(mark["files"]) | {rel})
    tmp = run_dir / (MARKER + ".tmp")
    tmp.write_text(json.dumps(mark) + "\n")
    os.replace(tmp, run_dir / MARKER)
