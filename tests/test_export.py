"""Firmware export: each target's coefficients, applied by an independent re-implementation of that
target's own formula (written out here from the firmware sources cited in docs/export.md), reproduce
the physics model wherever the target can hold it (to 1e-9), and the CLI reports what is lost."""

import json
import shutil
import subprocess

import jax.numpy as jnp
import numpy as np
import pytest

import bayesmag
from bayesmag import CalibrationData, PhysicsModel, inputs_from_data
from bayesmag._src.app import export as E
from bayesmag._src.app.artifact import Calibration
from bayesmag._src.app.cli import main
from bayesmag._src.app.config import config_from_dict
from bayesmag._src.core.domain import Domain
from helpers import TRUE_THETA

T0 = 22.5


def _cal(theta=TRUE_THETA, t0=T0, extra=()):
    model = PhysicsModel.paper(t0=t0, extra=extra)
    p = model.n_params
    return Calibration(model=model, theta=np.asarray(theta, float), cov=np.tile(np.eye(p) * 1e-8, (3, 1, 1)),
                       sigma_in=np.eye(4) * 1e-4, residual_sd=np.full(3, 0.05),
                       domain=Domain((-60.0, -60.0, -60.0, 5.0), (60.0, 60.0, 60.0, 45.0)))


def _rows(n=400, seed=0, t=None):
    r = np.random.default_rng(seed)
    b = r.uniform(-50, 50, (n, 3))
    temp = r.uniform(5, 45, n) if t is None else np.full(n, float(t))
    return CalibrationData(b, temp, None)


def _physics(cal, rows):
    return np.asarray(cal.model.predict_all(jnp.asarray(cal.theta), inputs_from_data(rows)))


def test_magcal_round_trip_at_reference_temperature():
    cal = _cal()
    ex = E.build_export(cal, None, t_ref=31.0)
    rows = _rows(t=31.0)
    A, b = np.array(ex.A), np.array(ex.b)
    mine = np.array([[sum((row[j] - b[j]) * A[j, i] for j in range(3)) for i in range(3)] for row in rows.b_meas])
    np.testing.assert_allclose(mine, _physics(cal, rows), rtol=0, atol=1e-9)
    # and the algebra: A = M^T, b = -M^-1 o
    M, o = E.affine_at(E.thermo_affine_coefficients(cal), 31.0)
    np.testing.assert_allclose(A.T @ b, -o, atol=1e-12)


def test_default_reference_temperature_is_the_middle_of_the_training_range():
    ex = E.build_export(_cal(), None)
    assert ex.t_ref == pytest.approx(25.0) and ex.t_range == (5.0, 45.0)


def test_json_holds_the_full_thermo_affine_model(tmp_path):
    cal = _cal()
    doc = json.loads(E.render("json", E.build_export(cal, None)))
    rows = _rows()
    S, Ks, O, Ko = (np.array(doc[k]) for k in ("S", "Ks", "O", "Ko"))
    tc = rows.temperature - doc["t0"]
    mine = np.stack([sum((S[i, j] + Ks[i, j] * tc) * rows.b_meas[:, j] for j in range(3)) + O[i] + Ko[i] * tc
                     for i in range(3)], 1)
    np.testing.assert_allclose(mine, _physics(cal, rows), atol=1e-9)
    assert doc["units"]["Ks"] == "1/C" and doc["units"]["Ko"] == "uT/C"


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_c_header_compiles_and_reproduces_the_model(tmp_path):
    cal = _cal()
    (tmp_path / "cal.h").write_text(E.render("c-header", E.build_export(cal, None)))
    rows = _rows(n=20, seed=3)
    lines = "\n".join(f"{{ double b[3] = {{{r[0]:.17g}, {r[1]:.17g}, {r[2]:.17g}}}, o[3]; bayesmag_calibrate(b, {t:.17g}, o); "
                      f'printf("%.17g %.17g %.17g\\n", o[0], o[1], o[2]); }}'
                      for r, t in zip(rows.b_meas, rows.temperature))
    (tmp_path / "main.c").write_text(f'#include <stdio.h>\n#include "cal.h"\nint main(void) {{\n{lines}\nreturn 0; }}\n')
    subprocess.run(["cc", "-std=c99", "-Wall", "-Werror", "-o", str(tmp_path / "m"), str(tmp_path / "main.c")],
                   check=True, cwd=tmp_path)
    out = np.loadtxt(subprocess.run([str(tmp_path / "m")], capture_output=True, text=True, check=True).stdout
                     .splitlines())
    np.testing.assert_allclose(out, _physics(cal, rows), atol=1e-9)


