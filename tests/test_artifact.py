"""Saved calibrations: save -> load -> apply reproduces the run; bad artifacts and bad input are clear errors."""

import csv
import json

import numpy as np
import pytest

import bayesmag
from bayesmag import CalibrationData, DataError, write_csv
from bayesmag._src.app.apply import apply_calibration
from bayesmag._src.app.artifact import ArtifactError, load
from bayesmag._src.app.cli import main
from bayesmag._src.app.config import config_from_dict

UQ = {"n_params": 40, "n_qmc": 64, "seed": 3, "method": "psqmc"}


def _run(tmp_path, sim=None, **over):
    raw = {"data": {"source": "simulated", "simulate": sim or {"design": "campaign", "n": 1200, "seed": 1,
                                                                "noise_sd": 0.05}},
           "split": {"kind": "time_blocks", "test_fraction": 0.2}, "uq": UQ, "physics": {"t0": "mean"},
           "output": {"figures": False, "progress": False}, **over}
    out = tmp_path / "run"
    res = bayesmag.run_job(config_from_dict(raw), out)
    return res, out


def test_save_load_apply_reproduces_run_predictions(tmp_path):
    res, out = _run(tmp_path)
    cal = load(out)
    test = res["data"].subset(res["split"].test)
    # the test rows are time blocks of the training runs: same session, no transfer part
    pred = cal.predict(test, method="psqmc", n_params=UQ["n_params"], n_qmc=UQ["n_qmc"], seed=UQ["seed"],
                       new_session=False)
    rows = list(csv.DictReader(open(out / "predictions.csv")))
    assert all(float(r["x_transfer"]) == 0.0 for r in rows)
    for a, ax in enumerate("xyz"):
        run_pred = np.array([float(r[f"{ax}_predicted"]) for r in rows])
        run_tot = np.array([float(r[f"{ax}_total"]) for r in rows])
        np.testing.assert_allclose(pred["calibrated"][:, a], run_pred, rtol=1e-7)    # CSV keeps 8 digits
        np.testing.assert_allclose(pred["total"][:, a], run_tot, rtol=1e-7)
    # and exactly (bit for bit) against the in-memory run
    np.testing.assert_array_equal(pred["calibrated"], res["uq"].mean)
    # a new recording (the default) adds the saved transfer sd in quadrature, reported as its own column
    tau = np.array([res["metrics"]["transfer"]["sd"][a] for a in "xyz"])
    np.testing.assert_array_equal(cal.transfer_sd, tau)
    assert res["metrics"]["transfer"]["method"] == "leave_one_run_out" and np.all(tau > 0)
    new = cal.predict(test, method="psqmc", n_params=UQ["n_params"], n_qmc=UQ["n_qmc"], seed=UQ["seed"])
    np.testing.assert_allclose(new["total"] ** 2, pred["total"] ** 2 + tau**2, rtol=1e-10)
    np.testing.assert_array_equal(new["transfer"], np.broadcast_to(tau, new["transfer"].shape))
    assert "Transfer to a new session" in (out / "report.md").read_text()


def test_a_hysteresis_calibration_runs_and_applies_in_chunks_as_one_piece(tmp_path):
    """A job with the catalogue's hysteresis term (whose state is set by earlier rows) runs: its physics UQ took
    perturbed, chunked rows and failed with a TypeError before. Applied in 500-row chunks it gives the predictions
    of one piece (to 1e-12 relative, the rounding of the chunk-sized sums): the state is evaluated on the whole
    recording, not restarted per chunk (before: up to 0.12 uT apart on y over 244 of 4800 rows)."""
    res, out = _run(tmp_path, physics={"t0": "mean", "extra_terms": [{"name": "hysteresis", "axis": "x",
                                                                      "threshold": 20.0}]})
    assert res["metrics"]["physics"]["rmse"]["x"] < 0.2
    cal = load(out)
    new = bayesmag.simulate.simulate(2400, design="campaign", seed=5, noise_sd=0.05)
    state = np.asarray(cal.model.terms[1].state(bayesmag.inputs_from_data(new)))
    assert (np.diff(state[:500]) != 0).any() or (state[500:] != 0).any()     # a history to carry over
    kw = {"method": "psqmc", "n_params": UQ["n_params"], "n_qmc": UQ["n_qmc"], "seed": UQ["seed"]}
    whole, chunked = cal.predict(new, chunk_size=100_000, **kw), cal.predict(new, chunk_size=500, **kw)
    for k in ("calibrated", "total", "lower", "upper"):
        np.testing.assert_allclose(chunked[k], whole[k], rtol=1e-12, atol=0, err_msg=k)


