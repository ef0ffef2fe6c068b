"""Firmware export: each target's coefficients, applied by an independent re-implementation of that
target's own formula (written out here from the firmware sources cited in docs/export.md), reproduce
the physics model wherever the target can hold it (to 1e-9), and the CLI reports what is lost."""

import json
import re
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


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    raw = {"data": {"source": "simulated", "simulate": {"design": "campaign", "n": 1200, "seed": 1, "noise_sd": 0.05}},
           "split": {"kind": "time_blocks", "test_fraction": 0.2}, "uq": {"method": "analytic"},
           "physics": {"t0": "mean"}, "output": {"figures": False, "progress": False}}
    out = tmp_path_factory.mktemp("export") / "run"
    bayesmag.run_job(config_from_dict(raw), out)
    return out


@pytest.mark.extended
def test_export_cli_on_a_run_measures_the_loss_on_held_out_rows(run_dir, capsys):
    out = run_dir
    for fmt in E.FORMATS:
        assert main(["export", str(out), "--format", fmt]) == 0
        assert (out / f"calibration{E.FORMATS[fmt]}").exists()
    text = capsys.readouterr().out
    assert text.count("On the 240 held-out (test) rows") == len(E.FORMATS)
    doc = json.loads((out / "calibration.json").read_text())               # the artifact is untouched
    assert doc["format"] == "bayesmag.calibration"
    ex = json.loads((out / "calibration.export.json").read_text())
    assert ex["format"] == "bayesmag.export"
    # the exact form's error against the reference is the job's own physics test RMSE: the same held-out rows
    m = json.loads((out / "metrics.json").read_text())
    assert ex["accuracy"]["rows"] == "held-out (test) rows" and ex["accuracy"]["n_rows"] == m["split"]["n_test"]
    for a in "xyz":
        assert ex["accuracy"]["formats"]["json"]["vs_reference"][a] == pytest.approx(m["physics"]["rmse"][a], rel=1e-6)
    assert bayesmag.load(out).theta.shape == (3, 8)
    from bayesmag._src.app.outdir import check_out
    check_out(out)                     # the exports are listed in the run's marker: the folder may be re-run


def test_json_export_holds_covariance_and_U(run_dir):
    from bayesmag._src.app.report import expanded_uncertainties
    E.export_run(run_dir, "json")
    doc = json.loads((run_dir / "calibration.export.json").read_text())
    cal = bayesmag.load(run_dir)
    params = json.loads((run_dir / "params.json").read_text())
    assert doc["covariance"]["parameters"] == ["S_x", "S_y", "S_z", "Ks_x", "Ks_y", "Ks_z", "O", "Ko"]
    for i, a in enumerate("xyz"):
        c = np.array(doc["covariance"]["per_axis"][a])
        np.testing.assert_allclose(c, cal.cov[i], rtol=1e-12)
        np.testing.assert_allclose(np.sqrt(np.diag(c)), [params["axes"][a]["std"][n] for n in doc["covariance"]
                                                        ["parameters"]], rtol=1e-9)   # the certificate's u
    U = doc["expanded_uncertainty"]
    want = expanded_uncertainties(json.loads((run_dir / "metrics.json").read_text()), params)
    assert U["unit"] == "uT" and U["level"] == 0.95
    for a in "xyz":
        assert U["same_session"][a] == pytest.approx(want["same_session"][a]["U"], rel=1e-12)
        assert U["new_session"][a] > U["same_session"][a]                 # the transfer term adds
    report = (run_dir / "report.md").read_text()
    row = next(ln for ln in report.splitlines() if ln.startswith("| **expanded uncertainty U = k u_c, new session"))
    assert [c.strip() for c in row.strip("|").split("|")][3:6] == [f"{U['new_session'][a]:.2g}" for a in "xyz"]


