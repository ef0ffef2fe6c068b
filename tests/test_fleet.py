"""Fleet calibration (core/fleet_fit.py, core/simulate_fleet.py, app/fleet.py): the batched fit, covariance and
uncertainty against the single-sensor code run one sensor at a time; padding; planted defects flagged; verdicts."""

import json
import re

import numpy as np
import pandas as pd
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
@pytest.mark.extended
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


def test_report_regenerates_a_sensor_certificate(small_fleet, tmp_path, capsys):
    """`bayesmag report sensors/<id>` rewrites the sensor's certificate as the fleet wrote it (it was refused: the
    sensor folder has no marker of its own; the fleet's lists its files); a look-alike folder is still refused."""
    import shutil
    s, out = small_fleet
    sid = s["sensors"][0]["id"]
    d = out / "sensors" / sid
    want = (d / "report.md").read_text()
    (d / "report.md").unlink()
    (d / "report.html").write_text("damaged")
    assert main(["report", str(d)]) == 0
    assert (d / "report.md").read_text() == want and "damaged" not in (d / "report.html").read_text()
    fake = tmp_path / "copy" / "sensors" / sid                # no fleet marker above it
    shutil.copytree(d, fake)
    assert main(["report", str(fake)]) == 2
    assert "not a finished bayesmag run folder" in capsys.readouterr().err


def test_fewer_than_40_sensors_skips_outliers_not_limits(small_fleet, tmp_path, monkeypatch):
    import bayesmag._src.app.fleet as F
    monkeypatch.setattr(F, "MIN_SENSORS_OUTLIERS", 41)
    s = run_fleet(_cfg(tmp_path, figures=False, sensor_folders=False), tmp_path / "o", progress=False)
    assert not s["outlier_test"]["computed"] and "41" in s["outlier_test"]["reason"]
    assert s["outliers"] == [] and sorted(s["flagged"]) == sorted(small_fleet[0]["ground_truth"]["defective"])
    # the report and the table say "not tested", not "no" (the test was not run)
    report = (tmp_path / "o" / "fleet_report.md").read_text()
    assert "| not tested |" in report and "| no |" not in report
    assert "| max_offset_ut | uT |" in report and "| O[x] | uT |" in report and "| Ks_x[x] | 1/C |" in report
    import csv
    rows = list(csv.DictReader(open(tmp_path / "o" / "fleet_table.csv")))
    assert {r["outlier"] for r in rows} == {""}


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