@pytest.mark.extended
def test_a_thermal_lag_calibration_applies_in_chunks_as_one_piece(tmp_path):
    """The input transforms see a series: applied in 700-row chunks, each chunk is predicted with the rows its
    thermal lag remembers on both sides (45 tau; here tau about 70 s at 1 s steps), so the result is that of one
    piece (to 1e-9 relative). Before, the lag restarted at each chunk as at a run start."""
    from chamber_campaigns import campaign

    data, _ = campaign("lag_first_order", seed=2, n=3000)
    write_csv(data, tmp_path / "chamber.csv")
    res, out = _run(tmp_path, data={"path": str(tmp_path / "chamber.csv")},
                    physics={"t0": "mean", "extra_terms": [{"name": "thermal_lag", "tau0": 60.0}]})
    cal = load(out)
    tau = np.exp(cal.theta[:, list(cal.model.param_names).index("log_tau")])
    assert np.all((tau > 30) & (tau < 150)), tau
    kw = {"method": "psqmc", "n_params": UQ["n_params"], "n_qmc": UQ["n_qmc"], "seed": UQ["seed"]}
    whole, chunked = cal.predict(data, chunk_size=100_000, **kw), cal.predict(data, chunk_size=700, **kw)
    for k in ("calibrated", "total", "lower", "upper"):
        np.testing.assert_allclose(chunked[k], whole[k], rtol=1e-9, atol=1e-12, err_msg=k)


def test_apply_cli_without_reference_and_with_nan_rows(tmp_path, capsys):
    _, out = _run(tmp_path)
    d = bayesmag.simulate.simulate(300, design="campaign", seed=9, noise_sd=0.05)
    b = d.b_meas.copy()
    b[[4, 100], 1] = np.nan
    p = tmp_path / "field.csv"
    write_csv(CalibrationData(b, d.temperature, None, d.time, d.run), p)
    rc = main(["apply", "--model", str(out), "--data", str(p), "--out", str(tmp_path / "cal.csv"), "--no-progress"])
    assert rc == 0
    err = capsys.readouterr().err
    assert "2 row(s) have non-finite inputs" in err and "data row(s) 5, 101" in err
    rows = list(csv.DictReader(open(tmp_path / "cal.csv")))
    assert len(rows) == 300                                       # nothing dropped, order kept
    assert rows[4]["valid"] == "0" and rows[5]["valid"] == "1"
    assert rows[4]["in_domain_reason"] == "0" and float(rows[5]["y_transfer"]) > 0
    assert set(r["in_domain_reason"] for r in rows) <= {str(c) for c in range(16)}   # bit codes, REASON_CODES
    np.testing.assert_allclose([float(r["time"]) for r in rows], d.time, atol=1e-6)


