"""The scikit-learn estimator and the library's predict, as a Python user drives them (an outside smoke pass of the
estimator API found each case here silent or wrong; each test fails on the code before its fix)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import bayesmag
from bayesmag._src.app.calibrator import NotFittedError
from bayesmag._src.core.data import CalibrationData, DataError, DataNote
from bayesmag._src.core.domain import Domain

FAST = {"uq": {"n_params": 20, "n_qmc": 32, "seed": 0}}


@pytest.fixture(scope="module")
def data():
    return bayesmag.simulate.simulate(600, design="campaign", seed=1, noise_sd=0.05)


@pytest.fixture(scope="module")
def frame(data):
    return bayesmag.to_frame(data)


@pytest.fixture(scope="module")
def fitted(frame):
    return bayesmag.Calibrator(FAST).fit(frame)


def test_predict_honours_its_own_units(data, frame):
    """Before: ``predict(X, field_unit=...)`` used the constructor's unit: fitted on nT, given uT rows with
    ``field_unit="uT"``, every value was divided by 1000 again (errors up to 61 uT, every row in domain)."""
    nt = frame.copy()
    cols = [c for c in nt.columns if c.startswith(("bx", "by", "bz"))]
    nt[cols] = nt[cols] * 1000.0
    c = bayesmag.Calibrator(FAST, field_unit="nT").fit(nt)
    out = c.predict(frame, field_unit="uT")
    ref = bayesmag.Calibrator(FAST).fit(frame).predict(frame)
    np.testing.assert_allclose(out["x_calibrated"], ref["x_calibrated"], atol=1e-8)
    k = frame.assign(temperature=frame["temperature"] + 273.15)
    np.testing.assert_allclose(c.predict(k, field_unit="uT", temperature_unit="K")["y_calibrated"],
                               ref["y_calibrated"], atol=1e-8)


def test_a_dataframe_y_is_read_by_its_column_names(data, frame):
    """Before: y with columns ``bz_ref, by_ref, bx_ref`` was read by position (x and z swapped, score -9.95)."""
    X = frame.drop(columns=["bx_ref", "by_ref", "bz_ref"])
    y = frame[["bx_ref", "by_ref", "bz_ref"]]
    a = bayesmag.Calibrator(FAST).fit(X, y)
    b = bayesmag.Calibrator(FAST).fit(X, y[["bz_ref", "by_ref", "bx_ref"]])
    np.testing.assert_allclose(b.physics_fit_.theta, a.physics_fit_.theta, rtol=1e-12, atol=1e-12)
    with pytest.raises(DataError, match="cannot be matched"):
        bayesmag.Calibrator(FAST).fit(X, y.rename(columns={"bx_ref": "refX"}))
    unnamed = y.set_axis(["a", "b", "c"], axis=1)          # names that say nothing: by position, as scikit-learn
    np.testing.assert_allclose(bayesmag.Calibrator(FAST).fit(X, unnamed).physics_fit_.theta,
                               a.physics_fit_.theta, rtol=1e-12, atol=1e-12)


def test_a_second_reference_in_x_is_named(frame):
    """Before: ``fit(X_with_reference, y)`` used y silently where the two differ."""
    y = frame[["bx_ref", "by_ref", "bz_ref"]] * 1.1
    with pytest.warns(DataNote, match="y is the reference used"):
        bayesmag.Calibrator(FAST).fit(frame, y)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataNote)
        bayesmag.Calibrator(FAST).fit(frame, frame[["bx_ref", "by_ref", "bz_ref"]])     # the same: no note


def test_rows_without_times_get_no_rate_flags(data, frame, fitted, tmp_path):
    """Before: without a time column the rows were 1 s apart (row index) and 175 of 422 rows were flagged
    ``field_rate`` / ``temperature_rate`` by ``Calibrator.predict`` and ``bayesmag apply``; ``load().predict`` of the
    same frame flagged none."""
    every8 = frame.iloc[::8]                 # 2 s apart: one row per "second" read their rates 8x too high
    no_time = every8.drop(columns=["time"])
    reasons = fitted.predict(no_time)["in_domain_reason"].astype(str)
    assert not any("rate" in r for r in reasons)             # before: 27 of 75 rows flagged
    with_time = fitted.predict(every8)
    assert (with_time["in_domain_reason"].astype(str) == reasons).all()      # these rows are inside: same flags
    d = CalibrationData(data.b_meas, data.temperature, data.b_ref)
    assert not d.time_given and data.time_given and d.subset(np.arange(5)).time_given is False
    assert Domain.from_data(d).rate_high is None            # rows without times give no rate limits either
    path = tmp_path / "no_time.csv"
    no_time.to_csv(path, index=False)
    run = tmp_path / "cal"
    fitted.save(run)
    from bayesmag._src.app.apply import apply_calibration
    s = apply_calibration(run, path, tmp_path / "out.csv", n_params=10, n_qmc=16)
    assert any("no time column" in w and "time column is nan" in w for w in s["warnings"])
    assert not any(k.endswith("rate") for k in s["outside_domain_by_reason"])
    import pandas as pd
    assert pd.read_csv(tmp_path / "out.csv")["time"].isna().all()            # before: 0, 1, 2, ... (the row index)


def test_network_settings_likelihood_is_honoured_or_refused():
    """Before: ``NetworkSettings(likelihood="laplace")`` trained a Gaussian network without a word."""
    assert bayesmag.NetworkSettings(likelihood="laplace").likelihoods == ("laplace",)
    assert bayesmag.NetworkSettings(likelihood="laplace", likelihoods=("gaussian", "laplace")).likelihoods == \
        ("gaussian", "laplace")
    with pytest.raises(ValueError, match="likelihoods=\\('laplace',\\)"):
        bayesmag.NetworkSettings(likelihood="laplace", likelihoods=("gaussian", "student_t"))


def test_estimator_contract(frame, fitted, tmp_path):
    """scikit-learn's conventions the smoke pass found broken: NotFittedError, regressor tags, a refit keeping the
    last fit's ``run_dir_``, ``overrides`` given as one string, the saved config naming simulated data."""
    with pytest.raises(NotFittedError) as e:
        bayesmag.Calibrator().predict(frame)
    assert isinstance(e.value, (ValueError, AttributeError, RuntimeError))
    c = bayesmag.Calibrator(FAST, out=tmp_path / "a").fit(frame)
    assert c.run_dir_ == tmp_path / "a" / "run"
    c.set_params(out=None).fit(frame)
    assert not hasattr(c, "run_dir_")
    t = bayesmag.Calibrator(FAST, "physics.temperature_terms=false").fit(frame)
    assert "Ks_x" not in set(t.params_["parameter"])
    cfg = (fitted.save(tmp_path / "saved") / "config.resolved.toml").read_text()
    assert "simulated" not in cfg and "no [data] source" in cfg
    assert "source" not in (bayesmag.load(tmp_path / "saved").config or {}).get("data", {})


