r"""Firmware export: a saved calibration as the coefficients other tools and autopilots take.

The physics model (paper eq. 1-2) at temperature :math:`T` is affine in the measured field,

.. math::  B_{\mathrm{cal}} = M(T)\,B + o(T), \quad M = S + K_s (T - T_0), \quad o = O + K_o (T - T_0),

with row ``i`` of ``M`` the gains of output axis ``i``. The targets:

* ``json``: every physics coefficient (S, Ks, O, Ko, T0, extra terms by name), units, the
  training domain and the hard/soft-iron form below. Exact for the physics stage.
* ``c-header``: the thermo-affine coefficients and a C99 ``static inline`` function that applies
  them (double precision). Exact for the thermo-affine model; extra terms are not written.
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
dropped, and :func:`accuracy_loss` measures on the run's training rows how far each exported
form is from the full model (physics + network) and from the reference. Sources for the
firmware formulas are in docs/export.md.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from .jsonio import dumps
from .data import AXES, CalibrationData

__all__ = ["FORMATS", "ExportError", "affine_at", "hard_soft_iron", "fit_symmetric_affine", "px4_params",
           "ardupilot_params", "apply_magcal", "apply_px4", "apply_ardupilot", "exported_prediction",
           "accuracy_loss", "render", "export_run", "thermo_affine_coefficients"]

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
    warnings: tuple[str, ...] = ()


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


def accuracy_loss(ex: Export, train: CalibrationData, full: np.ndarray) -> dict:
    """Per format, on the training rows: RMSE (uT) of the exported form against the full model and the reference."""
    out = {"n_rows": int(train.n), "full_model_vs_reference": _rmse(full, train.b_ref) if train.has_reference else None,
           "formats": {}}
    for fmt in FORMATS:
        pred = exported_prediction(fmt, ex, train.b_meas, train.temperature)
        out["formats"][fmt] = {"vs_full_model": _rmse(pred, full),
                               "vs_reference": _rmse(pred, train.b_ref) if train.has_reference else None}
    return out


def build_export(cal, train: CalibrationData | None = None, *, t_ref: float | None = None) -> Export:
    """Coefficients of every target from a :class:`~bayesmag.Calibration`; least-squares targets need ``train``.

    Without ``train`` (the training rows cannot be reloaded), PX4 and ArduPilot are fitted on a
    grid over the training domain instead and no accuracy is measured.
    """
    from .physics import inputs_from_data
    import jax.numpy as jnp

    coef = thermo_affine_coefficients(cal)
    lo, hi = cal.domain.low, cal.domain.high
    t_range = (float(lo[3]), float(hi[3]))
    warnings: list[str] = []
    if t_ref is None:                    # where most training rows are; the domain's middle without them
        t_ref = float(np.median(train.temperature)) if train is not None else 0.5 * (t_range[0] + t_range[1])
    else:
        t_ref = check_t_ref(t_ref)
        if not t_range[0] <= t_ref <= t_range[1]:
            warnings.append(f"--temperature {t_ref:g} C lies outside the training range [{t_range[0]:.4g}, "
                            f"{t_range[1]:.4g}] C: the exported coefficients there are extrapolation.")
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
    ex = Export(coef, t_ref, t_range, A, b, px4, ap, tuple(dropped_components(cal)), cal.network is not None, None,
                source, tuple(warnings))
    _check_finite(ex)
    if train is not None:
        full = cal.predict(train)["calibrated"] if cal.network is not None else phys
        ex = dataclasses.replace(ex, accuracy=accuracy_loss(ex, train, full))
    return ex


def check_t_ref(t_ref) -> float:
    """A reference temperature (C) to export at: finite, not below absolute zero, at most 1e4 C; else ExportError."""
    try:
        t = float(t_ref)
    except (TypeError, ValueError):
        raise ExportError(f"--temperature {t_ref!r} is not a number; give a temperature in C, e.g. 25.") from None
    if not np.isfinite(t) or not -273.15 <= t <= 1e4:
        raise ExportError(f"--temperature {t_ref!r} is not a usable temperature: it must be finite and within "
                          f"[-273.15, 10000] C (e.g. the sensor's working temperature, 25).")
    return t


def _check_finite(ex: Export) -> None:
    """Never export a non-finite coefficient: name the first one (the calibration is degenerate)."""
    named = {f"coef.{k}": v for k, v in ex.coef.items()}
    named.update({"A": ex.A, "b": ex.b, "t_ref": ex.t_ref})
    named.update({f"px4.{k}": v for k, v in (ex.px4 or {}).items()})
    named.update({f"ardupilot.{k}": v for k, v in (ex.ardupilot or {}).items()})
    for k, v in named.items():
        if not np.isfinite(np.asarray(v, dtype=np.float64)).all():
            raise ExportError(f"the exported coefficient {k} would be non-finite ({np.asarray(v).tolist()}); nothing "
                              f"was written. The calibration is degenerate at this temperature: check it with "
                              f"`bayesmag report`, or export at another --temperature.")


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
    lines = [f"WARNING: {w}" for w in ex.warnings]
    lines.append(f"{fmt} cannot hold: " + ("; ".join(parts) if parts else "nothing of this model (exact)") + ".")
    acc = ex.accuracy
    if acc is None:
        lines.append("Accuracy loss not measured: the training rows could not be reloaded.")
    else:
        f = acc["formats"][fmt]
        fmt3 = lambda d: ", ".join(f"{a} {d[a]:.4g}" for a in AXES)  # noqa: E731
        lines.append(f"On the {acc['n_rows']} training rows, RMSE (uT) vs the full model: {fmt3(f['vs_full_model'])}"
                     + (f"; vs the reference: {fmt3(f['vs_reference'])} (full model: "
                        f"{fmt3(acc['full_model_vs_reference'])})" if f["vs_reference"] else "") + ".")
    return lines


def _json_doc(ex: Export) -> dict:
    c = ex.coef
    return {
        "format": "bayesmag.export", "model": "B_cal[i] = sum_j (S[i][j] + Ks[i][j] (T - t0)) B[j] + O[i] + Ko[i] (T - t0)",
        "units": {"field": "uT", "temperature": "C", "S": "1", "Ks": "1/C", "O": "uT", "Ko": "uT/C", "t0": "C"},
        "t0": c["t0"], "S": c["S"].tolist(), "Ks": c["Ks"].tolist(), "O": c["O"].tolist(), "Ko": c["Ko"].tolist(),
        "hard_soft_iron": {"form": "B_cal = (B - b) A (row vectors)", "temperature": ex.t_ref, "A": ex.A.tolist(),
                           "b": ex.b.tolist()},
        "domain": {"temperature": list(ex.t_range)}, "dropped_components": list(ex.dropped),
        "residual_network_dropped": ex.has_network, "accuracy": ex.accuracy,
    }


def render(fmt: str, ex: Export) -> str:
    """The file text of format ``fmt``."""
    notes = limitations(fmt, ex)
    if fmt == "json":
        return dumps({**_json_doc(ex), "notes": notes}) + "\n"
    if fmt == "magcal":
        return dumps({"form": "B_cal = (B - b) * A  (row vectors, MATLAB magcal convention)", "units": "uT",
                           "temperature_C": ex.t_ref, "A": ex.A.tolist(), "b": ex.b.tolist(), "notes": notes},
                          indent=2) + "\n"
    if fmt == "px4":
        head = ["# PX4 parameters (QGroundControl .params: vehicle-id component-id name value type)",
                "# B_cal = D (B - thermal(T) - CAL_MAG0_OFF), gauss; thermal(T) = sum_k TC_M0_Xk * (T - TC_M0_TREF)^k,",
                "# T clamped to [TC_M0_TMIN, TC_M0_TMAX]. Set TC_M0_ID to your magnetometer's device id.",
                f"# Fitted by least squares on {ex.source}."] + [f"# {n}" for n in notes]
        body = [f"1\t1\t{k}\t{v:.9g}\t{6 if isinstance(v, int) else 9}" for k, v in ex.px4.items()]
        return "\n".join(head + ["1\t1\tTC_M0_ID\t0\t6"] + body) + "\n"
    if fmt == "ardupilot":
        head = ["# ArduPilot compass parameters (.parm): B_cal = [DIA/ODI] * SCALE * (B + OFS), milligauss",
                f"# Fitted by least squares on {ex.source}."] + [f"# {n}" for n in notes]
        return "\n".join(head + [f"{k},{v:.9g}" for k, v in ex.ardupilot.items()]) + "\n"
    if fmt == "c-header":
        c = ex.coef

        def arr(v):
            v = np.asarray(v)
            if v.ndim == 1:
                return "{" + ", ".join(f"{x:.17g}" for x in v) + "}"
            return "{" + ", ".join(arr(r) for r in v) + "}"
        lines = ["/* bayesmag calibration (generated by `bayesmag export --format c-header`).",
                 " * B_cal[i] = sum_j (S[i][j] + KS[i][j] (T - T0)) B[j] + O[i] + KO[i] (T - T0)",
                 " * Units: field uT, temperature C. Valid for T in "
                 f"[{ex.t_range[0]:.6g}, {ex.t_range[1]:.6g}] C (training domain)."]
        lines += [f" * {n}" for n in notes] + [" */",
                  "#ifndef BAYESMAG_CALIBRATION_H", "#define BAYESMAG_CALIBRATION_H", "",
                  f"static const double BAYESMAG_T0 = {c['t0']:.17g};",
                  f"static const double BAYESMAG_TMIN = {ex.t_range[0]:.17g};",
                  f"static const double BAYESMAG_TMAX = {ex.t_range[1]:.17g};",
                  f"static const double BAYESMAG_S[3][3] = {arr(c['S'])};",
                  f"static const double BAYESMAG_KS[3][3] = {arr(c['Ks'])};",
                  f"static const double BAYESMAG_O[3] = {arr(c['O'])};",
                  f"static const double BAYESMAG_KO[3] = {arr(c['Ko'])};", "",
                  "/* Hard/soft-iron form at T = BAYESMAG_TREF: out = (B - b) A, row vectors. */",
                  f"static const double BAYESMAG_TREF = {ex.t_ref:.17g};",
                  f"static const double BAYESMAG_A[3][3] = {arr(ex.A)};",
                  f"static const double BAYESMAG_B[3] = {arr(ex.b)};", "",
                  "static inline void bayesmag_calibrate(const double b[3], double t, double out[3])",
                  "{",
                  "    const double tc = t - BAYESMAG_T0;",
                  "    for (int i = 0; i < 3; ++i) {",
                  "        double acc = BAYESMAG_O[i] + BAYESMAG_KO[i] * tc;",
                  "        for (int j = 0; j < 3; ++j) acc += (BAYESMAG_S[i][j] + BAYESMAG_KS[i][j] * tc) * b[j];",
                  "        out[i] = acc;",
                  "    }",
                  "}", "", "#endif /* BAYESMAG_CALIBRATION_H */"]
        return "\n".join(lines) + "\n"
    raise ExportError(f"export format {fmt!r} is not known; it must be one of {list(FORMATS)}.")


def training_rows(cal) -> CalibrationData:
    """The run's training rows, reloaded through its saved config (data source and split)."""
    from .config import config_from_dict
    from .data import make_split
    from .job import load_data

    raw = {k: v for k, v in cal.config.items() if v is not None}
    cfg = config_from_dict(_drop_none(raw))
    data = load_data(cfg)
    s = cfg.split
    split = make_split(data, kind=s.kind, test_fraction=s.test_fraction, seed=s.seed, test_runs=s.test_runs,
                       n_blocks=s.n_blocks)
    return data.subset(split.train)


def _drop_none(d):
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    return d


def export_run(run_dir: str | Path, fmt: str, out: str | Path | None = None, *, t_ref: float | None = None,
               measure: bool = True) -> tuple[Path, Export]:
    """Write the calibration in ``run_dir`` as format ``fmt``; returns the file and the :class:`Export`."""
    from .artifact import load

    if fmt not in FORMATS:
        raise ExportError(f"export format {fmt!r} is not known; it must be one of {list(FORMATS)}.")
    cal = load(run_dir)
    train = None
    if measure:
        try:
            train = training_rows(cal)
        except Exception as e:  # noqa: BLE001 -- the export is still useful without the accuracy table
            import warnings
            warnings.warn(f"training rows could not be reloaded ({e}); accuracy loss not measured.", stacklevel=2)
    ex = build_export(cal, train, t_ref=t_ref)
    out = Path(out) if out else Path(run_dir) / f"calibration{FORMATS[fmt]}"
    out.write_text(render(fmt, ex))
    _register(Path(run_dir), out)
    return out, ex


def _register(run_dir: Path, path: Path) -> None:
    """List an export written inside a run folder in its marker, so a later run may still replace the folder."""
    import os

    from .outdir import MARKER, marker_status

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
