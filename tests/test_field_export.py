"""Firmware exports of a field (magnitude-only) calibration in the symmetric frame (app/field_export.py).

A magnitude fit leaves the frame's rotation free: S = R P (polar), |S u + O| = |P u + R^T O|. The exports rotate
the gauge-frame fit by R^T so that S is symmetric and PX4's / ArduPilot's symmetric soft-iron matrix can hold it.
The PX4 and ArduPilot files are read back and applied here by the firmware formulas (docs/export.md), written
out independently of bayesmag's own ``apply_px4`` / ``apply_ardupilot``.
"""

import json

import numpy as np
import pandas as pd
import pytest

import bayesmag
from bayesmag._src.app.config import load_config
from bayesmag._src.app.field_export import FieldCalibration, field_export_texts
from bayesmag._src.core.data import CalibrationData
from bayesmag._src.core.field import FieldFit, FieldModel
from bayesmag._src.core.measurement import Constant, Scalar, Vector
from bayesmag.simulate import simulate_field

FIELD = 50.0
#: the PX4 / ArduPilot |B| RMSE may exceed the full model's by at most this fraction (constant temperature: they
#: hold the model exactly in the symmetric frame; in the gauge frame they were 3.6x the full model's)
REL_TOL = 0.05


def _read_parm(text):
    return {k: float(v) for k, v in (ln.split(",") for ln in text.splitlines() if ln.strip() and ln[0] != "#")}


def _read_params(text):
    return {f[2]: float(f[3]) for f in (ln.split("\t") for ln in text.splitlines() if ln.strip() and ln[0] != "#")}


def _sym(d, diag, off):
    (a, b, c), (x, y, z) = (d[k] for k in diag), (d[k] for k in off)
    return np.array([[a, x, y], [x, b, z], [y, z, c]])


def _ardupilot(p, u):
    """ArduPilot AP_Compass correct_field: mat * (SCALE * (mag + offsets)), milligauss (1 uT = 10 mG)."""
    mat = _sym(p, ("COMPASS_DIA_X", "COMPASS_DIA_Y", "COMPASS_DIA_Z"), ("COMPASS_ODI_X", "COMPASS_ODI_Y", "COMPASS_ODI_Z"))
    ofs = np.array([p["COMPASS_OFS_X"], p["COMPASS_OFS_Y"], p["COMPASS_OFS_Z"]])
    return ((10.0 * u + ofs) * p["COMPASS_SCALE"]) @ mat.T / 10.0


def _px4(p, u, t):
    """PX4: scale * (data - thermal offset(T) - offset), gauss (1 uT = 0.01 G), T clamped to [TMIN, TMAX]."""
    D = _sym(p, ("CAL_MAG0_XSCALE", "CAL_MAG0_YSCALE", "CAL_MAG0_ZSCALE"),
             ("CAL_MAG0_XODIAG", "CAL_MAG0_YODIAG", "CAL_MAG0_ZODIAG"))
    dt = np.clip(t, p["TC_M0_TMIN"], p["TC_M0_TMAX"]) - p["TC_M0_TREF"]
    th = np.stack([sum(p[f"TC_M0_X{k}_{i}"] * dt ** k for k in range(4)) for i in range(3)], 1)
    off = np.array([p["CAL_MAG0_XOFF"], p["CAL_MAG0_YOFF"], p["CAL_MAG0_ZOFF"]])
    return (u / 100.0 - th - off) @ D.T * 100.0


def _rmse_mag(B, truth):
    return float(np.sqrt(np.mean((np.linalg.norm(B, axis=1) - truth) ** 2)))


