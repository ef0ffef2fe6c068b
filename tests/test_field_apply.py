"""`bayesmag apply` with a field calibration (app/field_apply.py, core/field_calibration.py): a new recording of the
same sensor calibrated against the simulated truth, the job's own held-out predictions reproduced, the domain
flags, and the errors."""

import csv
import json

import numpy as np
import pytest

import bayesmag
from bayesmag._src.app.apply import apply_calibration
from bayesmag._src.app.cli import main
from bayesmag._src.core.field_calibration import DOMAIN_KEYS, FieldCalibration


def _write(path, c, rows, *, scalar=True, ref=False):
    head = ["time", "run", "bx_meas", "by_meas", "bz_meas", "temperature"] + (["F_ovh"] if scalar else [])
    head += ["bx_ref", "by_ref", "bz_ref"] if ref else []
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        for i in rows:
            row = [c.data.time[i], c.data.run[i], *c.data.b_meas[i], c.data.temperature[i]]
            row += [c.f_ref[i]] if scalar else []
            row += list(c.data.b_ref[i]) if ref else []
            w.writerow([repr(float(v)) for v in row])
    return path


def _cfg(path, **meas):
    from bayesmag._src.app.config import config_from_dict
    return config_from_dict({"name": "scalar_csv", "data": {"path": str(path)},
                             "measurement": {"kind": "scalar", "scalar_column": "F_ovh", "exports": ["json"], **meas},
                             "split": {"kind": "time_blocks", "test_fraction": 0.2, "n_blocks": 2},
                             "physics": {"t0": "mean"}, "output": {"figures": False, "progress": False}})


@pytest.fixture(scope="module")
def field_run(tmp_path_factory):
    """One dance (15 -> 35 C): its first 1500 rows calibrated against their scalar column, the last 600 (30-35 C,
    partly above the training temperatures) kept back as a new recording of the same sensor."""
    from bayesmag.simulate import simulate_field
    tmp = tmp_path_factory.mktemp("field_apply")
    c = simulate_field("dance", n=2100, seed=4, temperature=(15.0, 35.0))
    train = _write(tmp / "train.csv", c, range(1500))
    new = _write(tmp / "new.csv", c, range(1500, 2100))
    res = bayesmag.run_job(_cfg(train), tmp / "run")
    return {"c": c, "tmp": tmp, "run": tmp / "run", "train": train, "new": new, "res": res}


def _read(path):
    with open(path) as fh:
        r = list(csv.reader(fh))
    return r[0], np.array(r[1:], float)