def test_apply_says_when_its_method_differs_from_the_runs_and_how_to_reproduce_it(tmp_path, capsys):
    """The run used psqmc (Monte-Carlo means), `apply` the exact moments: the same rows' calibrated values differed
    (Belsten run 5: up to 0.3 uT) without a word. Now a note names both and the flags that reproduce the run's
    predictions.csv, and they do (apply draws with the run's [uq] seed)."""
    res, out = _run(tmp_path)
    test = res["data"].subset(res["split"].test)
    write_csv(test, tmp_path / "test.csv")
    assert main(["apply", "--model", str(out), "--data", str(tmp_path / "test.csv"), "--out", str(tmp_path / "a.csv"),
                 "--no-progress"]) == 0
    said = capsys.readouterr().out
    flags = f"--uq psqmc --n-params {UQ['n_params']} --n-qmc {UQ['n_qmc']}"
    assert "note: the calibration's run propagated" in said and flags in said, said
    assert main(["apply", "--model", str(out), "--data", str(tmp_path / "test.csv"), "--out", str(tmp_path / "b.csv"),
                 "--no-progress", *flags.split()]) == 0
    assert "note: the calibration's run" not in capsys.readouterr().out
    run = list(csv.DictReader(open(out / "predictions.csv")))
    exact = list(csv.DictReader(open(tmp_path / "a.csv")))
    again = list(csv.DictReader(open(tmp_path / "b.csv")))
    for ax in "xyz":
        r = np.array([float(x[f"{ax}_predicted"]) for x in run])
        np.testing.assert_allclose([float(x[f"{ax}_calibrated"]) for x in again], r, rtol=1e-7)
        assert np.abs(np.array([float(x[f"{ax}_calibrated"]) for x in exact]) - r).max() > 1e-7   # MC error


def test_out_of_domain_rows_flagged(tmp_path):
    """Train on a restricted field range of a simulated sensor, apply to a wider one."""
    res, out = _run(tmp_path, sim={"design": "iid", "n": 3000, "seed": 0, "noise_sd": 0.05, "field_range": 20.0},
                    split={"kind": "random", "test_fraction": 0.2})
    cal = load(out)
    wide = bayesmag.simulate.simulate(2000, design="iid", seed=1, noise_sd=0.05, field_range=50.0)
    pred = cal.predict(wide)
    # field_range bounds the true (reference) field; the measured field is scaled by the sensor's gains
    far = (np.abs(wide.b_ref) > 35).any(axis=1)
    near = (np.abs(wide.b_ref) < 15).all(axis=1)
    assert pred["in_domain"][far].mean() < 0.05, pred["in_domain"][far].mean()
    assert all("field_range" in w for w in pred["in_domain_reason"][far & ~pred["in_domain"]])
    # near rows are inside the value ranges (iid rows jump between random fields, so the wider recording's
    # field rates can exceed the training ones: flagged as field_rate, never as a range)
    assert not any("range" in w or "temperature" in w for w in pred["in_domain_reason"][near])
    # applying it warns with the count
    p = tmp_path / "wide.csv"
    write_csv(wide, p)
    s = apply_calibration(out, p, tmp_path / "w.csv")
    assert any("outside the calibration's training domain" in w for w in s["warnings"])


def test_bad_artifacts_say_why(tmp_path):
    _, out = _run(tmp_path)
    (out / "calibration.npz").rename(tmp_path / "moved.npz")
    with pytest.raises(ArtifactError, match=r"incomplete: \['calibration.npz'\] missing"):
        load(out)
    (tmp_path / "moved.npz").rename(out / "calibration.npz")
    doc = json.loads((out / "calibration.json").read_text())
    doc["format_version"] = 99
    (out / "calibration.json").write_text(json.dumps(doc))
    with pytest.raises(ArtifactError, match="format version 99; this bayesmag reads versions"):
        load(out)
    with pytest.raises(ArtifactError, match="not a folder"):
        load(out / "metrics.json")


def test_units_checked_against_training(tmp_path):
    _, out = _run(tmp_path)
    d = bayesmag.simulate.simulate(200, design="campaign", seed=2, noise_sd=0.05)
    p = tmp_path / "nt.csv"
    write_csv(CalibrationData(d.b_meas * 1000, d.temperature, None, d.time, d.run), p)
    with pytest.raises(DataError, match="looks like nT"):
        apply_calibration(out, p, tmp_path / "o.csv")
    k = tmp_path / "k.csv"
    write_csv(CalibrationData(d.b_meas, d.temperature + 273.15, None, d.time, d.run), k)
    with pytest.raises(DataError, match="--temperature-unit K"):
        apply_calibration(out, k, tmp_path / "o.csv")
    s = apply_calibration(out, k, tmp_path / "o.csv", temperature_unit="K")
    assert s["n_valid"] == 200