def _symmetric_theta(ko=True):
    """A sensor that PX4/ArduPilot can hold exactly: S symmetric, Ks = 0 (and Ko = 0 for ArduPilot)."""
    S = np.array([[1.05, 0.02, -0.03], [0.02, 0.97, 0.01], [-0.03, 0.01, 1.10]])
    th = np.zeros((3, 8))
    th[:, :3] = S
    th[:, 6] = [3.0, -12.0, 7.5]
    th[:, 7] = [0.04, -0.02, 0.01] if ko else 0.0
    return th


def _px4_firmware(p, b_ut, t):
    """PX4: Correct() = scale * (data - thermal_offset - offset); thermal offset a cubic in clamped T - TREF (gauss)."""
    g = b_ut / 100.0
    scale = np.array([[p["CAL_MAG0_XSCALE"], p["CAL_MAG0_XODIAG"], p["CAL_MAG0_YODIAG"]],
                      [p["CAL_MAG0_XODIAG"], p["CAL_MAG0_YSCALE"], p["CAL_MAG0_ZODIAG"]],
                      [p["CAL_MAG0_YODIAG"], p["CAL_MAG0_ZODIAG"], p["CAL_MAG0_ZSCALE"]]])
    out = []
    for row, temp in zip(g, t):
        dt = min(max(temp, p["TC_M0_TMIN"]), p["TC_M0_TMAX"]) - p["TC_M0_TREF"]
        thermal = [p[f"TC_M0_X0_{a}"] + p[f"TC_M0_X1_{a}"] * dt + p[f"TC_M0_X2_{a}"] * dt**2
                   + p[f"TC_M0_X3_{a}"] * dt**3 for a in range(3)]
        off = [p["CAL_MAG0_XOFF"], p["CAL_MAG0_YOFF"], p["CAL_MAG0_ZOFF"]]
        out.append(scale @ (row - np.array(thermal) - np.array(off)))
    return np.array(out) * 100.0


def _parse_px4(text):
    return {f[2]: (int(f[3]) if f[4] == "6" else float(f[3]))
            for f in (ln.split("\t") for ln in text.splitlines() if ln and not ln.startswith("#"))}


def test_px4_params_are_exact_for_a_model_it_can_hold():
    cal = _cal(_symmetric_theta(ko=True))
    rows = _rows(n=500, seed=4)
    ex = E.build_export(cal, None)
    p = _parse_px4(E.render("px4", ex))
    inside = (rows.temperature >= ex.t_range[0]) & (rows.temperature <= ex.t_range[1])
    np.testing.assert_allclose(_px4_firmware(p, rows.b_meas, rows.temperature)[inside], _physics(cal, rows)[inside],
                               atol=1e-6)                              # the file keeps 9 significant digits
    np.testing.assert_allclose(E.apply_px4(ex.px4, rows.b_meas, rows.temperature), _physics(cal, rows), atol=1e-9)
    assert p["TC_M0_TREF"] == pytest.approx(25.0) and p["TC_M0_TMIN"] == 5.0 and p["TC_M0_TMAX"] == 45.0
    assert p["CAL_MAG0_XSCALE"] == pytest.approx(1.05) and p["CAL_MAG0_XODIAG"] == pytest.approx(0.02)
    # gauss: the offset c = -S^-1 O at TREF, in uT / 100
    c = -np.linalg.solve(_symmetric_theta()[:, :3], E.affine_at(E.thermo_affine_coefficients(cal), 25.0)[1])
    assert p["CAL_MAG0_YOFF"] == pytest.approx(c[1] / 100.0, rel=1e-8)