def test_px4_file_has_device_placeholders_and_instructions(run_dir):
    text = E.render("px4", E.build_export(bayesmag.load(run_dir), None))
    active = _parse_px4(text)
    for name in ("CAL_MAG0_ID", "TC_M0_ID", "CAL_MAG0_ROT", "CAL_MAG0_PRIO"):
        assert name not in active                                          # nothing device-specific is loaded ...
        assert any(ln.startswith("# 1\t1\t" + name + "\t") for ln in text.splitlines())   # ... but a placeholder is
    assert "# 1\t1\tCAL_MAG0_ID\t<DEVICE_ID>\t6" in text and "only to the magnetometer whose device id" in text
    assert "PX4 applies it after this calibration" in text


def test_ardupilot_file_states_the_frame_and_units(run_dir):
    text = E.render("ardupilot", E.build_export(bayesmag.load(run_dir), None))
    active = [ln.split(",")[0] for ln in text.splitlines() if ln and not ln.startswith("#")]
    assert "COMPASS_DEV_ID" not in active and "# COMPASS_DEV_ID,<DEVICE_ID>" in text
    assert "body frame" in text and "COMPASS_ORIENT" in text and "must equal bx_meas x 10" in text


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc) on this machine")
def test_c_header_float_variant_domain_check_and_test_vector(run_dir, tmp_path):
    from bayesmag._src.core.domain import REASON_CODES
    cal = bayesmag.load(run_dir)
    E.export_run(run_dir, "c-header", tmp_path / "cal.h")
    header = (tmp_path / "cal.h").read_text()
    d = cal.domain
    lo, hi = np.asarray(d.low), np.asarray(d.high)
    x = lo + np.random.default_rng(8).uniform(0.02, 0.98, (30, 4)) * (hi - lo)       # inside the domain
    rows = CalibrationData(x[:, :3], x[:, 3], None)
    # domain probes: inside, field out (x), temperature out, field rate out (z), temperature rate out, all
    mid = 0.5 * (lo + hi)
    rate_ok, rate_hi = 0.5 * np.asarray(d.rate_high), 1.5 * np.asarray(d.rate_high)
    probes = [(mid, rate_ok), (np.r_[hi[0] + 1, mid[1:]], rate_ok), (np.r_[mid[:3], lo[3] - 1], rate_ok),
              (mid, np.r_[rate_ok[:2], rate_hi[2], rate_ok[3]]), (mid, np.r_[rate_ok[:3], rate_hi[3]]),
              (hi + 1, rate_hi)]
    want = [0, REASON_CODES["field_range"], REASON_CODES["temperature"], REASON_CODES["field_rate"],
            REASON_CODES["temperature_rate"], 15]
    c_rows = "\n".join(f"{{ double b[3] = {{{r[0]:.17g}, {r[1]:.17g}, {r[2]:.17g}}}, o[3]; "
                        f"float bf[3] = {{{r[0]:.9g}f, {r[1]:.9g}f, {r[2]:.9g}f}}, of[3]; "
                        f"bayesmag_calibrate(b, {t:.17g}, o); bayesmag_calibrate_f(bf, {t:.9g}f, of); "
                        f'printf("%.17g %.17g %.17g %.9g %.9g %.9g\\n", o[0], o[1], o[2], (double)of[0], (double)of[1], '
                        f"(double)of[2]); }}" for r, t in zip(rows.b_meas, rows.temperature))
    c_probes = "\n".join(f"{{ double b[3] = {{{p[0]:.17g}, {p[1]:.17g}, {p[2]:.17g}}}, r[3] = {{{q[0]:.17g}, "
                          f'{q[1]:.17g}, {q[2]:.17g}}}; printf("%d\\n", bayesmag_in_domain(b, {p[3]:.17g}, r, '
                          f"{q[3]:.17g})); }}" for p, q in probes)
    # apply's own verdict (no rates) on points of the measured box's corners region, where the calibrated output
    # leaves the training reference's range although every measured component is inside its own (the header
    # checked only the measured ranges before)
    box = lo + np.random.default_rng(9).uniform(-0.02, 1.02, (60, 4)) * (hi - lo)
    box_rows = CalibrationData(box[:, :3], box[:, 3], None)
    apply_codes = [sum(REASON_CODES[k] for k in (["field_range"] if o[:3].any() else [])
                       + (["temperature"] if o[3] else [])) for o in d.outside(box_rows, _physics(cal, box_rows))[:, :4]]
    c_box = "\n".join(f"{{ double b[3] = {{{p[0]:.17g}, {p[1]:.17g}, {p[2]:.17g}}}; "
                       f'printf("%d\\n", bayesmag_in_domain(b, {p[3]:.17g}, NULL, 0.0)); }}' for p in box)
    (tmp_path / "main.c").write_text('#include <stdio.h>\n#include "cal.h"\nint main(void) {\n'
                                     f'{c_rows}\n{c_probes}\nprintf("%d\\n", bayesmag_self_test());\n{c_box}\n'
                                     'return 0; }\n')
    # -Wdouble-promotion: the float variant does no double arithmetic (what a Cortex-M4F needs)
    subprocess.run(["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-Wdouble-promotion", "-Wfloat-conversion",
                    "-o", str(tmp_path / "m"), str(tmp_path / "main.c")], check=True, cwd=tmp_path)
    lines = subprocess.run([str(tmp_path / "m")], capture_output=True, text=True, check=True).stdout.splitlines()
    out = np.array([[float(v) for v in ln.split()] for ln in lines[:30]])
    phys = _physics(cal, rows)
    np.testing.assert_allclose(out[:, :3], phys, atol=1e-9)                  # double: exact
    err_f = np.abs(out[:, 3:] - phys).max()
    assert err_f < E.TEST_TOL_F and err_f > 0                               # float: rounding only, well below 1e-3 uT
    assert [int(v) for v in lines[30:36]] == want
    assert lines[36] == "0"                                                # the header's own self-test passes
    assert [int(v) for v in lines[37:97]] == apply_codes
    out_only = [o[:3].any() and not d.outside(CalibrationData(p[None, :3], p[None, 3], None))[0, :3].any()
                for p, o in zip(box, d.outside(box_rows, _physics(cal, box_rows)))]
    assert any(out_only), "no probe has its calibrated output alone outside the range: the check is not exercised"
    # the test vector in the header is the model's output (computed here independently)
    vec_in = np.array(eval(header.split("BAYESMAG_TEST_IN[BAYESMAG_N_TEST][4] = ")[1].split(";")[0]
                           .replace("{", "[").replace("}", "]")))
    vec_out = np.array(eval(header.split("BAYESMAG_TEST_OUT[BAYESMAG_N_TEST][3] = ")[1].split(";")[0]
                            .replace("{", "[").replace("}", "]")))
    np.testing.assert_allclose(vec_out, _physics(cal, CalibrationData(vec_in[:, :3], vec_in[:, 3], None)), atol=1e-12)
    assert not Domain(tuple(d.low), tuple(d.high)).outside(CalibrationData(vec_in[:, :3], vec_in[:, 3], None)).any()
    m = json.loads((run_dir / "metrics.json").read_text())
    from bayesmag._src.app.report import expanded_uncertainties
    U = expanded_uncertainties(m, json.loads((run_dir / "params.json").read_text()))
    same = [float(v) for v in header.split("BAYESMAG_U_SAME_SESSION[3] = {")[1].split("}")[0].split(",")]
    np.testing.assert_allclose(same, [U["same_session"][a]["U"] for a in "xyz"], rtol=1e-5)