def test_apply_reproduces_the_runs_held_out_predictions(field_run, capsys):
    """The run's predictions.csv (held-out rows of the training recording) is what apply gives those rows."""
    run, tmp = field_run["run"], field_run["tmp"]
    assert main(["apply", "--model", str(run), "--data", str(field_run["train"]), "--out", str(tmp / "a.csv"),
                 "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "reference magnitude from the scalar column 'F_ovh'" in out, out
    head, a = _read(tmp / "a.csv")
    assert head[:2] == ["time", "run"] and head[-3:] == ["in_domain_reason", "in_domain", "valid"]
    with open(run / "predictions.csv") as fh:
        p = list(csv.DictReader(fh))
    rows = np.array([int(r["row"]) for r in p])
    col = {h: a[:, j] for j, h in enumerate(head)}
    for mine, theirs in (("magnitude", "predicted_magnitude"), ("magnitude_total", "total"),
                         ("magnitude_lower", "lower"), ("magnitude_upper", "upper")):
        np.testing.assert_allclose(col[mine][rows], [float(r[theirs]) for r in p], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(col["in_domain"][rows].astype(bool), [r["in_domain"] == "True" for r in p])


def test_a_new_recording_of_the_same_sensor_is_calibrated_to_the_truth(field_run):
    """Against the simulation's truth: |B| within the noise, intervals covering in domain, and the calibrated
    vector equal to the true field up to one rotation (the gauge; Procrustes), rows above training's temperature
    flagged with code 2."""
    c, tmp = field_run["c"], field_run["tmp"]
    s = apply_calibration(field_run["run"], field_run["new"], tmp / "b.csv")
    head, a = _read(tmp / "b.csv")
    col = {h: a[:, j] for j, h in enumerate(head)}
    idx = np.arange(1500, 2100)
    dom = col["in_domain"].astype(bool)
    hot = c.data.temperature[idx] > field_run["res"]["stage"].train.temperature.max() + 1.5
    assert hot.any() and not dom[hot].any()
    assert np.all(col["in_domain_reason"][hot].astype(int) & 2)
    truth = np.linalg.norm(c.data.b_ref[idx], axis=1)
    err = col["magnitude"] - truth
    assert np.sqrt(np.mean(err[dom] ** 2)) < 0.15, np.sqrt(np.mean(err[dom] ** 2))
    inside = (truth >= col["magnitude_lower"]) & (truth <= col["magnitude_upper"])
    assert inside[dom].mean() >= 0.85, inside[dom].mean()
    # the calibrated vector is the true field in the gauge frame: one rotation R maps it (orthogonal Procrustes)
    B = np.column_stack([col[f"{x}_calibrated"] for x in "xyz"])[dom]
    T = c.data.b_ref[idx][dom]
    U, _, Vt = np.linalg.svd(B.T @ T)
    R = U @ Vt
    assert np.sqrt(np.mean((B @ R - T) ** 2)) < 0.3
    m = s["magnitude_metrics"]
    assert m["reference"].startswith("the scalar column") and m["n"] == 600
    assert s["outside_domain_by_reason"].get("temperature", 0) >= hot.sum()


def test_the_saved_calibration_round_trips_and_matches_the_fit(field_run):
    """``bayesmag.load_field`` gives the fit's own predictions (library and file agree to 1e-12)."""
    cal = bayesmag.load_field(field_run["run"])
    fit = field_run["res"]["stage"].fit
    c = field_run["c"]
    u, t = c.data.b_meas[:50], c.data.temperature[:50]
    np.testing.assert_allclose(cal.fit.calibrate(u, t), fit.calibrate(u, t), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(cal.fit.cov, fit.cov, rtol=1e-12)
    p = cal.predict(u, t)
    np.testing.assert_allclose(p["magnitude_total"], cal.interval_scale * fit.predict_magnitude(u, t)["total"],
                               rtol=1e-12)
    again = FieldCalibration.from_json(json.loads(json.dumps(cal.to_json())))
    np.testing.assert_allclose(again.predict(u, t)["magnitude_upper"], p["magnitude_upper"], rtol=1e-12)
    assert set(cal.ranges) == set(DOMAIN_KEYS)


def test_rows_with_a_non_finite_reading_are_marked_invalid(field_run):
    cal = bayesmag.load_field(field_run["run"])
    c = field_run["c"]
    u, t = c.data.b_meas[:5].copy(), c.data.temperature[:5].copy()
    u[1, 2], t[3] = np.nan, np.inf
    p = cal.predict(u, t)
    assert p["valid"].tolist() == [True, False, True, False, True]
    assert np.isnan(p["magnitude"][[1, 3]]).all() and np.isfinite(p["magnitude"][[0, 2, 4]]).all()
    assert not p["in_domain"][[1, 3]].any()


@pytest.mark.parametrize("edit, match", [
    (lambda d: {k: v for k, v in d.items() if k != "cov"}, r"lacks \['cov'\].*re-run"),
    (lambda d: {k: v for k, v in d.items() if k != "predictive"}, r"no 'predictive' section.*re-run"),
    (lambda d: {**d, "theta": d["theta"][:-1]}, r"'theta' must have shape \(18,\)"),
    (lambda d: {**d, "format_version": 99}, r"format_version 99.*upgrade"),
    (lambda d: {**d, "predictive": {**d["predictive"], "interval_scale": -1}}, r"interval_scale -1"),
    # hand edits an outside smoke pass made, each of which ran to wrong numbers with exit status 0
    (lambda d: {**d, "t0": float("nan")}, r"'t0' = nan must be a finite"),
    (lambda d: {**d, "theta": [float("nan")] + d["theta"][1:]}, r"'theta' holds NaN or inf at index \[0\]"),
    (lambda d: {**d, "cov": [[-abs(d["cov"][0][0])] + d["cov"][0][1:]] + d["cov"][1:]}, r"positive semi-definite"),
    (lambda d: {**d, "cov": [[d["cov"][0][0], d["cov"][0][1] + 1e-3] + d["cov"][0][2:]] + d["cov"][1:]},
     r"not a symmetric"),
    (lambda d: {**d, "s2": 0.0}, r"'s2' = 0.0 must be a positive noise variance"),
    (lambda d: {**d, "predictive": {**d["predictive"], "interval_scale": 1e6}}, r"interval_scale 1000000.0 must be"),
    (lambda d: {**d, "theta": d["theta"][:12] + [1e9] + d["theta"][13:]}, r"offsets O = .* are not a sensor's"),
    (lambda d: {**d, "predictive": {**d["predictive"], "domain_ranges": {
        **d["predictive"]["domain_ranges"], "temperature": [50.0, 10.0]}}}, r"domain_ranges \['temperature'\]"),
    (lambda d: {**d, "predictive": {**d["predictive"], "transfer": {"sd": -0.2, "method": "leave_one_run_out"}}},
     r"'predictive.transfer' must be null or .*-0.2"),
    (lambda d: {**d, "predictive": {**d["predictive"], "transfer": {"sd": float("nan"), "method": "x"}}},
     r"'predictive.transfer' must be null"),
    # edits that pass every range check (an outside tester's: each was applied with exit 0): the content hash
    (lambda d: {**d, "theta": d["theta"][:12] + [d["theta"][12] + 1.0] + d["theta"][13:]}, r"edited or damaged"),
    (lambda d: {**d, "s2": d["s2"] / 100}, r"edited or damaged.*content_sha256"),
    (lambda d: {**d, "predictive": {**d["predictive"], "interval_scale": 0.1}}, r"edited or damaged"),
])
def test_a_damaged_or_old_field_calibration_is_named(field_run, tmp_path, capsys, edit, match):
    import shutil
    run = tmp_path / "run"
    shutil.copytree(field_run["run"], run)
    doc = json.loads((run / "field_params.json").read_text())
    (run / "field_params.json").write_text(json.dumps(edit(doc)))
    assert main(["apply", "--model", str(run), "--data", str(field_run["new"]), "--out", str(tmp_path / "o.csv"),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "field_params.json" in err and len(err.strip().splitlines()) == 1, err
    import re
    assert re.search(match, err), err
    assert not (tmp_path / "o.csv").exists()


def test_field_apply_never_overwrites_the_training_recording_or_a_run_file(field_run, capsys):
    before = field_run["train"].read_bytes()
    for out in (field_run["train"], field_run["run"] / "metrics.json"):
        assert main(["apply", "--model", str(field_run["run"]), "--data", str(field_run["new"]), "--out", str(out),
                     "--force", "--no-progress"]) == 2
    assert field_run["train"].read_bytes() == before


def test_a_field_run_on_dask_says_what_to_do(field_run, tmp_path, capsys):
    pytest.importorskip("dask")
    assert main(["apply", "--model", str(field_run["run"]), "--data", str(field_run["new"]), "--out",
                 str(tmp_path / "parts"), "--scheduler", "tcp://127.0.0.1:1", "--no-progress"]) == 2
    assert "field-calibration run" in capsys.readouterr().err


@pytest.mark.extended
def test_a_free_field_calibration_says_its_magnitudes_are_relative(tmp_path):
    from bayesmag._src.app.config import config_from_dict
    from bayesmag.simulate import simulate_field
    c = simulate_field("dance", n=900, seed=1, temperature=(15.0, 35.0))
    rec = _write(tmp_path / "r.csv", c, range(900), scalar=False)
    cfg = config_from_dict({"name": "free", "data": {"path": str(rec)},
                            "measurement": {"kind": "constant", "field": "free", "exports": ["json"]},
                            "split": {"kind": "time_blocks", "test_fraction": 0.2, "n_blocks": 2},
                            "physics": {"t0": "mean"}, "output": {"figures": False, "progress": False}})
    bayesmag.run_job(cfg, tmp_path / "run")
    s = apply_calibration(tmp_path / "run", rec, tmp_path / "o.csv")
    assert any("relative" in w for w in s["warnings"]) and "magnitude_metrics" not in s
    ref = _write(tmp_path / "ref.csv", c, range(900), scalar=False, ref=True)      # a reference in uT: not scored
    s = apply_calibration(tmp_path / "run", ref, tmp_path / "o2.csv")
    assert "magnitude_metrics" not in s and any("relative" in n for n in s["notes"]), s["notes"]


def test_readings_must_be_rows_of_three(field_run):
    """A (3, n) array was reshaped into rows silently (magnitudes of 17-86 uT from a 50 uT field)."""
    cal = bayesmag.load_field(field_run["run"])
    u, t = field_run["c"].data.b_meas[:5], field_run["c"].data.temperature[:5]
    with pytest.raises(ValueError, match=r"\(n, 3\).*shape \(3, 5\).*transposed"):
        cal.predict(u.T, t)
    with pytest.raises(ValueError, match="one value per reading"):
        cal.predict(u, t[:4])


def test_the_training_recording_is_protected_from_another_folder(field_run, tmp_path, monkeypatch, capsys):
    """The run was given a relative [data] path; apply from another folder resolved it there and replaced the
    training recording (vector and field apply, and export). The run's marker now records where it started."""
    import shutil
    work = tmp_path / "work"
    work.mkdir()
    shutil.copy(field_run["train"], work / "train.csv")
    shutil.copy(field_run["new"], work / "new.csv")
    monkeypatch.chdir(work)
    cfg = _cfg("train.csv")
    bayesmag.run_job(cfg, work / "run")
    before = (work / "train.csv").read_bytes()
    monkeypatch.chdir(tmp_path)
    assert main(["apply", "--model", "work/run", "--data", "work/new.csv", "--out", "work/train.csv", "--force",
                 "--no-progress"]) == 2
    assert "trained on" in capsys.readouterr().err
    assert (work / "train.csv").read_bytes() == before


def test_the_reference_column_is_scored_where_it_can_be_and_said_where_not(field_run, tmp_path, capsys):
    """The scalar column in nT, with empty or zero cells, semicolon-separated, or absent: the rows are calibrated
    (one output, exit status 0) and the score is given on the usable rows or skipped with a note saying why. Before:
    an nT column scored as 'RMSE 5e4 uT, coverage 0 %'; a NaN cell failed after the output was written; a
    semicolon file was not scored."""
    lines = field_run["new"].read_text().splitlines()
    head = lines[0].split(",")
    j = head.index("F_ovh")

    def variant(name, edit, sep=","):
        rows = [r.split(",") for r in lines[1:]]
        for i, r in enumerate(rows):
            edit(i, r)
        (tmp_path / name).write_text("\n".join(sep.join(r) for r in [head] + rows) + "\n")
        return tmp_path / name

    def run(path):
        out = tmp_path / (path.stem + ".out.csv")
        rc = main(["apply", "--model", str(field_run["run"]), "--data", str(path), "--out", str(out), "--no-progress"])
        text = capsys.readouterr()
        assert rc == 0 and out.exists(), text.err
        return text.out

    def n_t(i, r):
        r[j] = repr(float(r[j]) * 1000)

    def holes(i, r):
        if i in (5, 9):
            r[j] = "" if i == 5 else "0"
    out = run(variant("nT.csv", n_t))
    assert "not scored" in out and "looks like nT" in out and "RMSE" not in out, out
    out = run(variant("holes.csv", holes))
    assert "2 row(s) of column 'F_ovh' hold no positive finite magnitude" in out and "(598 rows)" in out, out
    out = run(variant("semi.csv", lambda i, r: None, sep=";"))
    assert "reference magnitude from the scalar column 'F_ovh' (600 rows)" in out, out
    no_f = tmp_path / "noF.csv"
    no_f.write_text("\n".join(",".join(c for k, c in enumerate(line.split(",")) if k != j) for line in lines) + "\n")
    out = run(no_f)
    assert "not scored: the recording has neither bx_ref" in out and "RMSE" not in out, out
    assert "gauge frame" in out


def test_vector_only_options_and_a_missing_field_params_file_are_named(field_run, tmp_path, capsys):
    import shutil
    s = apply_calibration(field_run["run"], field_run["new"], tmp_path / "o.csv",
                                                  method="psqmc", n_qmc=10)
    assert any("--uq, --n-qmc" in w and "ignored" in w for w in s["warnings"]), s["warnings"]
    run = tmp_path / "run"
    shutil.copytree(field_run["run"], run)
    (run / "field_params.json").unlink()
    assert main(["apply", "--model", str(run), "--data", str(field_run["new"]), "--out", str(tmp_path / "p.csv"),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "field_params.json is missing from this field-calibration run" in err, err


def test_another_sites_field_is_named_as_such_not_as_extrapolation(tmp_path):
    """A flight of the same sensor at a site whose field is 48 uT (training: 50 uT): every row was flagged
    `magnitude` with "their values are extrapolation and their intervals may be far too narrow", while the
    magnitude intervals covered 95 % there. The flag stays; the warning now says what a whole recording flagged
    only for its magnitude usually is."""
    from bayesmag.simulate import simulate_field
    train = simulate_field("two_temperature", n=2000, sensor_seed=7, seed=1)
    site = simulate_field("two_temperature", n=1000, sensor_seed=7, seed=9, field=48.0)
    bayesmag.run_job(_cfg(_write(tmp_path / "train.csv", train, range(2000))), tmp_path / "run")
    s = apply_calibration(tmp_path / "run", _write(tmp_path / "site.csv", site, range(1000)), tmp_path / "o.csv")
    assert s["outside_domain_by_reason"] == {"magnitude": s["n_outside_domain"]} and s["n_outside_domain"] > 900
    msg = next(w for w in s["warnings"] if "in_domain=false" in w)
    assert "flagged magnitude (in_domain=false) only" in msg and "another site" in msg and "extrapolation" not in msg
    assert s["magnitude_metrics"]["coverage"] >= 0.9                     # the calibration holds there