@pytest.fixture(scope="module", params=["constant", "scalar"])
def run20(request, tmp_path_factory):
    """A hand 'dance' at a constant 20 C (the tester's case), calibrated by ``bayesmag run`` with the constant or
    scalar measurement model; time blocks held out."""
    kind = request.param
    d = tmp_path_factory.mktemp(f"fx_{kind}")
    c = simulate_field("dance", n=2000, sensor_seed=7, seed=5, temperature=(20.0, 20.0), field=FIELD)
    x = c.data
    pd.DataFrame(dict(time=x.time, run=x.run, bx_meas=x.b_meas[:, 0], by_meas=x.b_meas[:, 1], bz_meas=x.b_meas[:, 2],
                      temperature=x.temperature, f_ref=c.f_ref)).to_csv(d / "dance20.csv", index=False)
    meas = 'kind="constant"\nfield=50.0\n' if kind == "constant" else 'kind="scalar"\nscalar_column="f_ref"\n'
    (d / "c.toml").write_text(f'name="c"\n[data]\npath="{d / "dance20.csv"}"\n[measurement]\n{meas}'
                              '[split]\nkind="time_blocks"\ntest_fraction=0.2\nn_blocks=4\n[output]\nfigures=false\n'
                              'progress=false\n')
    res = bayesmag.run_job(load_config(d / "c.toml"), d / "r")
    rows = pd.read_csv(d / "r" / "predictions.csv")["row"].to_numpy()
    truth = np.linalg.norm(x.b_ref, axis=1)[rows]          # the true field magnitude of the held-out rows
    files = {s: (d / "r" / f"calibration{s}").read_text() for s in (".parm", ".params", ".export.json",
                                                                     ".magcal.json", ".h")}
    return {"kind": kind, "res": res, "rows": rows, "truth": truth, "files": files, "u": x.b_meas[rows],
            "t": x.temperature[rows]}


@pytest.mark.extended
def test_px4_ardupilot_magnitude_matches_the_full_model_at_constant_temperature(run20):
    """(a) On the held-out rows, |B| RMSE against the true field: PX4 and ArduPilot (read back from the files and
    applied by the firmware formulas) within REL_TOL of the full model and of magcal (before the symmetric frame:
    0.190 / 0.191 uT against 0.053, constant model)."""
    u, t, truth, f = run20["u"], run20["t"], run20["truth"], run20["files"]
    fit = run20["res"]["stage"].fit
    full = _rmse_mag(fit.calibrate(u, t), truth)
    mc = json.loads(f[".magcal.json"])
    magcal = _rmse_mag((u - np.array(mc["b"])) @ np.array(mc["A"]), truth)
    ardu = _rmse_mag(_ardupilot(_read_parm(f[".parm"]), u), truth)
    px4 = _rmse_mag(_px4(_read_params(f[".params"]), u, t), truth)
    assert full < 0.1 and abs(magcal - full) <= REL_TOL * full
    assert ardu <= (1 + REL_TOL) * min(full, magcal), (run20["kind"], ardu, px4, full, magcal)
    assert px4 <= (1 + REL_TOL) * min(full, magcal), (run20["kind"], ardu, px4, full, magcal)
    # the files say which frame they are in and no longer claim the rotation cannot be held
    for s in (".parm", ".params", ".h"):
        assert "symmetric frame" in f[s] and "Frame rotation R" in f[s] and "|B| is unchanged" in f[s]
        assert "cannot hold its rotation" not in f[s] and "rotation (antisymmetric) part of S" not in f[s]