def test_every_export_names_its_certificate(run_dir, tmp_path):
    """Traceability: each exported file carries the calibration ID, date and data sha256 of the run's report.md."""
    cert = json.loads((run_dir / "metrics.json").read_text())["certificate"]
    assert re.fullmatch(r"[0-9a-f]{16}", cert["calibration_id"]) and len(cert["data_sha256"]) == 64
    assert f"| calibration ID | {cert['calibration_id']} |" in (run_dir / "report.md").read_text()
    for fmt in E.FORMATS:
        path, _ = E.export_run(run_dir, fmt, tmp_path / f"cal{E.FORMATS[fmt]}")
        text = path.read_text()
        if fmt in ("json", "magcal"):
            assert json.loads(text)["certificate"] == cert, fmt
        else:
            line = next(ln for ln in text.splitlines()[:8] if "certificate: calibration ID" in ln)   # near the top
            assert cert["calibration_id"] in line and cert["data_sha256"] in line and cert["date_utc"] in line, fmt
            assert "device under test: not stated" in line                         # the fixture names no DUT
    # a calibration without metrics.json (no certificate known): no line, nothing invented
    ex = E.build_export(bayesmag.load(run_dir))
    assert E.certificate_line(ex) is None and "certificate:" not in E.render("px4", ex)