def test_a_sensor_recorded_at_one_temperature_is_not_signed_off(tmp_path):
    """Belsten run 3 alone (23.90-24.01 C) got a tempco verdict from thermal terms the data cannot inform (Ko[z]
    -2.1 uT/C, S_y[y] -1.54 at t0 25): now its tempco is not scored and it fails 'temperature_span', with a note."""
    import dataclasses as dc
    from bayesmag._src.core.data import write_csv
    recs, _ = simulate_fleet(3, 700, seed=2, n_defective=0)
    (tmp_path / "recs").mkdir()
    for k, r in enumerate(recs):
        if k == 1:
            r = dc.replace(r, temperature=24.0 + 0.05 * np.sin(np.arange(r.n) / 50.0))
        write_csv(r, tmp_path / "recs" / f"unit-{k}.csv")
    cfg = tmp_path / "f.toml"
    cfg.write_text('[fleet]\nrecordings = "recs"\nfigures = false\nbatch_size = 4\n')
    assert main(["fleet", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    s = {x["id"]: x for x in json.loads((tmp_path / "out" / "fleet.json").read_text())["sensors"]}
    narrow = s["unit-1"]
    assert narrow["verdict"] == "fail" and "temperature_span" in narrow["fails_limits"]
    assert "max_offset_tempco" not in narrow["fails_limits"] and narrow["training_temperature_span_c"] < 0.11
    assert "not measured" in narrow["notes"][0]
    assert "unit-1: the training temperature spans only" in (tmp_path / "out" / "fleet_report.md").read_text()
    for k in ("unit-0", "unit-2"):
        assert "temperature_span" not in s[k]["fails_limits"] and "notes" not in s[k]


# ------------------------------------------------------------------ sensor folders = single-run folders (#27)


def _single_run_files(tmp_path, *, network: bool, figures: bool) -> set:
    """The file set of a small single `bayesmag run` folder (simulated, analytic UQ)."""
    from bayesmag._src.app.config import config_from_dict
    from bayesmag._src.app.job import run_job
    raw = {"name": "one", "data": {"source": "simulated", "simulate": {"n": 800, "design": "campaign", "seed": 1}},
           "split": {"test_fraction": 0.25}, "physics": {"t0": 25.0}, "uq": {"method": "analytic", "transfer": "off"},
           "output": {"figures": figures}}
    if network:
        raw["network"] = {**NET, "interval_calibration": "none"}
    run_job(config_from_dict(raw), tmp_path / "single", progress=False)
    return {p.name for p in (tmp_path / "single").iterdir() if not p.name.startswith(".")}


#: A small network (1 hidden layer of 8 units, 4 epochs): the tests check the plumbing, not the accuracy.
NET = {"enabled": True, "hidden_layers": 1, "width": 8, "max_epochs": 4, "batch_size": 32, "mc_passes": 10,
       "seed": 2}


def test_sensor_folder_has_the_single_run_file_set(small_fleet, tmp_path):
    """Every sensor folder holds the files of a single `bayesmag run` folder (the fleet folder's marker lists
    them; a sensor folder has no marker of its own)."""
    s, out = small_fleet
    want = _single_run_files(tmp_path, network=False, figures=False)
    assert {"predictions.csv", "report.md", "report.html", "metrics.json", "calibration.json"} <= want
    for x in s["sensors"]:
        d = out / "sensors" / x["id"]
        assert {p.name for p in d.iterdir()} == want, x["id"]
    m = json.loads((d / "metrics.json").read_text())
    assert m["fleet"]["verdict"] == x["verdict"] and m["split"]["n_test"] == x["n_test"]
    np.testing.assert_allclose(list(m["physics"]["rmse"].values()), list(x["test_rmse"].values()), rtol=1e-9)
    np.testing.assert_allclose(list(m["physics"]["coverage"].values()), list(x["test_coverage"].values()), rtol=1e-9)
    pred = np.genfromtxt(d / "predictions.csv", delimiter=",", names=True)
    assert len(pred) == x["n_test"]
    np.testing.assert_allclose(np.sqrt(np.mean((pred["x_reference"] - pred["x_predicted"]) ** 2)), x["test_rmse"]["x"],
                               rtol=1e-6)
    assert "# Calibration report" in (d / "report.md").read_text()


def test_score_rows_equals_score_per_axis():
    """The fleet's row-block scorer gives the numbers of metrics.score_per_axis (blocks of 512, last one padded)."""
    from bayesmag._src.app.fleet_sensors import score_rows
    from bayesmag._src.core.likelihoods import get_likelihood
    from bayesmag._src.core.metrics import score_per_axis
    rng = np.random.default_rng(0)
    y, loc, scale = rng.normal(size=(1100, 3)), rng.normal(size=(1100, 3)), rng.uniform(0.5, 2, (1100, 3))
    for fam, extra in (("gaussian", {}), ("student_t", {"df": np.full((1100, 3), 5.0)})):
        dist = get_likelihood(fam)(loc=loc, scale=scale, **extra)
        got, want = score_rows(y, dist, 0.9), score_per_axis(y, dist, 0.9)
        for k in want:
            np.testing.assert_allclose(list(got[k].values()), list(want[k].values()), rtol=1e-9, err_msg=k)


def test_apply_and_export_take_a_sensor_folder(small_fleet, tmp_path, capsys):
    """`bayesmag apply --model sensors/<id>` and `bayesmag export sensors/<id>` work; the export is listed in the
    fleet folder's marker, so the fleet folder may still be replaced by a later fleet run."""
    import shutil

    from bayesmag._src.app.outdir import check_out, marker_status
    from bayesmag._src.core.data import write_csv
    s, out0 = small_fleet
    out = tmp_path / "fleet"
    shutil.copytree(out0, out)
    sid = s["sensors"][3]["id"]
    recs, truth = simulate_fleet(40, 800, seed=1, n_defective=5, rows_spread=0.2)
    write_csv(recs[truth.ids.index(sid)], tmp_path / "rec.csv")
    assert main(["apply", "--model", str(out / "sensors" / sid), "--data", str(tmp_path / "rec.csv"), "--out",
                 str(tmp_path / "cal.csv"), "--no-progress"]) == 0
    cal = np.genfromtxt(tmp_path / "cal.csv", delimiter=",", names=True)
    assert len(cal) == recs[truth.ids.index(sid)].n
    capsys.readouterr()
    assert main(["export", str(out / "sensors" / sid), "--format", "c-header"]) == 0
    said = capsys.readouterr()
    assert "could not be reloaded" not in said.out + said.err        # the sensor's held-out rows were found
    listed = marker_status(out)["files"]
    assert any(f.startswith(f"sensors/{sid}/") and f.endswith(".h") for f in listed)
    check_out(out)                                                  # not refused: every file is the fleet's


@pytest.mark.extended
def test_fleet_network_batched_equals_single_sensor_training(tmp_path):
    """[network] enabled: each sensor's network is the single-sensor training of its residuals with the same seed
    (tolerance of tests/test_network_batch.py), fused into its predictions, saved with its calibration."""
    import jax

    from bayesmag._src.app.artifact import load
    from bayesmag._src.app.fleet import load_recordings
    from bayesmag._src.core.data import make_split
    from bayesmag._src.core.network import fit_residual_network
    from bayesmag._src.core.predictor import network_inputs
    from test_network_batch import ATOL_WEIGHTS
    raw = {"name": "net", "fleet": {"source": "simulated", "batch_size": 2, "figures": False,
                                    "simulate": {"n_sensors": 3, "n_rows": 700, "seed": 3, "n_defective": 0,
                                                 "rows_spread": 0.2}},
           "split": {"test_fraction": 0.25}, "physics": {"t0": 25.0}, "network": NET}
    cfg = fleet_config_from_dict(raw, base=tmp_path)
    s = run_fleet(cfg, tmp_path / "out", progress=False)
    recs, ids, _ = load_recordings(cfg)
    shortest = int(np.argmin([r.n for r in recs]))            # the most padded one
    for i, sid in enumerate(ids):
        x = s["sensors"][i]
        assert x["prediction"] == "hybrid (gaussian)" and "physics_test_rmse" in x
        m = json.loads((tmp_path / "out" / "sensors" / sid / "metrics.json").read_text())
        np.testing.assert_allclose(list(m["hybrid"]["gaussian"]["rmse"].values()), list(x["test_rmse"].values()),
                                   rtol=1e-9)
        if i != shortest:                                      # one single-sensor training (each length compiles)
            continue
        sp = make_split(recs[i], kind="time_blocks", test_fraction=0.25, seed=0)
        train = recs[i].subset(sp.train)
        cal = load(tmp_path / "out" / "sensors" / sid)
        pr = cal.predictor()
        r = train.b_ref - pr.fit.predict(inputs_from_data(train))
        spec = cfg.network.spec("gaussian")
        ref = fit_residual_network(network_inputs(train), r, spec, seed=NET["seed"], validation=cfg.network.validation,
                                   validation_fraction=cfg.network.validation_fraction, groups=train.run)
        net = pr.network                                   # the network saved with the sensor's calibration
        assert net is not None
        for a, b in zip(jax.tree.leaves(net.params), jax.tree.leaves(ref.params)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=ATOL_WEIGHTS)
        assert [m["network"]["training"]["gaussian"][ax]["epochs_run"] for ax in "xyz"] == \
            [int(e) for e in ref.info.epochs_run]
    assert "hybrid_predicted" in (tmp_path / "out" / "sensors" / ids[0] / "predictions.csv").read_text().split("\n")[0]
    assert s["timings"]["network_train"] > 0


@pytest.mark.parametrize("net, key", [({"interval_calibration": "conformal"}, "interval_calibration"),
                                      ({"likelihoods": ["gaussian", "laplace"]}, "likelihoods"),
                                      ({"width": 0}, "network.width")])
def test_bad_fleet_network_config_names_the_key(net, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        fleet_config_from_dict({"fleet": {"source": "simulated"}, "network": {"enabled": True, **net}})


def test_fleet_network_too_large_for_a_sensor_is_one_line(tmp_path, capsys):
    """A network too large for a sensor's rows stops the fleet before any training: one line naming the sensor and
    the key, exit status 2, nothing written."""
    cfg = tmp_path / "f.toml"
    cfg.write_text('[fleet]\nsource = "simulated"\nfigures = false\n'
                   '[fleet.simulate]\nn_sensors = 2\nn_rows = 300\nn_defective = 0\n'
                   '[network]\nenabled = true\nwidth = 64\nhidden_layers = 4\n')
    assert main(["fleet", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bayesmag: error: sensor SN00000") and "network.width" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_sensor_folder_with_network_and_figures_has_the_single_run_file_set(tmp_path):
    """With [network] and [output] figures = true a sensor folder holds the single run's figures too (slow:
    figures of a single run and of 2 sensors)."""
    want = _single_run_files(tmp_path, network=True, figures=True)
    raw = {"name": "f", "fleet": {"source": "simulated", "batch_size": 2, "figures": False,
                                  "simulate": {"n_sensors": 2, "n_rows": 800, "seed": 1, "n_defective": 0}},
           "split": {"test_fraction": 0.25}, "physics": {"t0": 25.0}, "network": NET, "output": {"figures": True}}
    run_fleet(fleet_config_from_dict(raw, base=tmp_path), tmp_path / "out", progress=False)
    for d in (tmp_path / "out" / "sensors").iterdir():
        assert {p.name for p in d.iterdir()} == want


def test_fast_prediction_writer_writes_the_same_bytes(tmp_path):
    """The fleet's column-wise predictions.csv writer equals the single run's row-by-row one, byte for byte."""
    from bayesmag._src.app.fleet_sensors import write_predictions
    from bayesmag._src.app.job import write_predictions as single
    from bayesmag._src.core.simulate import simulate
    rng = np.random.default_rng(1)
    d = simulate(300, design="campaign", seed=5)
    cols = {"predicted": rng.normal(size=(300, 3)) * 10.0 ** rng.integers(-9, 9, (300, 3)), "covered": rng.random((300, 3)) > .5,
            "in_domain_reason": np.broadcast_to(np.where(rng.random(300) > .5, "ok", "temperature,rate")[:, None],
                                                (300, 3)), "n": rng.integers(0, 5, (300, 3)),
            "obj": np.broadcast_to(np.array(["", "x", "rate"], dtype=object)[rng.integers(0, 3, 300)][:, None], (300, 3))}
    rows = np.sort(rng.choice(1000, 300, replace=False))
    write_predictions(tmp_path / "a.csv", d, rows, cols)
    single(tmp_path / "b.csv", d, rows, cols)
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()


def test_fleet_training_progress_in_a_log_is_one_line_per_stopped_network():
    """In a log (not a terminal) the batched training reports a line only when another network stops."""
    import io
    import types

    from bayesmag._src.app.fleet_sensors import training_reporter
    log = io.StringIO()
    report = training_reporter(log)
    done = np.zeros(6, bool)
    for epoch in range(1, 301):
        if epoch % 50 == 0:
            done[epoch // 50 - 1] = True
        report(types.SimpleNamespace(done=done.copy(), epochs=np.full(6, epoch)))
    lines = log.getvalue().splitlines()
    assert len(lines) == 7                      # the first report, then one per stopped network
    assert "\r" not in log.getvalue()
    assert lines[-1].startswith("  fleet: network training, 6 of 6")


# ------------------------------------------------------------------ fourth safety pass (fleet of CSV files)


def _csv_fleet(tmp_path, *, data_table: str = ""):
    """A fleet of three CSV recordings: U0 good (700 rows), U1 47 rows spread over its recording (36 training rows
    for 8 parameters per axis, sigma_in "auto" far too large), U2 its first 15 rows (12 training rows, field held:
    the data cannot inform every parameter). Returns (summary, fleet folder, recordings folder)."""
    from bayesmag._src.core.data import write_csv
    recs, _ = simulate_fleet(3, 700, seed=2, n_defective=0)
    (tmp_path / "recs").mkdir()
    write_csv(recs[0], tmp_path / "recs" / "U0.csv")
    write_csv(recs[1].subset(np.linspace(0, recs[1].n - 1, 47).astype(int)), tmp_path / "recs" / "U1.csv")
    write_csv(recs[2].subset(np.arange(15)), tmp_path / "recs" / "U2.csv")
    cfg = tmp_path / "f.toml"
    cfg.write_text('[fleet]\nrecordings = "recs"\nfigures = false\nbatch_size = 4\n' + data_table)
    assert main(["fleet", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    return json.loads((tmp_path / "out" / "fleet.json").read_text()), tmp_path / "out", tmp_path / "recs"


@pytest.fixture(scope="module")
def csv_fleet(tmp_path_factory):
    return _csv_fleet(tmp_path_factory.mktemp("csvfleet"))


def test_a_fleet_sensors_recording_is_never_overwritten(tmp_path, capsys):
    """`apply --out recs/U0.csv --force` replaced the sensor's training recording with the apply output, and
    `export --out recs/U0.csv --force` wrote over it: both are refused, as for a run folder."""
    s, out, recs = _csv_fleet(tmp_path)
    before = (recs / "U0.csv").read_bytes()
    capsys.readouterr()
    assert main(["apply", "--model", str(out / "sensors" / "U0"), "--data", str(recs / "U1.csv"), "--out",
                 str(recs / "U0.csv"), "--force", "--no-progress"]) == 2
    assert "was trained on" in capsys.readouterr().err
    assert main(["export", str(out / "sensors" / "U0"), "--format", "json", "--out", str(recs / "U0.csv"),
                 "--force"]) == 2
    assert "training recording" in capsys.readouterr().err
    assert (recs / "U0.csv").read_bytes() == before
    # sixth outside pass: another sensor's recording was replaced with --force (U1's calibration writing U0.csv)
    for cmd in (["apply", "--model", str(out / "sensors" / "U1"), "--data", str(recs / "U2.csv"), "--out",
                 str(recs / "U0.csv"), "--force", "--no-progress"],
                ["export", str(out / "sensors" / "U1"), "--format", "json", "--out", str(recs / "U0.csv"), "--force"]):
        assert main(cmd) == 2
        assert "another sensor of its fleet" in capsys.readouterr().err
    assert (recs / "U0.csv").read_bytes() == before
    from bayesmag._src.app.inputs import protected_recordings, recording_paths
    # a sensor folder written before [data] path was kept: the recording its metrics.json names
    assert [p.resolve() for p in recording_paths(None, out / "sensors" / "U0")] == [(recs / "U0.csv").resolve()]
    assert {p.resolve() for p in protected_recordings(None, out / "sensors" / "U0")} == {
        (recs / f"U{i}.csv").resolve() for i in range(3)}
    # export of a sensor whose recording is gone names the file it looked for (it said "could not be reloaded
    # ('U0')"), and a new recording's apply says fleets estimate no transfer term
    (recs / "U1.csv").rename(tmp_path / "U1_moved.csv")
    assert main(["export", str(out / "sensors" / "U1"), "--format", "px4", "--out", str(tmp_path / "u1.px4")]) == 2
    assert f"not found (looked for {recs / 'U1.csv'}" in capsys.readouterr().err
    assert main(["apply", "--model", str(out / "sensors" / "U0"), "--data", str(recs / "U2.csv"), "--out",
                 str(tmp_path / "u2.csv"), "--no-progress"]) == 0
    assert "a `bayesmag fleet` sensor: fleets do not estimate one" in capsys.readouterr().err


def test_fleet_export_refuses_a_changed_recording(tmp_path, capsys):
    """5 uT added to U0's bx_ref after the fleet: export --format px4 reported RMSE from the altered rows; now the
    sensor's file sha256 is recorded (as a run's) and the least-squares export is refused."""
    from bayesmag._src.core.datasets import sha256_of
    s, out, recs = _csv_fleet(tmp_path)
    m = json.loads((out / "sensors" / "U0" / "metrics.json").read_text())
    assert m["certificate"]["data_sha256"] == sha256_of(recs / "U0.csv")
    lines = (recs / "U0.csv").read_text().splitlines()
    i = lines[0].split(",").index("bx_ref")
    rows = [ln.split(",") for ln in lines[1:]]
    for r in rows:
        r[i] = repr(float(r[i]) + 5.0)
    (recs / "U0.csv").write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")
    capsys.readouterr()
    assert main(["export", str(out / "sensors" / "U0"), "--format", "px4", "--out", str(tmp_path / "u0.params")]) == 2
    assert "has changed since the run" in capsys.readouterr().err
    assert not (tmp_path / "u0.params").exists()


def test_a_sensor_with_too_few_rows_fails_on_its_design_warnings(csv_fleet):
    """U1 (36 training rows for 8 parameters per axis, sigma_in "auto" 2-4 uT against a true 0.05) passed with
    warnings [] where `bayesmag run` warns: it now fails 'design' and 'input_noise', and the warnings are in its
    metrics.json, params.json and report, fleet.json and fleet_report.md."""
    s, out, _ = csv_fleet
    u1 = {x["id"]: x for x in s["sensors"]}["U1"]
    assert u1["verdict"] == "fail" and {"design", "input_noise"} <= set(u1["fails_limits"])
    assert any("rows for 8 parameters" in w for w in u1["warnings"]) and s["warnings"]["U1"] == u1["warnings"]
    m = json.loads((out / "sensors" / "U1" / "metrics.json").read_text())
    assert any("rows for 8 parameters" in w for w in m["warnings"])
    assert any("sigma_in" in w for w in m["warnings"])
    assert json.loads((out / "sensors" / "U1" / "params.json").read_text())["design_warnings"]
    assert "rows for 8 parameters" in (out / "sensors" / "U1" / "report.md").read_text()
    assert "U1: WARNING: The fit used 36 rows" in (out / "fleet_report.md").read_text()
    u0 = {x["id"]: x for x in s["sensors"]}["U0"]
    assert u0["verdict"] == "pass" and u0["warnings"] == []


def test_a_rank_deficient_sensor_fails_unidentifiable_and_is_not_exported(csv_fleet, tmp_path, capsys):
    """U2 (12 training rows, field held) wrote a loadable calibration with offsets of 1600 uT and a condition
    number of 5e300, failing only limits: it now fails 'unidentifiable' with a note, and export refuses it unless
    --force."""
    s, out, _ = csv_fleet
    u2 = {x["id"]: x for x in s["sensors"]}["U2"]
    assert "unidentifiable" in u2["fails_limits"]
    assert any("cannot inform every parameter" in n for n in u2["notes"])
    capsys.readouterr()
    assert main(["export", str(out / "sensors" / "U2"), "--format", "json", "--out", str(tmp_path / "u2.json")]) == 2
    err = capsys.readouterr().err
    assert "cannot inform every parameter" in err and "--force" in err and len(err.strip().splitlines()) == 1
    assert main(["export", str(out / "sensors" / "U2"), "--format", "json", "--out", str(tmp_path / "u2.json"),
                 "--force"]) == 0
    assert "WARNING: sensor U2 FAILED the fleet's sign-off" in capsys.readouterr().out


def test_a_failed_sensor_says_so_in_its_report_export_and_apply(csv_fleet, tmp_path, capsys):
    """A failed sensor's report.md did not mention the fleet verdict, and export / apply said nothing."""
    s, out, recs = csv_fleet
    assert "**Fleet verdict: FAIL** (design, input_noise;" in (out / "sensors" / "U1" / "report.md").read_text()
    assert "**Fleet verdict: PASS**" in (out / "sensors" / "U0" / "report.md").read_text()
    capsys.readouterr()
    assert main(["export", str(out / "sensors" / "U1"), "--format", "json", "--out", str(tmp_path / "u1.json")]) == 0
    assert "WARNING: sensor U1 FAILED the fleet's sign-off (design, input_noise" in capsys.readouterr().out
    assert main(["apply", "--model", str(out / "sensors" / "U1"), "--data", str(recs / "U0.csv"), "--out",
                 str(tmp_path / "u1.csv"), "--no-progress"]) == 0
    said = capsys.readouterr()
    assert "WARNING: sensor U1 FAILED the fleet's sign-off" in said.out + said.err
    assert main(["export", str(out / "sensors" / "U0"), "--format", "json", "--out", str(tmp_path / "u0.json")]) == 0
    assert "FAILED" not in capsys.readouterr().out


def test_a_coverage_limit_in_percent_is_refused():
    """fleet.limits.min_coverage = 95 was accepted, and every sensor then failed min_coverage."""
    with pytest.raises(ConfigError, match=r"fleet\.limits\.min_coverage.*0\.95"):
        fleet_config_from_dict({"fleet": {"source": "simulated", "limits": {"min_coverage": 95}}})
    cfg = fleet_config_from_dict({"fleet": {"source": "simulated", "limits": {"min_coverage": 1}}})
    assert cfg.limits.min_coverage == 1


def _write_recordings(tmp_path, prefix, recs, column, change, rename=None):
    """``recs/<prefix><k>.csv`` for each recording, ``column``'s values passed through ``change`` and the header
    renamed by ``rename`` (a logger's own units and names)."""
    import csv
    from bayesmag._src.core.data import write_csv
    (tmp_path / "recs").mkdir()
    for k, r in enumerate(recs):
        path = tmp_path / "recs" / f"{prefix}{k}.csv"
        write_csv(r, path)
        rows = list(csv.reader(open(path)))
        c = rows[0].index(column)
        for row in rows[1:]:
            row[c] = repr(change(float(row[c])))
        rows[0] = [(rename or {}).get(h, h) for h in rows[0]]
        with open(path, "w", newline="") as f:
            csv.writer(f).writerows(rows)


def test_fleet_data_table_reads_kelvin_and_mapped_columns(tmp_path, capsys):
    """The kelvin error said 'Set [data] temperature_unit = "K"' and a missing column suggested [data.columns], and
    the fleet config refused key 'data': both now apply to every recording (and to export's reload)."""
    _write_recordings(tmp_path, "K", simulate_fleet(2, 700, seed=2, n_defective=0)[0], "temperature",
                      lambda v: v + 273.15, rename={"bx_meas": "Bx"})
    cfg = tmp_path / "f.toml"
    cfg.write_text('[fleet]\nrecordings = "recs"\nfigures = false\n')
    capsys.readouterr()
    assert main(["fleet", str(cfg), "--out", str(tmp_path / "bad"), "--no-progress"]) == 2
    assert "sensor K0" in capsys.readouterr().err
    cfg.write_text('[fleet]\nrecordings = "recs"\nfigures = false\n[data]\ntemperature_unit = "K"\n'
                   '[data.columns]\nbx_meas = "Bx"\n')
    assert main(["fleet", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    s = json.loads((tmp_path / "out" / "fleet.json").read_text())
    assert s["n_pass"] == 2, s["failed_limits"]
    capsys.readouterr()
    assert main(["export", str(tmp_path / "out" / "sensors" / "K0"), "--format", "px4", "--out",
                 str(tmp_path / "k0.params")]) == 0
    assert "could not be reloaded" not in capsys.readouterr().out
    with pytest.raises(ConfigError, match=r"data\.temperature_unit"):
        fleet_config_from_dict({"fleet": {"recordings": "recs"}, "data": {"temperature_unit": "F"}})
    with pytest.raises(ConfigError, match="simulated fleet has no files"):
        fleet_config_from_dict({"fleet": {"source": "simulated"}, "data": {"temperature_unit": "K"}})


def test_fleet_data_time_unit_reads_millisecond_stamps(tmp_path):
    """A fleet's recordings stamped in ms: `[data] time_unit = "ms"` converts them to seconds, as a run's does
    (the fleet config refused the key); the sensor folder's predictions carry seconds; a unit outside the set is
    refused naming it."""
    recs, _ = simulate_fleet(2, 700, seed=4, n_defective=0)
    _write_recordings(tmp_path, "M", recs, "time", lambda v: v * 1000.0)
    cfg = tmp_path / "f.toml"
    cfg.write_text('[fleet]\nrecordings = "recs"\nfigures = false\n[data]\ntime_unit = "ms"\n')
    assert main(["fleet", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    import pandas as pd
    pred = pd.read_csv(tmp_path / "out" / "sensors" / "M0" / "predictions.csv")
    assert np.isin(pred["time"].to_numpy(), recs[0].time).all()             # seconds again, row for row
    saved = json.loads((tmp_path / "out" / "sensors" / "M0" / "calibration.json").read_text())["config"]
    assert saved["time_unit"] == "ms"
    with pytest.raises(ConfigError, match=r"data\.time_unit.*'us'"):
        fleet_config_from_dict({"fleet": {"recordings": "recs"}, "data": {"time_unit": "sec"}})


@pytest.mark.parametrize("how", ["manifest", "copy"])
def test_two_sensors_with_one_recording_are_refused(tmp_path, capsys, how):
    """Sixth outside pass: a manifest naming one file for two ids, or a copied file, gave both sensors a pass and
    a certificate (their metrics.json held the same data_sha256)."""
    from bayesmag._src.core.data import write_csv
    recs, _ = simulate_fleet(3, 400, seed=4, n_defective=0)
    (tmp_path / "recs").mkdir()
    for i in range(3):
        write_csv(recs[i], tmp_path / "recs" / f"U{i}.csv")
    if how == "copy":
        (tmp_path / "recs" / "U2.csv").write_bytes((tmp_path / "recs" / "U0.csv").read_bytes())
        spec = '[fleet]\nrecordings = "recs"\nfigures = false\n'
    else:
        (tmp_path / "man.csv").write_text("id,path\nA1,recs/U0.csv\nA2,recs/U1.csv\nA3,recs/U0.csv\n")
        spec = '[fleet]\nmanifest = "man.csv"\nfigures = false\n'
    cfg = tmp_path / "f.toml"
    cfg.write_text(spec)
    assert main(["fleet", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    want = ("sensor U0 .* and sensor U2 " if how == "copy" else "sensor A1 .* and sensor A3 ")
    assert re.search(want + r".*identical \(same sha256\)", err), err
    assert not (tmp_path / "out").exists()


def test_every_bad_recording_is_named_in_one_error(tmp_path, capsys):
    """Sixth outside pass: with three broken files (a NaN, kelvin, a missing column) the fleet named one, so each
    took a rerun to find. Now one error names all three sensors and what is wrong with each; nothing is written."""
    from bayesmag._src.core.data import write_csv
    recs, _ = simulate_fleet(5, 400, seed=5, n_defective=0)
    (tmp_path / "recs").mkdir()
    for i in range(5):
        write_csv(recs[i], tmp_path / "recs" / f"U{i}.csv")
    df = pd.read_csv(tmp_path / "recs" / "U1.csv")
    df.loc[7, "bx_meas"] = np.nan
    df.to_csv(tmp_path / "recs" / "U1.csv", index=False)
    df = pd.read_csv(tmp_path / "recs" / "U3.csv")
    df["temperature"] += 273.15
    df.to_csv(tmp_path / "recs" / "U3.csv", index=False)
    pd.read_csv(tmp_path / "recs" / "U4.csv").drop(columns="by_meas").to_csv(tmp_path / "recs" / "U4.csv", index=False)
    cfg = tmp_path / "f.toml"
    cfg.write_text('[fleet]\nrecordings = "recs"\nfigures = false\n')
    assert main(["fleet", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "3 of 5 sensors cannot be calibrated" in err and len(err.strip().splitlines()) == 1, err
    assert re.search(r"sensor U1: .*'bx_meas'.*row\(s\) 8", err) and re.search(r"sensor U3: .*kelvin", err)
    assert re.search(r"sensor U4: .*by_meas", err)
    assert not (tmp_path / "out").exists()