def test_report_written_and_regenerated(tmp_path, capsys):
    _, out = _run(tmp_path)
    text = (out / "report.md").read_text()
    assert "| S_x |" in text and "Condition number" in text and "Uncertainty budget" in text
    (out / "report.md").unlink()
    assert main(["report", str(out)]) == 0 and (out / "report.md").exists()


@pytest.mark.parametrize("likelihood,fourier,extra", [
    ("gaussian", 0, {}), ("student_t", 0, {}),
    ("gaussian", 8, {"validation": "time_blocks", "recalibrate": True})])
@pytest.mark.extended
def test_hybrid_calibration_round_trip(tmp_path, likelihood, fourier, extra):
    """A run with the residual network: save -> load -> apply reproduces the run's hybrid predictions."""
    net = {"enabled": True, "likelihoods": [likelihood], "hidden_layers": 2, "width": 16, "batch_size": 128,
           "max_epochs": 20, "patience": 5, "mc_passes": 8, "seed": 2, "fourier_features": fourier,
           **extra}
    res, out = _run(tmp_path, network=net)
    cal = load(out)
    assert cal.network is not None and cal.likelihood == likelihood
    # the conformal fold networks are kept as a deep ensemble: every member saved (test blocks of 0.2 of a run:
    # fold blocks of 0.25 of the training rows, so 3 of the default 5 folds fit, hybrid.conformal_plan)
    assert cal.network["meta"]["members"] == 3 and json.loads((out / "calibration.json").read_text())[
        "format_version"] == 2
    assert ("member2/fourier/frequencies" in cal.network["arrays"]) == (fourier > 0)
    assert ("member2/recalibration/variance_scale" in cal.network["arrays"]) == bool(extra)
    test = res["data"].subset(res["split"].test)
    assert cal.interval_scale is not None                              # conformal scale (default) saved
    pred = cal.predict(test, method="psqmc", n_params=UQ["n_params"], n_qmc=UQ["n_qmc"], seed=UQ["seed"],
                       new_session=False)
    rows = list(csv.DictReader(open(out / "predictions.csv")))
    for a, ax in enumerate("xyz"):
        np.testing.assert_allclose(pred["calibrated"][:, a], [float(r[f"{ax}_hybrid_predicted"]) for r in rows],
                                   rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(pred["total"][:, a], [float(r[f"{ax}_hybrid_total"]) for r in rows], rtol=1e-6)
        np.testing.assert_allclose(pred["upper"][:, a], [float(r[f"{ax}_hybrid_upper"]) for r in rows], rtol=1e-6)


def test_hybrid_runs_are_bit_identical(tmp_path):
    """Same config and seeds on the same machine: identical predictions, metrics and network weights."""
    net = {"enabled": True, "likelihoods": ["gaussian"], "hidden_layers": 2, "width": 16, "batch_size": 128,
           "max_epochs": 15, "patience": 5, "mc_passes": 8, "seed": 4}
    raw = {"data": {"source": "simulated", "simulate": {"design": "campaign", "n": 1200, "seed": 1, "noise_sd": 0.05}},
           "split": {"kind": "time_blocks", "test_fraction": 0.2}, "uq": UQ, "physics": {"t0": "mean"},
           "network": net, "output": {"figures": False, "progress": False}}
    for name in ("a", "b"):
        bayesmag.run_job(config_from_dict(raw), tmp_path / name)
    assert (tmp_path / "a/predictions.csv").read_bytes() == (tmp_path / "b/predictions.csv").read_bytes()
    za, zb = np.load(tmp_path / "a/calibration.npz"), np.load(tmp_path / "b/calibration.npz")
    assert sorted(za.files) == sorted(zb.files)
    for k in za.files:
        np.testing.assert_array_equal(za[k], zb[k])


def test_report_shows_network_parts_when_hybrid(tmp_path):
    net = {"enabled": True, "likelihoods": ["gaussian"], "hidden_layers": 2, "width": 16, "batch_size": 128,
           "max_epochs": 10, "patience": 5, "mc_passes": 8}
    _, out = _run(tmp_path, network=net)
    text = (out / "report.md").read_text()
    assert "network aleatoric" in text and "network epistemic" in text and "`moment_match`" in text


# --------------------------------------------------------------------------- deep ensemble in the calibration

ENS_NET = {"enabled": True, "likelihoods": ["gaussian"], "hidden_layers": 1, "width": 8, "batch_size": 128,
           "max_epochs": 8, "patience": 3, "mc_passes": 9, "seed": 1, "conformal_folds": 2}


@pytest.fixture(scope="module")
def ensemble_run(tmp_path_factory):
    res, out = _run(tmp_path_factory.mktemp("ens"), network=ENS_NET)
    return res, out


def _copy(out, tmp_path):
    import shutil
    shutil.copytree(out, tmp_path / "run")
    return tmp_path / "run"


def test_ensemble_calibration_saves_every_member_and_predicts_with_all(ensemble_run):
    from bayesmag._src.core.network import NetworkEnsemble, mc_predict
    from bayesmag._src.core.predictor import network_inputs

    res, out = ensemble_run
    pr = res["predictor"]
    assert isinstance(pr.network, NetworkEnsemble) and len(pr.network.members) == 2
    cal = load(out)
    ens = cal.predictor().network
    assert isinstance(ens, NetworkEnsemble) and len(ens.members) == 2
    for saved, kept in zip(ens.members, pr.network.members):
        for a, b in zip(saved.params, kept.params):
            np.testing.assert_array_equal(a.w, b.w)
    test = res["data"].subset(res["split"].test)
    got = cal.predict(test, method="psqmc", n_params=UQ["n_params"], n_qmc=UQ["n_qmc"], seed=UQ["seed"],
                      new_session=False)
    np.testing.assert_array_equal(got["calibrated"], res["hybrid"]["gaussian"].mean)
    # the ensemble's epistemic part is the pooled one (passes 5 + 4 over the two members)
    want = mc_predict(ens, network_inputs(test), passes=9, seed=1)
    np.testing.assert_allclose(got["epistemic_nn"], want.epistemic, rtol=1e-12)
    assert res["metrics"]["network"]["training"]["gaussian"]["conformal"]["ensemble_passes"] == [5, 4]


def test_single_network_calibration_of_the_previous_version_still_loads(ensemble_run, tmp_path):
    """A calibration written before ensembles (one network under network/..., format version 1) loads as
    one network and predicts with it."""
    from bayesmag._src.core.network import NetworkEnsemble, ResidualNetwork, mc_predict
    from bayesmag._src.core.predictor import network_inputs

    res, out = ensemble_run
    run = _copy(out, tmp_path)
    with np.load(run / "calibration.npz") as f:
        a = {(k.replace("network/member0/", "network/") if k.startswith("network/member0/") else k): f[k]
             for k in f.files if not k.startswith("network/member1/")}
    np.savez(run / "calibration.npz", **a)
    doc = json.loads((run / "calibration.json").read_text())
    doc["format_version"] = 1
    doc["network"].pop("members")
    doc["arrays"].pop("sha256")                 # written before the arrays' checksums were kept
    (run / "calibration.json").write_text(json.dumps(doc))
    cal = load(run)
    net = cal.predictor().network
    assert isinstance(net, ResidualNetwork) and not isinstance(net, NetworkEnsemble)
    test = res["data"].subset(res["split"].test)
    got = cal.predict(test, new_session=False)
    want = mc_predict(res["predictor"].network.members[0], network_inputs(test), passes=9, seed=1)
    np.testing.assert_allclose(got["epistemic_nn"], want.epistemic, rtol=1e-12)


def test_physics_and_single_network_calibrations_stay_format_1(tmp_path):
    _, out = _run(tmp_path, network={**ENS_NET, "interval_calibration": "none"})
    doc = json.loads((out / "calibration.json").read_text())
    assert doc["format_version"] == 1 and "members" not in doc["network"]
    assert "network/layer0/w" in np.load(out / "calibration.npz").files


def _tamper(run, drop=(), arrays=None, members="keep"):
    with np.load(run / "calibration.npz") as f:
        a = {k: f[k] for k in f.files if k not in drop}
    for k, v in (arrays or {}).items():
        a[k] = v(a[k]) if callable(v) else v
    np.savez(run / "calibration.npz", **a)
    if members != "keep":
        doc = json.loads((run / "calibration.json").read_text())
        doc["network"]["members"] = members
        (run / "calibration.json").write_text(json.dumps(doc))


def _nan_first(w):
    w = w.copy()
    w.flat[0] = np.nan
    return w


ENSEMBLE_TAMPER = {
    "members_more_than_saved": (dict(members=3), r"lacks network/member2/layer0/w"),
    "members_one": (dict(members=1), r"'network.members' = 1 must be an integer of at least 2"),
    "members_not_int": (dict(members="2"), r"'network.members' = '2' must be an integer"),
    "member_layer_missing": (dict(drop=("network/member1/layer1/w",)), r"lacks network/member1/layer1/w"),
    "member_nan": (dict(arrays={"network/member1/layer0/w": _nan_first}), r"'network/member1/layer0/w'.*NaN"),
    "member_shape": (dict(arrays={"network/member1/standardizer/x_mean": np.zeros(5)}),
                     r"member network/member1/ differs from member 0 .*standardizer/x_mean"),
    "member_width": (dict(arrays={"network/member1/layer0/w": lambda w: w[..., :4],
                                  "network/member1/layer0/b": lambda b: b[..., :4]}), r"member1/layer 1 .*do not chain"),
    "stray_array": (dict(arrays={"network/layer0/w": np.ones((3, 4, 8))}), r"outside the 2 ensemble members"),
    "members_lost": (dict(members=None), r"describes a network but|lacks network/layer0/w"),
}


@pytest.mark.parametrize("case", sorted(ENSEMBLE_TAMPER))
def test_tampered_ensemble_is_refused_naming_the_field(ensemble_run, tmp_path, case):
    _, out = ensemble_run
    run = _copy(out, tmp_path)
    kw, match = ENSEMBLE_TAMPER[case]
    _tamper(run, **kw)
    with pytest.raises(ArtifactError, match=match):
        load(run)


@pytest.mark.extended
def test_a_thermal_lag_job_is_fitted_and_scored_within_the_recording(tmp_path):
    """The held-out time blocks of a split are rows of the recording: a model with a thermal lag is fitted on the
    training rows within it and predicts the test rows within it, i.e. as the saved calibration predicts the whole
    recording at those rows (to 1e-9). On a 90 s lag campaign (sessions that differ by nothing) with the lag
    `bayesmag discover` named, cutting the series up gave: test RMSE 1.0 / 5.5 / 1.0 uT and coverage 58 % (each
    block predicted alone, the lag restarted as at a run start); tau 96-122 s (fitted on the training rows alone,
    the lag running across each held-out block as if the temperature had stopped); leave-one-run-out transfer sd
    1.0 / 4.4 / 0.52 uT, the hierarchical one 0.08 / 0.56 / 0.07; `export`'s full model 1.1 / 5.8 / 0.92 uT.
    Declared here: test RMSE under 0.15 uT and coverage over 90 % per axis (reading noise 0.05 uT), tau within 10 %
    of 90 s, both transfer sds under 0.1 uT (measured 0.057-0.060 and 0.013-0.015), the export's full-model RMSE
    within 5 % of the job's (the job's is the PS-QMC mean, the export's the point prediction)."""
    from bayesmag._src.app import export as E
    from bayesmag._src.core.data import split_time_blocks
    sim = {"design": "campaign", "n": 2400, "seed": 0, "noise_sd": 0.05,
           "effects": [{"name": "thermal_lag", "tau": 90.0}]}
    res, out = _run(tmp_path, sim=sim, uq={**UQ, "transfer": "hierarchical"},
                    physics={"t0": "mean", "extra_terms": [{"name": "thermal_lag", "tau0": 60.0}]})
    m = res["metrics"]["physics"]
    assert all(m["rmse"][ax] < 0.15 and m["coverage"][ax] > 0.9 for ax in "xyz"), m
    cal = load(out)
    tau = np.exp(cal.theta[:, list(cal.model.param_names).index("log_tau")])
    assert np.all(np.abs(tau / 90.0 - 1) < 0.1), tau
    tr = res["metrics"]["transfer"]
    assert tr["method"].startswith("hierarchical"), tr["method"]
    assert all(tr["sd"][ax] < 0.1 for ax in "xyz"), tr["sd"]
    assert all(v < 0.1 for v in tr["per_run"]["model"]["loro_sd"].values()), tr["per_run"]["model"]["loro_sd"]
    data = res["data"]
    test = split_time_blocks(data.run, test_fraction=0.2, seed=0).test
    np.testing.assert_array_equal(test, res["split"].test)
    whole = cal.predict(data, method="psqmc", n_params=UQ["n_params"], n_qmc=UQ["n_qmc"], seed=UQ["seed"],
                        new_session=False)
    np.testing.assert_allclose(res["uq"].mean, whole["calibrated"][test], rtol=1e-9, atol=1e-9)
    series = E.split_recording(cal)
    ex = E.build_export(cal, series[0].subset(series[1]), held_out=series[0].subset(series[2]), series=series)
    full = ex.accuracy["full_model_vs_reference"]
    assert all(abs(full[ax] / m["rmse"][ax] - 1) < 0.05 for ax in "xyz"), (full, m["rmse"])


def test_a_recording_whose_time_step_is_not_trainings_is_warned_about(tmp_path):
    """The rate limits are per second: a new recording with time in ms, or without a time column (rows 1 s apart),
    flagged different rows silently (186 / 8 / 0 of 600 rows for s / none / ms on a 4 Hz recording). The domain now
    keeps training's median step (saved with the calibration) and apply warns beyond 3x either way."""
    import dataclasses as dc

    from bayesmag._src.core.data import CalibrationData
    res, out = _run(tmp_path)
    cal = load(out)
    d = res["data"]
    step = np.median(np.diff(d.time)[d.run[1:] == d.run[:-1]])
    assert cal.domain.step == pytest.approx(step) and cal.domain.step == res["domain"].step
    assert cal.domain.step_note(d) is None
    assert "time step" in cal.domain.step_note(dc.replace(d, time=d.time * 1000.0))
    bare = CalibrationData(d.b_meas, d.temperature, None)                      # no time column: row index
    assert (cal.domain.step_note(dc.replace(bare, time_given=True)) is None) == (1 / 3 <= 1.0 / step <= 3)
    assert cal.domain.step_note(bare) is None       # rows without times: no rates checked (apply says so instead)


def test_an_edited_array_is_refused_by_its_checksum(tmp_path):
    """Before: theta[0, 0] x 1.5 in calibration.npz was applied (x RMSE 10.5 uT): plausible values pass the field
    checks. Each array's sha256 is kept in calibration.json; a file without them (older) still loads."""
    _, run = _run(tmp_path)
    with np.load(run / "calibration.npz") as f:
        a = {k: f[k] for k in f.files}
    a["theta"] = a["theta"].copy()
    a["theta"][0, 0] *= 1.5
    np.savez(run / "calibration.npz", **a)
    with pytest.raises(ArtifactError, match=r"\['theta'\] differ from the checksums"):
        load(run)
    doc = json.loads((run / "calibration.json").read_text())
    doc["arrays"].pop("sha256")
    (run / "calibration.json").write_text(json.dumps(doc))
    assert load(run).theta[0, 0] == a["theta"][0, 0]