def test_unknown_format_is_an_error_naming_the_valid_ones(tmp_path):
    with pytest.raises(E.ExportError, match="must be one of"):
        E.export_run(tmp_path, "matlab")



def test_export_says_training_rows_without_a_split_and_skips_a_changed_recording(tmp_path):
    """``split.kind = "none"``: the accuracy is on the training rows and says so (it said "held-out (test) rows").
    A recording edited since the run (sha256 no longer the certificate's): the accuracy is not measured on it, with a
    warning (before: an x RMSE of 0.50 uT against the run's 0.05 after shifting bx_ref by 0.5 uT, silently)."""
    rec = tmp_path / "rec.csv"
    bayesmag.write_csv(bayesmag.simulate.simulate(600, design="campaign", seed=2, noise_sd=0.05), rec)
    raw = {"data": {"path": str(rec)}, "split": {"kind": "none"}, "uq": {"method": "analytic"},
           "physics": {"t0": "mean"}, "output": {"figures": False, "progress": False}}
    run = tmp_path / "run"
    bayesmag.run_job(config_from_dict(raw), run)
    _, ex = E.export_run(run, "json", tmp_path / "a.export.json")
    assert ex.accuracy["rows"].startswith("training rows") and ex.accuracy["n_rows"] == 600
    text = rec.read_text().splitlines()
    head = text[0].split(",")
    k = head.index("bx_ref")
    rows = [r.split(",") for r in text[1:]]
    for r in rows:
        r[k] = repr(float(r[k]) + 0.5)
    rec.write_text("\n".join([text[0]] + [",".join(r) for r in rows]) + "\n")
    _, ex = E.export_run(run, "json", tmp_path / "b.export.json")
    assert ex.accuracy is None and any("has changed since the run" in w for w in ex.warnings)
    assert any(line.startswith("WARNING:") and "has changed" in line for line in E.limitations("json", ex))
    # a least-squares target is fitted on the training rows: refused without them (it was fitted on a domain grid)
    with pytest.raises(E.ExportError, match="has changed since the run.*least-squares fit"):
        E.export_run(run, "px4", tmp_path / "c.params")


@pytest.mark.extended
def test_export_from_another_folder_finds_a_relative_recording(tmp_path, monkeypatch):
    """A run given a relative ``[data] path`` and exported from another folder: the recording is found from the
    folder the run started in (before: not found, and the PX4 form was fitted on a grid over the training box:
    CAL_MAG0_YSCALE -0.022 instead of 1.12 on the smoke pass's real recording)."""
    home = tmp_path / "home"
    home.mkdir()
    bayesmag.write_csv(bayesmag.simulate.simulate(600, design="campaign", seed=2, noise_sd=0.05), home / "rec.csv")
    monkeypatch.chdir(home)
    raw = {"data": {"path": "rec.csv"}, "split": {"kind": "time_blocks", "test_fraction": 0.2},
           "uq": {"method": "analytic"}, "output": {"figures": False, "progress": False}}
    bayesmag.run_job(config_from_dict(raw), home / "run")
    here = E.export_run(home / "run", "px4", tmp_path / "here.params")[1]
    monkeypatch.chdir(tmp_path)
    there = E.export_run(home / "run", "px4", tmp_path / "there.params")[1]
    assert there.accuracy is not None and set(there.px4) == set(here.px4)
    for k in here.px4:
        np.testing.assert_array_equal(np.asarray(there.px4[k]), np.asarray(here.px4[k]))
    (home / "rec.csv").rename(home / "moved.csv")
    with pytest.raises(E.ExportError, match=r"recording is not found \(looked for rec.csv, .*home/rec.csv\).*"
                                            r"least-squares"):     # the files it looked for, named
        E.export_run(home / "run", "px4", tmp_path / "gone.params")