def test_ardupilot_params_are_exact_for_a_model_it_can_hold():
    cal = _cal(_symmetric_theta(ko=False))
    rows = _rows(n=300, seed=5)
    p = {k: float(v) for k, v in (ln.split(",") for ln in E.render("ardupilot", E.build_export(cal, None))
                                  .splitlines() if not ln.startswith("#"))}
    mat = np.array([[p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
                    [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
                    [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]]])
    mg = rows.b_meas * 10.0                                            # 1 uT = 10 mG
    fw = np.array([mat @ ((m + np.array([p["COMPASS_OFS_X"], p["COMPASS_OFS_Y"], p["COMPASS_OFS_Z"]]))
                          * p["COMPASS_SCALE"]) for m in mg]) / 10.0
    np.testing.assert_allclose(fw, _physics(cal, rows), atol=1e-6)


def test_fit_symmetric_affine_recovers_known_coefficients(rng):
    D = np.array([[1.1, 0.05, -0.02], [0.05, 0.9, 0.03], [-0.02, 0.03, 1.2]])
    Ecoef = rng.normal(size=(3, 3))
    b = rng.uniform(-50, 50, (200, 3))
    poly = np.column_stack([np.ones(200), rng.uniform(-10, 10, 200), rng.uniform(-10, 10, 200)])
    y = b @ D.T - poly @ Ecoef
    D_hat, E_hat = E.fit_symmetric_affine(b, y, poly)
    np.testing.assert_allclose(D_hat, D, atol=1e-10)
    np.testing.assert_allclose(E_hat, Ecoef, atol=1e-9)


def test_a_rotated_sensor_loses_accuracy_in_symmetric_targets_and_says_so():
    th = _symmetric_theta(ko=False)
    c, s = np.cos(0.05), np.sin(0.05)
    th[:, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ th[:, :3]   # a small misalignment: not symmetric
    cal = _cal(th)
    rows = _rows(n=600, seed=6)
    rows = CalibrationData(rows.b_meas, rows.temperature, _physics(cal, rows))
    ex = E.build_export(cal, rows)
    assert ex.t_ref == pytest.approx(np.median(rows.temperature))        # where the training rows are
    acc = ex.accuracy["formats"]
    assert max(acc["json"]["vs_full_model"].values()) < 1e-9
    assert max(acc["magcal"]["vs_full_model"].values()) < 1e-9          # Ks = Ko = 0: exact at every T
    assert min(acc["ardupilot"]["vs_full_model"][a] for a in "xy") > 0.1
    text = E.render("ardupilot", ex)
    assert "rotation (antisymmetric) part of S" in text and "On the 600 training rows" in text


def test_extra_terms_are_named_as_dropped():
    from bayesmag._src.core.catalogue import make_extra
    term = make_extra("axis_quadratic", t0=T0)
    cal = _cal(np.column_stack([TRUE_THETA, np.full((3, len(term.param_names())), 1e-3)]), extra=(term,))
    ex = E.build_export(cal, None)
    assert ex.dropped == ("axis_quadratic",)
    assert "axis_quadratic" in E.limitations("json", ex)[0]


def test_export_cli_on_a_run_measures_the_loss(tmp_path, capsys):
    raw = {"data": {"source": "simulated", "simulate": {"design": "campaign", "n": 1200, "seed": 1, "noise_sd": 0.05}},
           "split": {"kind": "time_blocks", "test_fraction": 0.2}, "uq": {"method": "analytic"},
           "physics": {"t0": "mean"}, "output": {"figures": False, "progress": False}}
    out = tmp_path / "run"
    bayesmag.run_job(config_from_dict(raw), out)
    for fmt in E.FORMATS:
        assert main(["export", str(out), "--format", fmt]) == 0
        assert (out / f"calibration{E.FORMATS[fmt]}").exists()
    text = capsys.readouterr().out
    assert text.count("On the 960 training rows") == len(E.FORMATS)
    doc = json.loads((out / "calibration.json").read_text())               # the artifact is untouched
    assert doc["format"] == "bayesmag.calibration"
    assert json.loads((out / "calibration.export.json").read_text())["format"] == "bayesmag.export"
    assert bayesmag.load(out).theta.shape == (3, 8)
    from bayesmag._src.app.outdir import check_out
    check_out(out)                     # the exports are listed in the run's marker: the folder may be re-run


def test_unknown_format_is_an_error_naming_the_valid_ones(tmp_path):
    with pytest.raises(E.ExportError, match="must be one of"):
        E.export_run(tmp_path, "matlab")