def test_output_field_works_with_scikit_learn_metrics(frame):
    """Before: ``predict`` returned 27 columns (one of text) and ``cross_val_score(scoring="neg_mean_squared_error")``,
    ``r2_score`` and ``cross_val_predict`` failed; ``output="field"`` returns the (n, 3) field they expect."""
    sk = pytest.importorskip("sklearn")
    from sklearn.model_selection import GroupKFold, cross_val_predict, cross_val_score
    from sklearn.utils import get_tags
    assert sk and get_tags(bayesmag.Calibrator()).regressor_tags is not None
    X = frame.drop(columns=["bx_ref", "by_ref", "bz_ref"])
    y = frame[["bx_ref", "by_ref", "bz_ref"]]
    est = bayesmag.Calibrator(FAST, output="field")
    s = cross_val_score(est, X, y, groups=frame["run"], cv=GroupKFold(3), scoring="neg_mean_squared_error")
    assert s.shape == (3,) and np.all(s < 0) and np.all(s > -1.0)
    p = cross_val_predict(est, X, y, groups=frame["run"], cv=GroupKFold(3))
    assert p.shape == (len(frame), 3) and p.dtype == np.float64
    with pytest.raises(ValueError, match="output"):
        bayesmag.Calibrator(FAST, output="df").fit(frame).predict(frame)


