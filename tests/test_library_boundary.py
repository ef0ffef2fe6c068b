"""The library's boundary checks, as the command line's: what a Python caller gets for bad input and for a
calibration that should not be trusted (an outside smoke pass of the Python API found each case here silent,
wrong or unclear; each test fails on the code before its fix)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import bayesmag
from bayesmag._src.core.data import CalibrationData, DataError
from bayesmag import CalibrationWarning
from bayesmag.field import Constant, FieldCalibration, Scalar, fit_field
from bayesmag.simulate import simulate_field

FAST = {"n_params": 20, "n_qmc": 32, "seed": 0}


@pytest.fixture(scope="module")
def data():
    return bayesmag.simulate.simulate(900, design="campaign", seed=0, noise_sd=0.05)


def _settings():
    return bayesmag.CalibrationSettings(uq=bayesmag.UQSettings(method="analytic"))


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("entry", ["calibrate", "fit_physics"])
def test_a_nan_reading_is_refused_naming_row_and_column(data, entry):
    """Before: numpy's LinAlgError 'SVD did not converge' with no row or column."""
    b = data.b_meas.copy()
    b[10, 1] = np.nan
    bad = CalibrationData(b, data.temperature, data.b_ref, data.time, data.run)
    fn = bayesmag.calibrate if entry == "calibrate" else bayesmag.fit_physics
    with pytest.raises(DataError, match=r"by_meas.*row\(s\) 11"):
        fn(bad)


def test_calibrate_refuses_a_field_in_nt_and_a_temperature_in_kelvin(data):
    nt = CalibrationData(data.b_meas * 1e3, data.temperature, data.b_ref * 1e3, data.time, data.run)
    with pytest.raises(DataError, match="nT"):
        bayesmag.calibrate(nt, _settings())
    kelvin = CalibrationData(data.b_meas, data.temperature + 273.15, data.b_ref, data.time, data.run)
    with pytest.raises(DataError, match="kelvin"):
        bayesmag.calibrate(kelvin, _settings())


def test_y_with_another_index_than_x_is_refused(data):
    """Before: y was paired with X by position after a shuffle: S_xx -0.05 instead of 1.1, no word."""
    df = bayesmag.to_frame(data)
    X, y = df.drop(columns=["bx_ref", "by_ref", "bz_ref"]), df[["bx_ref", "by_ref", "bz_ref"]]
    with pytest.raises(DataError, match=r"different indexes.*y.loc\[X.index\]"):
        bayesmag.Calibrator().fit(X, y.sample(frac=1.0, random_state=0))
    bayesmag.Calibrator().fit(X, y.loc[X.index])                        # aligned: fits


def test_a_non_finite_y_is_named_as_y(data):
    df = bayesmag.to_frame(data)
    y = df[["bx_ref", "by_ref", "bz_ref"]].to_numpy().copy()
    y[5, 2] = np.inf
    with pytest.raises(DataError, match=r"y \(the reference field\).*bz_ref.*row\(s\) 6"):
        bayesmag.Calibrator().fit(np.c_[data.b_meas, data.temperature], y)


def test_the_calibrator_refuses_rows_out_of_time_order_where_the_config_needs_them(data):
    """Before: the time-block split of ``honest_physics`` ran on shuffled rows (a random split in effect: coverage
    100 % on every axis) while ``bayesmag run`` refused the same file."""
    df = bayesmag.to_frame(data).sample(frac=1.0, random_state=0)
    with pytest.raises(DataError, match="not sorted.*time-block split"):
        bayesmag.Calibrator("honest_physics", holdout="config").fit(df)


# --------------------------------------------------------------------------- untrustworthy calibrations
def test_too_few_rows_and_no_temperature_span_warn_at_the_callers_line(data):
    """Before: 10 rows (2 residual dof, 0.002 C) gave Ko = -15872 +- 9193 uT/C with no warning."""
    ten = data.subset(np.arange(10))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run = bayesmag.calibrate(ten, _settings())
    ours = [w for w in caught if issubclass(w.category, CalibrationWarning)]
    text = " ".join(str(w.message) for w in ours)
    assert "10 rows for 8 parameters" in text and "temperature spans only" in text
    assert all(w.filename == __file__ for w in ours)                   # the user's line, not the library's
    assert {str(w.message) for w in ours} == set(run.warnings)
    assert len(run.fit.design_warnings) == 2


def test_a_well_designed_campaign_has_no_design_warning(data):
    run = bayesmag.calibrate(data, _settings())
    assert run.fit.design_warnings == ()


