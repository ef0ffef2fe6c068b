"""Fleet calibration (core/fleet_fit.py, core/simulate_fleet.py, app/fleet.py): the batched fit, covariance and
uncertainty against the single-sensor code run one sensor at a time; padding; planted defects flagged; verdicts."""

import json

import numpy as np
import pytest

from bayesmag._src.app.cli import main
from bayesmag._src.app.config import ConfigError
from bayesmag._src.app.fleet import fleet_config_from_dict, load_fleet_config, run_fleet
from bayesmag._src.core.fit import fit_physics
from bayesmag._src.core.fleet_fit import FleetData, fit_fleet, fleet_input_noise, fleet_uncertainty, robust_z
from bayesmag._src.core.physics import PhysicsModel, inputs_from_data
from bayesmag._src.core.physics_uq import estimate_input_noise, physics_uncertainty
from bayesmag._src.core.simulate import TrueParams, simulate
from bayesmag._src.core.simulate_fleet import DEFECTS, simulate_fleet

MODEL = PhysicsModel.paper(t0=25.0)


@pytest.fixture(scope="module")
def three():
    """Three sensors of different lengths (padding) and parameters."""
    rng = np.random.default_rng(3)
    recs = []
    for s, n in enumerate([600, 430, 520]):
        th = TrueParams.paper().theta.copy()
        th[:, 6] += rng.normal(0, 2, 3)
        recs.append(simulate(n, design="campaign", seed=s, params=TrueParams.from_theta(th), noise_sd=0.05))
    return recs