def test_exported_frame_is_a_rotation_and_symmetric_at_t0(run20):
    """(b) R is orthogonal with det +1, the exported S (at T0) symmetric to 1e-12, every coefficient the gauge fit's
    rotated by the same R^T, and every format in that one frame."""
    f = run20["files"]
    doc = json.loads(f[".export.json"])
    R = np.array(doc["field_frame"]["R"])
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12, rtol=0) and abs(np.linalg.det(R) - 1) < 1e-12
    S, Ks, O, Ko = (np.array(doc[k]) for k in ("S", "Ks", "O", "Ko"))
    assert np.abs(S - S.T).max() < 1e-12 and np.all(np.linalg.eigvalsh(S) > 0)
    Sg, Ksg, Og, Kog, _ = run20["res"]["stage"].fit.matrices()
    for a, g in ((S, Sg), (Ks, Ksg), (O, Og), (Ko, Kog)):
        assert np.allclose(a, R.T @ g, atol=1e-12, rtol=0)
    assert np.allclose(np.array(json.loads(f[".magcal.json"])["field_frame"]["R"]), R, atol=0, rtol=0)
    # magcal's A = M(Tr)^T in the same frame, and at constant temperature ArduPilot's matrix is S itself
    mc = json.loads(f[".magcal.json"])
    tc = mc["temperature_C"] - doc["t0"]
    assert np.allclose(np.array(mc["A"]), (S + Ks * tc).T, atol=1e-12, rtol=0)
    p = _read_parm(f[".parm"])
    D = _sym(p, ("COMPASS_DIA_X", "COMPASS_DIA_Y", "COMPASS_DIA_Z"), ("COMPASS_ODI_X", "COMPASS_ODI_Y", "COMPASS_ODI_Z"))
    assert np.allclose(D, S, atol=1e-6, rtol=0)
    for s in (".parm", ".params", ".h"):
        line = next(ln for ln in f[s].splitlines() if ln.startswith(("# Frame rotation R", "/* Frame rotation R")))
        nums = line.split(":", 1)[1].replace("*/", "").replace(";", " ").split()
        assert np.allclose(np.array(nums, float).reshape(3, 3), R, atol=1e-11, rtol=0)


def _fake_fit(meas, S, Ks, O, Ko, t0):
    model = FieldModel(meas, t0=t0)
    extra = (50.0,) * meas.n_extra
    th = model.pack(S, Ks, O, Ko, extra)
    p = len(th)
    return FieldFit(model, th, np.eye(p), np.zeros(p), np.ones(p), 0.0025, 0.0, 1.0, 100, True, 1, "white", {}, ())


@pytest.mark.parametrize("meas", [Constant(50.0), Scalar(), Constant(None)], ids=["constant", "scalar", "free"])
@pytest.mark.parametrize("negative_det", [False, True])
def test_rotated_model_keeps_every_magnitude(meas, negative_det):
    """(c) |B| of the exported (rotated) thermo-affine model equals the gauge model's to 1e-10 at random readings and
    temperatures from -20 to 80 C (T0 = 25 C), with temperature terms; also where det S < 0 (R stays a rotation,
    S' symmetric with one negative eigenvalue)."""
    rng = np.random.default_rng(3)
    S = np.triu(np.eye(3) + rng.normal(0, 0.05, (3, 3)))
    if negative_det:
        S[2, 2] = -S[2, 2]
    if meas.scale_gauge:
        S[2, 2] = 3.0 - S[0, 0] - S[1, 1]
    Ks, O, Ko = np.triu(rng.normal(0, 2e-3, (3, 3))), rng.normal(0, 10, 3), rng.normal(0, 0.2, 3)
    fit = _fake_fit(meas, S, Ks, O, Ko, t0=25.0)
    u, t = rng.normal(0, 40, (500, 3)), rng.uniform(-20, 80, 500)
    train = CalibrationData(u, t, None, source="random")
    cal = FieldCalibration.from_fit(fit, train)
    R = cal.frame
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12, rtol=0) and abs(np.linalg.det(R) - 1) < 1e-12
    Sp, Ksp, Op, Kop = cal.theta[:, :3], cal.theta[:, 3:6], cal.theta[:, 6], cal.theta[:, 7]
    assert np.abs(Sp - Sp.T).max() < 1e-12
    tc = (t - 25.0)[:, None]
    rotated = u @ Sp.T + tc * (u @ Ksp.T) + Op + tc * Kop
    gauge = fit.calibrate(u, t)
    assert np.allclose(np.linalg.norm(rotated, axis=1), np.linalg.norm(gauge, axis=1), atol=1e-10, rtol=0)
    assert np.allclose(rotated, gauge @ R, atol=1e-10, rtol=0)          # B_export = R^T B_gauge
    # and the json export holds exactly that model
    doc = json.loads(field_export_texts(fit, train, ("json",))["json"])
    assert np.allclose(np.array(doc["S"]), Sp, atol=0, rtol=0) and np.allclose(doc["field_frame"]["R"], R)