@pytest.mark.parametrize("entry", ["frame", "array", "apply"])
def test_celsius_declared_as_kelvin_is_refused(frame, fitted, tmp_path, entry):
    """Before: ``--temperature-unit K`` on Celsius data read -250 C and calibrated every row (all out of domain,
    coverage 0-5 %), nothing naming the temperature."""
    with pytest.raises(DataError, match="look like Celsius already"):
        if entry == "frame":
            fitted.predict(frame, temperature_unit="K")
        elif entry == "array":
            from bayesmag._src.core.frames import as_calibration_data
            as_calibration_data(frame[["bx_meas", "by_meas", "bz_meas", "temperature"]].to_numpy(), temperature_unit="K")
        else:
            from bayesmag._src.app.apply import apply_calibration
            frame.to_csv(tmp_path / "c.csv", index=False)
            apply_calibration(fitted.save(tmp_path / "cal"), tmp_path / "c.csv", tmp_path / "o.csv", temperature_unit="K")


def test_a_parquet_file_missing_a_column_is_named(frame, tmp_path):
    """Before: "the DataFrame has no column 'temperature' ... or a columns= mapping", neither the file nor --columns."""
    pytest.importorskip("pyarrow")
    from bayesmag._src.core.frames import load_table
    frame.drop(columns=["temperature"]).to_parquet(tmp_path / "r.parquet", index=False)
    with pytest.raises(DataError, match=r"r\.parquet has no column 'temperature'.*--columns"):
        load_table(tmp_path / "r.parquet")


def _tree(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.extended
def test_save_never_replaces_a_run_or_a_saved_calibration_unless_overwrite(data, fitted, tmp_path, capsys):
    """Seventh outside pass: ``Calibrator.save(path)`` into a complete ``bayesmag run`` folder replaced it (report,
    predictions, metrics gone) without a word. Now the ``--out`` rules: a complete bayesmag result is replaced only
    with ``overwrite=True`` (a refit with ``out=`` replaces its own earlier save, never a run), a folder with the
    user's files never, and ``bayesmag run --out`` never replaces a saved calibration."""
    from helpers import SMALL_JOB_CONFIG

    from bayesmag._src.app.cli import main
    from bayesmag._src.app.outdir import MARKER, OccupiedError, OutputError
    rec = tmp_path / "rec.csv"
    bayesmag.write_csv(data, rec)
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(SMALL_JOB_CONFIG.format(data=rec))
    run = tmp_path / "out" / "run"
    assert main(["run", str(cfg), "--out", str(run), "--no-progress"]) == 0
    before = _tree(run)
    assert "report.md" in before and "predictions.csv" in before
    with pytest.raises(OccupiedError) as e:
        fitted.save(run)
    msg = str(e.value)
    assert f"{run} holds a calibration run (`bayesmag run`)" in msg and "overwrite=True" in msg
    assert "--out" not in msg and f"{run}_2" in msg
    with pytest.raises(OccupiedError, match="out="):                    # fit(out=) into the run's parent: refused
        bayesmag.Calibrator(FAST, out=tmp_path / "out").fit(data)
    assert _tree(run) == before                                          # byte-identical, nothing computed over it

    saved = tmp_path / "saved"
    fitted.save(saved)
    with pytest.raises(OccupiedError, match="a calibration saved from Python"):
        fitted.save(saved)                                               # an earlier save is a complete calibration
    assert main(["run", str(cfg), "--out", str(saved), "--no-progress"]) == 2   # the CLI never replaces it either
    assert "holds a calibration saved from Python" in capsys.readouterr().err
    c = bayesmag.Calibrator(FAST, out=tmp_path / "own").fit(data)
    c.fit(data)                                                          # a refit replaces its own earlier save

    assert fitted.save(run, overwrite=True) == run                       # asked for: replaced
    assert "report.md" not in _tree(run) and bayesmag.load(run).theta.shape == fitted.calibration_.theta.shape
    assert json.loads((run / MARKER).read_text())["kind"] == "calibrator"
    (saved / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="notes.txt") as e:
        fitted.save(saved, overwrite=True)                               # never a file bayesmag did not write
    assert not isinstance(e.value, OccupiedError) and (saved / "notes.txt").read_text() == "mine"