@pytest.mark.parametrize("method", ["white", "ar1"])
def test_batched_fit_equals_per_sensor_fit(three, method):
    ff = fit_fleet(FleetData.from_recordings(three), MODEL, covariance_method=method, batch_size=4)
    assert ff.converged.all() and ff.identifiable.all()
    for i, rec in enumerate(three):
        ref = fit_physics(rec, MODEL, covariance_method=method)
        np.testing.assert_allclose(ff.theta[i], ref.theta, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(ff.cov[i], ref.cov, rtol=1e-7, atol=1e-16)
        np.testing.assert_allclose(ff.s2[i], ref.s2, rtol=1e-9)
        np.testing.assert_allclose(ff.rho1[i], [c["rho1"] for c in ref.cov_info], rtol=1e-8, atol=1e-12)


def test_batched_uncertainty_equals_per_sensor_analytic(three):
    fleet = FleetData.from_recordings(three)
    ff = fit_fleet(fleet, MODEL, covariance_method="white", batch_size=4)
    sig = fleet_input_noise(fleet)
    uq = fleet_uncertainty(ff, fleet, sig, batch_size=4)
    for i, rec in enumerate(three):
        np.testing.assert_allclose(sig[i], estimate_input_noise(rec), rtol=1e-12, atol=0)
        ref = physics_uncertainty(fit_physics(rec, MODEL), inputs_from_data(rec), sigma_in=sig[i], method="analytic")
        k = rec.n
        for got, want in ((uq.mean, ref.mean), (uq.aleatoric, ref.aleatoric), (uq.epistemic, ref.epistemic)):
            np.testing.assert_allclose(got[i, :k], want, rtol=1e-8, atol=1e-12)
        assert not uq.mean[i, k:].any()                     # padded rows stay zero


def test_padding_and_masking_change_nothing(three):
    """The same sensors padded with 150 junk rows (mask false) fit exactly as unpadded."""
    a = FleetData.from_recordings(three)
    b = FleetData.from_recordings(three, pad_to=three[0].n + 150)
    b.b_meas[0, three[0].n:] = 1e3                         # junk in the padding must be ignored
    b.b_ref[0, three[0].n:] = -1e3
    b.b_meas[1, three[1].n:] = -7.0
    fa, fb = fit_fleet(a, MODEL, batch_size=4), fit_fleet(b, MODEL, batch_size=4)
    np.testing.assert_allclose(fb.theta, fa.theta, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(fb.cov, fa.cov, rtol=1e-8)
    assert fb.n.tolist() == [r.n for r in three]


def test_robust_z_matches_definition():
    x = np.array([0.0, 1.0, 2.0, 3.0, 50.0])
    mad = 1.4826 * np.median(np.abs(x - 2.0))
    np.testing.assert_allclose(robust_z(x), (x - 2.0) / mad)


def test_simulated_fleet_ground_truth():
    recs, truth = simulate_fleet(12, 300, seed=4, n_defective=5, rows_spread=0.3)
    assert sorted(truth.defects.values()) == sorted(DEFECTS)
    assert all(210 <= r.n <= 300 for r in recs) and len({r.n for r in recs}) > 1
    i = truth.ids.index(next(k for k, v in truth.defects.items() if v == "offset"))
    assert truth.theta[i, 0, 6] > 15                       # the planted +25 uT offset is in the truth


def _cfg(tmp_path, **over):
    raw = {"name": "small", "fleet": {"source": "simulated", "batch_size": 4,
                                      "simulate": {"n_sensors": 40, "n_rows": 800, "seed": 1, "n_defective": 5,
                                                   "rows_spread": 0.2}},
           "split": {"test_fraction": 0.25}, "physics": {"t0": 25.0}}
    for k, v in over.items():
        raw["fleet"][k] = v
    return fleet_config_from_dict(raw, base=tmp_path)


@pytest.fixture(scope="module")
def small_fleet(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fleet")
    cfg = _cfg(tmp, figures=False)
    return run_fleet(cfg, tmp / "out", progress=False), tmp / "out"


def test_planted_units_flagged_exactly(small_fleet):
    s, out = small_fleet
    gt = s["ground_truth"]
    assert gt["exact"], gt
    assert sorted(s["flagged"]) == sorted(gt["defective"]) and s["n_fail"] == 5 and s["n_pass"] == 35
    want = {"offset": "max_offset_ut", "gain": "max_gain_error", "cross_axis": "max_cross_axis",
            "thermal": "max_offset_tempco", "noisy": "max_rmse_ut"}
    for sid, kind in gt["defective"].items():                # each defect fails its own limit and is an outlier
        assert want[kind] in s["failed_limits"][sid]
        assert sid in s["outliers"]
    on_disk = json.loads((out / "fleet.json").read_text())
    assert on_disk["flagged"] == s["flagged"] and (out / "fleet_report.md").exists()
    assert len(list((out / "sensors").iterdir())) == 40


def test_sensor_folder_is_a_calibration(small_fleet):
    """Each sensor folder loads as a calibration and predicts its own recording as the fleet fit does."""
    from bayesmag._src.app.artifact import load
    s, out = small_fleet
    recs, truth = simulate_fleet(40, 800, seed=1, n_defective=5, rows_spread=0.2)
    sid = next(x["id"] for x in s["sensors"] if x["verdict"] == "pass")
    i = truth.ids.index(sid)
    cal = load(out / "sensors" / sid)
    pred = cal.predict(recs[i])
    rmse = np.sqrt(np.mean((pred["calibrated"] - recs[i].b_ref) ** 2, axis=0))
    np.testing.assert_allclose(rmse, list(s["sensors"][i]["test_rmse"].values()), rtol=0.25)
    assert np.abs(cal.theta - truth.theta[i]).max() < 0.5


def test_fewer_than_40_sensors_skips_outliers_not_limits(small_fleet, tmp_path, monkeypatch):
    import bayesmag._src.app.fleet as F
    monkeypatch.setattr(F, "MIN_SENSORS_OUTLIERS", 41)
    s = run_fleet(_cfg(tmp_path, figures=False, sensor_folders=False), tmp_path / "o", progress=False)
    assert not s["outlier_test"]["computed"] and "41" in s["outlier_test"]["reason"]
    assert s["outliers"] == [] and sorted(s["flagged"]) == sorted(small_fleet[0]["ground_truth"]["defective"])


@pytest.mark.parametrize("raw, key", [
    ({"fleet": {"source": "simulated", "bogus": 1}}, "fleet.bogus"),
    ({"fleet": {"source": "simulated", "limits": {"max_offset": 3}}}, "fleet.limits.max_offset"),
    ({"fleet": {"source": "simulated", "simulate": {"n_sensors": 0}}}, "fleet.simulate.n_sensors"),
    ({"fleet": {"source": "simulated"}, "physics": {"t0": "mean"}}, "t0"),
    ({"fleet": {"source": "simulated", "recordings": "x/*.csv"}}, "exactly one of"),
    ({"fleet": {"source": "simulated"}, "physics": {"covariance": "newey_west"}}, "newey_west"),
])
def test_bad_fleet_config_names_the_key(raw, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        fleet_config_from_dict(raw)


def test_run_on_a_fleet_config_points_to_fleet(capsys):
    assert main(["run", "fleet_simulated"]) == 2
    err = capsys.readouterr().err.strip()
    assert "is a fleet config" in err and "bayesmag fleet" in err and len(err.splitlines()) == 1


def test_packaged_fleet_config_loads():
    from bayesmag._src.app.cli import _resolve_config
    cfg = load_fleet_config(_resolve_config("fleet_simulated"), ["fleet.simulate.n_sensors=50"])
    assert cfg.source == "simulated" and cfg.simulate.n_sensors == 50 and cfg.simulate.n_defective == 5


def test_fleet_from_a_folder_of_csv_files(tmp_path, capsys):
    """Recordings from files (ids = file stems) through the CLI; a bad file is one line naming the sensor."""
    from bayesmag._src.core.data import write_csv
    recs, _ = simulate_fleet(3, 700, seed=2, n_defective=0)
    (tmp_path / "recs").mkdir()
    for k, r in enumerate(recs):
        write_csv(r, tmp_path / "recs" / f"unit-{k}.csv")
    cfg = tmp_path / "f.toml"
    cfg.write_text('[fleet]\nrecordings = "recs"\nfigures = false\nbatch_size = 4\n')
    assert main(["fleet", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    s = json.loads((tmp_path / "out" / "fleet.json").read_text())
    assert [x["id"] for x in s["sensors"]] == ["unit-0", "unit-1", "unit-2"] and not s["outlier_test"]["computed"]
    capsys.readouterr()
    (tmp_path / "recs" / "unit-1.csv").write_text("time,run,bx_meas\n0,1,2\n")
    assert main(["fleet", str(cfg), "--out", str(tmp_path / "out2"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bayesmag: error: sensor unit-1") and len(err.splitlines()) == 1
    assert not (tmp_path / "out2").exists()