def test_symmetric_frame_is_the_polar_decomposition():
    """Where det S > 0, R and S' are scipy's polar decomposition S = R P."""
    import scipy.linalg
    from bayesmag._src.app.field_export import symmetric_frame
    rng = np.random.default_rng(0)
    S = np.triu(np.eye(3) + rng.normal(0, 0.1, (3, 3)))
    R, (Sp, _, _, _) = symmetric_frame(S, np.zeros((3, 3)), np.zeros(3), np.zeros(3))
    U, P = scipy.linalg.polar(S)
    assert np.allclose(R, U, atol=1e-12) and np.allclose(Sp, P, atol=1e-12)


def test_vector_fit_is_exported_in_its_own_frame():
    """A vector reference determines the rotation: no frame change."""
    rng = np.random.default_rng(1)
    S = np.eye(3) + rng.normal(0, 0.05, (3, 3))
    fit = _fake_fit(Vector(), S, np.zeros((3, 3)), rng.normal(0, 5, 3), np.zeros(3), t0=20.0)
    cal = FieldCalibration.from_fit(fit, CalibrationData(rng.normal(0, 40, (50, 3)), np.full(50, 20.0), None))
    assert cal.frame is None and np.allclose(cal.theta[:, :3], S)


@pytest.mark.extended
def test_field_exports_carry_the_magnitude_expanded_uncertainty(run20):
    """The JSON exports' ``expanded_uncertainty`` was null on every field run (a firmware user got coefficients with
    no U): now U of |B| equals metrics.json's field.transfer figures; one run gives no new-session U and says why."""
    import math
    tr = run20["res"]["metrics"]["field"]["transfer"]
    assert tr["method"] == "not_estimated" and tr["U_new_session"] is None       # one run: no between-session term
    for s in (".export.json", ".magcal.json"):
        u = json.loads(run20["files"][s])["expanded_uncertainty"]
        assert u["unit"] == "uT" and u["level"] == 0.95 and math.isclose(u["k"], 1.959964, rel_tol=1e-6)
        assert math.isclose(u["same_session"], tr["U_same_session"], rel_tol=1e-12) and u["new_session"] is None
        assert "not estimated" in u["applies"]
    h = run20["files"][".h"]
    assert "BAYESMAG_U_MAGNITUDE_SAME_SESSION" in h and "No BAYESMAG_U_MAGNITUDE_NEW_SESSION" in h
    assert "not known (the run folder has no metrics.json)" not in h
    for s in (".parm", ".params"):
        assert "Expanded uncertainty U of |B| (uT, coverage 95%" in run20["files"][s]


def test_field_uncertainty_doc_with_a_between_session_term():
    from bayesmag._src.app.field_export import field_uncertainty_doc
    tr = {"method": "leave_one_run_out", "k": 1.96, "U_same_session": 0.1, "U_new_session": 0.3, "warning": None}
    u = field_uncertainty_doc(tr, 0.95)
    assert (u["same_session"], u["new_session"], u["unit"]) == (0.1, 0.3, "uT") and "not estimated" not in u["applies"]
    assert field_uncertainty_doc(tr, 0.95, relative=True)["unit"].startswith("1 (relative")
    assert field_uncertainty_doc(None, 0.95) is None


def test_a_field_run_refused_by_export_lists_only_the_files_it_holds(tmp_path):
    from bayesmag._src.app.artifact import ArtifactError, field_run_error
    (tmp_path / "field_params.json").write_text("{}")
    (tmp_path / "calibration.parm").write_text("")
    with pytest.raises(ArtifactError) as e:
        field_run_error(tmp_path, ArtifactError)
    msg = str(e.value)
    assert "calibration.parm" in msg and "calibration.h" not in msg and "export.json" not in msg and "report.md" not in msg
    (tmp_path / "calibration.parm").unlink()
    with pytest.raises(ArtifactError, match="no exports"):
        field_run_error(tmp_path, ArtifactError)