def test_one_training_run_warns_that_there_is_no_between_session_term(data):
    one = data.subset(np.flatnonzero(data.run == data.run[0]))
    with pytest.warns(CalibrationWarning, match="no between-session term"):
        bayesmag.Calibrator().fit(one)


def test_the_command_line_prints_a_run_warning_once(tmp_path, capsys):
    from bayesmag._src.app.cli import main
    d = bayesmag.simulate.simulate(300, design="campaign", seed=1)
    one = d.subset(np.flatnonzero(d.run == d.run[0]))
    bayesmag.write_csv(one, tmp_path / "one.csv")
    rc = main(["run", "paper_physics", "--set", f"data.path={tmp_path / 'one.csv'}", "--set", "uq.method=\"analytic\"",
               "--set", "output.figures=false", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert rc == 0 and err.count("no between-session term") == 1, err


# --------------------------------------------------------------------------- field API
@pytest.fixture(scope="module")
def field():
    c = simulate_field("two_temperature", n=400, seed=11)
    return c, fit_field(c.data.b_meas, c.data.temperature, c.f_ref, Scalar())


@pytest.mark.parametrize("case, match", [("nT", "nT"), ("gauss", "gauss"), ("kelvin", "kelvin"),
                                         ("reference nT", "reference")])
def test_fit_field_checks_units_as_the_command_line(field, case, match):
    """Before: readings in nT converged to S_xx = 0.00098; in gauss 'tilt or tumble' notes; kelvin kept."""
    c, _ = field
    u, t, f = c.data.b_meas, c.data.temperature, c.f_ref
    u, t, f = {"nT": (u * 1e3, t, f), "gauss": (u / 100, t, f), "kelvin": (u, t + 273.15, f),
               "reference nT": (u, t, f * 1e3)}[case]
    with pytest.raises(DataError, match=match):
        fit_field(u, t, f, Scalar())


def test_fit_field_trusts_a_declared_low_field(field):
    c, ref = field
    weak = fit_field(c.data.b_meas / 100, c.data.temperature, np.full(c.data.n, 0.5), Constant(0.5), field_unit="uT")
    assert weak.converged


def test_a_field_calibration_refuses_readings_in_another_unit(field):
    c, fit = field
    u = c.data.b_meas
    cal = FieldCalibration(fit, 1.0, 0.95, {"bx_meas": (-60, 60), "by_meas": (-60, 60), "bz_meas": (-60, 60),
                                            "temperature": (-10, 50), "magnitude": (40, 60)})
    with pytest.raises(DataError, match="nT"):
        cal.predict(u * 1e3, c.data.temperature)
    with pytest.raises(DataError, match="kelvin"):
        cal.predict(u, c.data.temperature + 273.15)
    assert np.isfinite(cal.predict(u, c.data.temperature)["magnitude"]).all()
    assert len(repr(cal)) < 300                                         # not the covariance matrices


# --------------------------------------------------------------------------- consistency
def test_rates_are_checked_only_where_the_rows_have_times(data):
    """Before: the same rows got 99 rate flags as CalibrationData and 54 as an (n, 4) array (time taken as the row
    index there)."""
    cal = bayesmag.Calibrator().fit(data).calibration_
    new = bayesmag.simulate.simulate(300, design="campaign", seed=7, noise_sd=0.05)
    timed = cal.predict(new)
    assert any("rate" in r for r in timed["in_domain_reason"])          # the case: rates flag rows here
    arr = cal.predict(np.c_[new.b_meas, new.temperature])
    untimed_frame = cal.predict(bayesmag.to_frame(new).drop(columns=["time"]))
    for r in (arr["in_domain_reason"], untimed_frame["in_domain_reason"]):
        assert not any("rate" in x for x in r)
    values_only = np.array([";".join(k for k in x.split(";") if "rate" not in k) for x in timed["in_domain_reason"]])
    np.testing.assert_array_equal(np.asarray(arr["in_domain_reason"]), values_only)
    assert cal.predict(new, check_rates=False)["in_domain"].sum() == arr["in_domain"].sum()


def test_load_config_takes_a_packaged_name_as_the_command_line_does():
    assert bayesmag.load_config("quickstart").name == "quickstart"


def test_simulate_takes_effects_as_config_tables():
    from bayesmag._src.core.simulate import get_effect
    a = bayesmag.simulate.simulate(200, seed=1, effects=[{"name": "axis_quadratic", "coeff": 0.02}])
    b = bayesmag.simulate.simulate(200, seed=1, effects=[get_effect("axis_quadratic", coeff=0.02)])
    np.testing.assert_array_equal(a.b_meas, b.b_meas)
    with pytest.raises(TypeError, match="'name'"):
        bayesmag.simulate.simulate(200, seed=1, effects=[{"coeff": 0.02}])


def test_float32_entry_points_warn(field, monkeypatch):
    """``Calibrator.fit`` and ``field.fit_field`` computed in float32 without a word (``calibrate`` warned)."""
    import jax
    from bayesmag._src.core import precision
    with jax.enable_x64(False):
        with pytest.warns(bayesmag.Float64Warning, match="Calibrator.fit.*float32"):
            precision.warn_if_float32("Calibrator.fit")
    with warnings.catch_warnings():
        warnings.simplefilter("error", bayesmag.Float64Warning)
        precision.warn_if_float32("Calibrator.fit")                     # float64: silent
    called = []
    monkeypatch.setattr(precision, "warn_if_float32", called.append)
    c, _ = field
    fit_field(c.data.b_meas, c.data.temperature, c.f_ref, Scalar())
    assert called == ["field.fit_field"]
    import inspect
    from bayesmag._src.app.calibrator import Calibrator
    assert 'warn_if_float32("Calibrator.fit")' in inspect.getsource(Calibrator.fit)


def test_loading_a_field_run_as_a_vector_calibration_names_load_field(tmp_path):
    from bayesmag._src.app.artifact import ArtifactError, field_run_error
    (tmp_path / "field_params.json").write_text("{}")
    with pytest.raises(ArtifactError, match="load_field"):
        field_run_error(tmp_path, ArtifactError)


def test_a_job_reads_parquet_by_its_suffix_and_names_one_without_it(tmp_path):
    """`run` and `discover` said "not a text file (it holds NUL bytes)" of a Parquet file `apply` reads."""
    pytest.importorskip("pyarrow")
    from bayesmag._src.app.config import config_from_dict
    from bayesmag._src.app.inputs import load_data
    d = bayesmag.simulate.simulate(300, design="campaign", seed=3)
    bayesmag.to_frame(d).to_parquet(tmp_path / "rec.parquet", index=False)
    got = load_data(config_from_dict({"data": {"path": str(tmp_path / "rec.parquet")}}))
    np.testing.assert_allclose(got.b_ref, d.b_ref)
    (tmp_path / "rec.parquet").rename(tmp_path / "rec.csv")
    with pytest.raises(DataError, match="Parquet file without the .parquet suffix"):
        load_data(config_from_dict({"data": {"path": str(tmp_path / "rec.csv")}}))


def test_a_glitch_sample_in_the_reference_is_named(data):
    """One by_ref spike doubled the y RMSE with no word (smoke pass): a residual over OUTLIER_Z robust sds is named
    by run and time. The threshold leaves clean data alone (largest on Belsten 8.4, quickstart 5.1)."""
    ref = data.b_ref.copy()
    ref[31, 1] += 20.0
    spiked = CalibrationData(data.b_meas, data.temperature, ref, data.time, data.run)
    run = bayesmag.calibrate(spiked, _settings())
    text = [w for w in run.fit.design_warnings if "robust sds off" in w]
    assert len(text) == 1 and f"run {int(data.run[31])} time {data.time[31]:.6g} s (y" in text[0], text
    assert not [w for w in bayesmag.calibrate(data, _settings()).fit.design_warnings if "robust" in w]


@pytest.mark.realdata
def test_the_real_recording_has_no_gross_outlier(belsten):
    from bayesmag._src.core.fit import OUTLIER_Z, gross_outliers
    fit = bayesmag.fit_physics(belsten, bayesmag.PhysicsModel.paper(t0=0.0))
    assert not gross_outliers(fit.residuals(belsten)).any() and OUTLIER_Z >= 15


# --------------------------------------------------------------------------- the command line's side (smoke pass 3)
def test_a_hierarchical_transfer_on_one_run_says_it_was_not_fitted(data):
    from bayesmag._src.pipeline.sessions import hierarchical_transfer
    one = data.subset(np.flatnonzero(data.run == data.run[0]))
    tr, sessions = hierarchical_transfer(one, bayesmag.fit_physics(one))
    assert sessions is None and "hierarchical\" was asked for" in tr.warning and "was not fitted" in tr.warning


def test_apply_says_when_a_calibration_has_no_transfer_term():
    """`apply` to new sessions of a one-run calibration (coverage 21 / 15 / 37 %) printed no warning."""
    from types import SimpleNamespace
    from bayesmag._src.app.apply import new_session_notes
    model = bayesmag.PhysicsModel.paper()
    none = SimpleNamespace(transfer_sd=np.zeros(3), sessions=None, model=model)
    assert any("no between-session (transfer) term" in n for n in new_session_notes(none))
    some = SimpleNamespace(transfer_sd=np.array([0.1, 0.2, 0.1]), sessions=None, model=model)
    assert new_session_notes(some) == []


def test_a_field_job_refuses_the_vector_transfer_keys():
    from bayesmag._src.app.config import ConfigError, config_from_dict
    with pytest.raises(ConfigError, match=r"'uq.transfer' = 'hierarchical'.*field calibration.*valid: \['loro', 'off'\]"):
        config_from_dict({"data": {"source": "field_simulated"}, "uq": {"transfer": "hierarchical"}})
    config_from_dict({"data": {"source": "field_simulated"}})                # the defaults pass


def test_apply_names_a_folder_that_is_not_a_calibration(tmp_path):
    import json
    from bayesmag._src.app.artifact import ArtifactError, check_run_folder
    from bayesmag._src.app.outdir import MARKER
    (tmp_path / "findings.json").write_text("{}")
    (tmp_path / MARKER).write_text(json.dumps({"tool": "bayesmag", "complete": True, "files": ["findings.json"]}))
    with pytest.raises(ArtifactError, match=r"holds a discovery result \(`bayesmag discover`\), not a calibration"):
        check_run_folder(tmp_path)


# --------------------------------------------------------------------------- settings built in a script (fifth pass)
@pytest.mark.parametrize("cls, kw, match", [
    ("UQSettings", {"transfer": "hierarchal"}, r"transfer = 'hierarchal' is not valid.*'hierarchical'"),
    ("UQSettings", {"level": 95}, r"level = 95 must be in \(0, 1\)"),
    ("UQSettings", {"transfer_likelihood": "cauchy"}, r"transfer_likelihood = 'cauchy'.*'student_t'"),
    ("UQSettings", {"transfer_uninformed": "free"}, r"transfer_uninformed"),
    ("UQSettings", {"transfer_check": "off"}, r"transfer_check = 'off'.*'loro', 'warn'"),
    ("UQSettings", {"method": "pqsmc"}, r"method = 'pqsmc'.*'psqmc'"),
    ("UQSettings", {"n_params": 1}, r"n_params = 1 must be an integer of at least 2"),
    ("UQSettings", {"sigma_in": [0.05, 0.05, 0.05]}, r"sigma_in"),
    ("UQSettings", {"sigma_in": [0.05, 0.05, -0.05, 0.01]}, r"sigma_in.*>= 0"),
    ("UQSettings", {"reference_sd": -0.1}, r"reference_sd"),
    ("UQSettings", {"transfer_df": 2}, r"transfer_df = 2 must be a number > 2"),
    ("PhysicsSettings", {"covariance": "ar2"}, r"covariance = 'ar2'.*'newey_west'"),
    ("PhysicsSettings", {"t0": "men"}, r"t0 = 'men'"),
    ("PhysicsSettings", {"t0": 2000.0}, r"t0 = 2000.0 is not a reference temperature"),
    ("NutsSettings", {"chains": 0}, r"chains = 0"),
    ("NutsSettings", {"target_accept": 80}, r"target_accept = 80"),
    ("NutsSettings", {"chain_method": "threads"}, r"chain_method = 'threads'.*'vectorized'"),
])
def test_library_settings_are_checked_as_the_config_keys(cls, kw, match):
    """A script's settings: a misspelled `transfer` ran as "off" (new-session coverage 85-93 %), `level=95` and
    `transfer_likelihood="cauchy"` were accepted; now each is refused as the config key is, naming the value and the
    valid set. The defaults and every config-valid value still pass."""
    from bayesmag._src.pipeline import settings as S
    with pytest.raises(ValueError, match=match):
        getattr(S, cls)(**kw)
    getattr(S, cls)()


@pytest.mark.parametrize("transfer", ["loro", "hierarchical", "hierarchical_nuts", "off"])
def test_every_config_transfer_is_a_valid_setting(transfer):
    from bayesmag._src.app.config import _CHOICES
    assert set(_CHOICES["uq.transfer"]) == {"loro", "hierarchical", "hierarchical_nuts", "off"}
    bayesmag.UQSettings(transfer=transfer, sigma_in=[0.05, 0.05, 0.05, 0.01], reference_sd=[0.0, 0.01, 0.0])


def test_transfer_off_warns_that_new_sessions_get_no_between_session_term(data):
    """An explicit transfer="off" gave no CalibrationWarning (the other ways to lose the term warn)."""
    s = bayesmag.CalibrationSettings(uq=bayesmag.UQSettings(method="analytic", transfer="off"))
    with pytest.warns(CalibrationWarning, match=r"transfer = \"off\".*no between-session"):
        run = bayesmag.calibrate(data, s)
    assert any("transfer = \"off\"" in w for w in run.warnings)


def test_a_loaded_calibration_warns_on_predict_as_apply_does(data, tmp_path):
    """`bayesmag.load(run).predict(new)` of a one-run calibration said nothing where `apply` prints WARNING lines
    (no transfer term; rows out of domain: coverage 5-15 %); now the same texts as CalibrationWarnings. A
    same-session prediction (new_session=False) and warn=False say nothing."""
    from bayesmag._src.app.artifact import out_of_domain_note
    one = data.subset(np.flatnonzero(data.run == data.run[0]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = bayesmag.Calibrator(config={"uq": {"method": "analytic"}}).fit(one)
    cal.save(tmp_path / "one")
    loaded = bayesmag.load(tmp_path / "one")
    new = bayesmag.simulate.simulate(300, design="campaign", seed=7, noise_sd=0.05)
    with pytest.warns(CalibrationWarning) as rec:
        out = loaded.predict(new)
    texts = [str(w.message) for w in rec]
    assert any("no between-session (transfer) term" in t for t in texts), texts
    n_out = int((~out["in_domain"] & out["valid"]).sum())
    reasons = np.asarray(out["in_domain_reason"])[~out["in_domain"] & out["valid"]]
    assert n_out > 0 and any(out_of_domain_note(n_out, new.n, reasons)[1:] in t for t in texts), texts
    assert all(w.filename == __file__ for w in rec)                   # at the caller's line
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        inside = one.subset(np.arange(50))
        loaded.predict(inside, new_session=False)                     # rows of its session, in domain: silent
        loaded.predict(new, warn=False)


def test_python_messages_name_no_command_line_option(data, tmp_path):
    """`Calibrator.save(path)` into a user's folder said "--out mythesis ... e.g. --out mythesis_2" (Python has no
    --out); `bayesmag.load` of a folder bayesmag never wrote called it an incomplete run."""
    from bayesmag._src.app.artifact import ArtifactError
    from bayesmag._src.app.outdir import OutputError
    mine = tmp_path / "mythesis"
    mine.mkdir()
    (mine / "chapter1.tex").write_text("keep me")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = bayesmag.Calibrator(config={"uq": {"method": "analytic"}}).fit(data)
    with pytest.raises(OutputError) as e:
        cal.save(mine)
    assert "--out" not in str(e.value) and "mythesis_2" in str(e.value)
    assert (mine / "chapter1.tex").read_text() == "keep me"
    with pytest.raises(ArtifactError, match="holds no bayesmag calibration"):
        bayesmag.load(mine)


def test_a_weak_field_with_the_sensors_own_noise_is_read_as_uT_and_one_in_mT_is_refused(data):
    """Sixth outside pass: a calibration's own training rows at near-zero field (Belsten run 1, 99th percentile
    0.69 uT) were refused by predict as "looks like mT". The rows' noise tells: in uT a weak field keeps the
    sensor's noise (0.05 uT here), in mT it would be 1000x smaller."""
    cal = bayesmag.Calibrator().fit(data).calibration_
    rng = np.random.default_rng(3)
    n = 400
    weak = 0.4 * np.column_stack([np.sin(np.arange(n) / 50), np.cos(np.arange(n) / 50), np.ones(n)])
    rows = CalibrationData(weak + rng.normal(0, 0.05, (n, 3)), np.full(n, 24.0), None, time=np.arange(n) * 0.25)
    out = cal.predict(rows)                                  # accepted: the sensor's noise, a weak field
    assert np.isfinite(out["calibrated"]).all()
    mt = CalibrationData((data.b_meas[:n] + 0.0) / 1000, data.temperature[:n], None, time=data.time[:n])
    with pytest.raises(DataError, match="looks like mT"):
        cal.predict(mt)
