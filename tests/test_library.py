"""The library under the command line: ``calibrate`` on library settings, the ``Calibrator`` estimator, one
default for T0 and for the UQ method, public registries, and the compile cache configured on first use."""

from __future__ import annotations

import dataclasses
import inspect
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.stats

import bayesmag
from bayesmag._src.app.config import config_from_dict
from bayesmag._src.core.data import CalibrationData, DataError
from bayesmag._src.core.physics import T0_DEFAULT, PhysicsModel, resolve_t0
from bayesmag._src.pipeline.calibrate import CalibrationRun, calibrate
from bayesmag._src.pipeline.settings import CalibrationSettings, PhysicsSettings, UQSettings

ROOT = Path(__file__).resolve().parents[1]
FAST = {"n_params": 40, "n_qmc": 64, "seed": 2}


@pytest.fixture(scope="module")
def data():
    return bayesmag.simulate.simulate(600, design="campaign", seed=4)


# --------------------------------------------------------------------------- calibrate
def test_calibrate_is_the_job(tmp_path):
    """run_job = load, split, calibrate, write: the job's predictor and metrics are calibrate's on the same rows."""
    raw = {"name": "t", "data": {"source": "simulated", "simulate": {"n": 500, "design": "campaign", "seed": 1}},
           "split": {"kind": "time_blocks", "test_fraction": 0.2}, "uq": {**FAST, "method": "psqmc"},
           "output": {"figures": False, "progress": False}}
    cfg = config_from_dict(raw)
    result = bayesmag.run_job(cfg, tmp_path / "run")
    data, split = result["data"], result["split"]
    run = calibrate(data.subset(split.train), cfg.settings(), test=data.subset(split.test))
    assert isinstance(result["run"], CalibrationRun)
    np.testing.assert_array_equal(run.fit.theta, result["fit"].theta)
    np.testing.assert_array_equal(run.prediction.total, result["physics"].prediction.total)
    np.testing.assert_array_equal(run.predictor.transfer_sd, result["predictor"].transfer_sd)
    with pytest.raises(dataclasses.FrozenInstanceError):
        run.predictor = None


def test_calibrate_without_test_rows_fits_every_row_and_predicts_later(data):
    run = calibrate(data, CalibrationSettings(uq=UQSettings(**FAST)))
    assert run.fit.n == data.n and run.prediction is None and run.hybrid is None and run.nuts is None
    ref = bayesmag.fit_physics(data, PhysicsModel.paper(t0=float(np.mean(data.temperature))))
    np.testing.assert_allclose(run.fit.theta, ref.theta, rtol=1e-10, atol=1e-12)
    pred = run.predictor.predict(data)
    np.testing.assert_allclose(pred.mean, ref.predict(data), atol=1e-6)
    assert "physics" in repr(run) and len(repr(run)) < 100


def test_calibrate_refuses_rows_without_reference(data):
    with pytest.raises(DataError, match="reference"):
        calibrate(CalibrationData(data.b_meas, data.temperature, None))


def test_settings_are_library_types_with_the_configs_defaults():
    """The config's defaults are the library settings' defaults (written once)."""
    cfg = config_from_dict({"data": {"source": "simulated"}, "network": {"enabled": True}})
    s = cfg.settings()
    assert s.physics == PhysicsSettings() and s.uq == UQSettings()
    assert s.network is not None and s.network.validation == "time_blocks" and s.nuts is None
    assert s.conformal.folds == min(cfg.network.conformal_folds, 5)


# --------------------------------------------------------------------------- one default for T0 and the UQ method
def test_t0_has_one_default_resolved_in_one_place(tmp_path):
    from bayesmag._src.app.discover_cli import load_discover_config
    from bayesmag._src.pipeline.discover import DiscoverOptions

    assert T0_DEFAULT == "mean"
    assert config_from_dict({"data": {"source": "simulated"}}).physics.t0 == T0_DEFAULT
    assert PhysicsSettings().t0 == T0_DEFAULT and DiscoverOptions().t0 == T0_DEFAULT
    assert resolve_t0("mean", [10.0, 20.0, 33.0]) == pytest.approx(21.0) and resolve_t0(0, [10.0]) == 0.0
    with pytest.raises(ValueError, match="t0"):
        resolve_t0("median", [1.0])
    # an explicit t0 = 0.0 in [physics] reaches discover (it used to become "mean" there)
    p = tmp_path / "c.toml"
    p.write_text('[data]\nsource = "simulated"\n[physics]\nt0 = 0.0\n')
    assert load_discover_config(p)[1].t0 == 0.0
    p.write_text('[data]\nsource = "simulated"\n')
    assert load_discover_config(p)[1].t0 == "mean"


def test_uq_method_has_one_default_everywhere_predictions_are_made():
    from bayesmag._src.app.apply import apply_calibration
    from bayesmag._src.app.artifact import Calibration
    from bayesmag._src.core.physics_uq import DEFAULT_METHOD
    from bayesmag._src.core.predictor import UQOptions

    defaults = {
        "config": config_from_dict({"data": {"source": "simulated"}}).uq.method,
        "UQOptions": UQOptions().method, "UQSettings": UQSettings().method,
        "physics_uncertainty": inspect.signature(bayesmag.physics_uncertainty).parameters["method"].default,
        "Calibration.predict": inspect.signature(Calibration.predict).parameters["method"].default,
        "Calibration.predictor": inspect.signature(Calibration.predictor).parameters["method"].default,
        "apply": inspect.signature(apply_calibration).parameters["method"].default,
    }
    assert set(defaults.values()) == {DEFAULT_METHOD}, defaults


def test_auto_method_is_analytic_where_exact_else_psqmc(data):
    from bayesmag._src.core.physics_uq import resolve_method

    fit = bayesmag.fit_physics(data)
    inp = bayesmag.inputs_from_data(data)
    sig = np.diag([0.01, 0.01, 0.01, 0.05]) ** 2
    auto = bayesmag.physics_uncertainty(fit, inp, sigma_in=sig, n_params=30, seed=1)
    exact = bayesmag.physics_uncertainty(fit, inp, sigma_in=sig, method="analytic", n_params=30, seed=1)
    np.testing.assert_array_equal(auto.aleatoric, exact.aleatoric)
    lag = PhysicsModel.paper(extra=(bayesmag.ThermalLag(),))
    assert resolve_method("auto", fit.model) == "analytic" and resolve_method("auto", lag) == "psqmc"


# --------------------------------------------------------------------------- Calibrator: a scikit-learn estimator
def test_calibrator_constructor_only_stores_and_params_round_trip():
    cal = bayesmag.Calibrator("paper_physics", holdout=0.1)
    assert cal.get_params() == {"config": "paper_physics", "overrides": (), "out": None, "columns": None,
                                "temperature_unit": "C", "field_unit": None, "holdout": 0.1,
                                "duplicate_times": "ignore", "output": "full"}
    assert cal.set_params(holdout=None) is cal and cal.holdout is None
    with pytest.raises(ValueError, match="no parameter 'seed'"):
        cal.set_params(seed=1)
    assert repr(cal) == "Calibrator(config='paper_physics')"
    assert not any(k.endswith("_") for k in vars(cal))          # nothing fitted, nothing derived


def test_calibrator_fits_every_row_unless_a_holdout_is_given(data):
    cal = bayesmag.Calibrator({"uq": FAST}).fit(data)
    assert cal.physics_fit_.n == data.n and cal.metrics_ is None
    held = bayesmag.Calibrator({"uq": FAST, "split": {"kind": "time_blocks"}}, holdout=0.2).fit(data)
    assert 0.75 * data.n < held.physics_fit_.n < 0.85 * data.n          # 20 % of every run held out, in time blocks
    assert set(held.metrics_["physics"]) >= {"rmse", "crps", "coverage"}
    with pytest.raises(ValueError, match="holdout"):
        bayesmag.Calibrator(holdout=1.5).fit(data)


def test_calibrator_params_frame_is_labelled(data):
    cal = bayesmag.Calibrator({"uq": FAST}).fit(data)
    p = cal.params_
    assert list(p.columns) == ["axis", "parameter", "value", "sd", "unit"] and len(p) == 24
    row = p[(p.axis == "y") & (p.parameter == "Ko")].iloc[0]
    fit = cal.physics_fit_
    j = fit.model.param_names.index("Ko")
    assert row.value == fit.theta[1][j] and row.sd == pytest.approx(np.sqrt(fit.cov[1][j, j]), rel=1e-12)
    assert dict(zip(p.parameter[:8], p.unit[:8])) == {"S_x": "1", "S_y": "1", "S_z": "1", "Ks_x": "1/C",
                                                      "Ks_y": "1/C", "Ks_z": "1/C", "O": "uT", "Ko": "uT/C"}


def test_calibrator_score_is_minus_the_mean_crps(data):
    """Gaussian CRPS closed form (Gneiting & Raftery 2007) on the predicted mean and sd, against score()."""
    cal = bayesmag.Calibrator({"uq": FAST}).fit(data)
    out = cal.predict(data)
    z = (data.b_ref - out["calibrated"]) / out["total"]
    crps = out["total"] * (z * (2 * scipy.stats.norm.cdf(z) - 1) + 2 * scipy.stats.norm.pdf(z) - 1 / np.sqrt(np.pi))
    assert cal.score(data) == pytest.approx(-crps.mean(), rel=1e-6)


def test_calibrator_takes_arrays_in_a_documented_column_order(data):
    df = bayesmag.to_frame(data)
    a = bayesmag.Calibrator({"uq": FAST}).fit(df)
    X = np.column_stack([data.b_meas, data.temperature, data.time, data.run])
    b = bayesmag.Calibrator({"uq": FAST}).fit(X, data.b_ref)
    np.testing.assert_allclose(b.physics_fit_.theta, a.physics_fit_.theta, rtol=1e-12)
    np.testing.assert_allclose(b.predict(X[:, :4])["calibrated"], a.predict(data)["calibrated"], rtol=1e-10)
    with pytest.raises(DataError, match="shape"):
        b.predict(X[:, :3])


def test_y_is_the_reference_even_when_columns_maps_reference_columns(data):
    """``fit(X, y)`` with a ``columns`` mapping that also names reference columns of ``X``: ``y`` is the reference.
    Before, the mapped columns silently replaced it (offsets fitted -0.2 uT where y put them 5 uT higher)."""
    df = bayesmag.to_frame(data).rename(columns={"bx_ref": "RX", "by_ref": "RY", "bz_ref": "RZ"})
    y = data.b_ref + 5.0
    with pytest.warns(UserWarning, match="y is the reference used"):      # and says so (fourth safety pass)
        mapped = bayesmag.Calibrator({"uq": FAST}, columns={"bx_ref": "RX", "by_ref": "RY", "bz_ref": "RZ"}).fit(df, y)
    plain = bayesmag.Calibrator({"uq": FAST}).fit(bayesmag.CalibrationData(data.b_meas, data.temperature, y,
                                                                           data.time, data.run))
    np.testing.assert_allclose(mapped.physics_fit_.theta, plain.physics_fit_.theta, rtol=1e-10, atol=1e-12)


def test_calibrator_save_is_the_calibration_bayesmag_load_reads(data, tmp_path):
    cal = bayesmag.Calibrator({"uq": FAST}).fit(data)
    path = cal.save(tmp_path / "cal")
    again = bayesmag.load(path).predict(data)
    np.testing.assert_array_equal(again["upper"], cal.predict(data)["upper"])
    assert (path / "params.json").exists() and not (path / "metrics.json").exists()


def _sklearn():
    return pytest.importorskip("sklearn", reason="scikit-learn is the optional extra bayesmag[sklearn]")


def test_calibrator_clones_and_runs_in_a_pipeline(data):
    _sklearn()
    from sklearn.base import clone
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import FunctionTransformer

    cal = bayesmag.Calibrator({"uq": FAST}, holdout=None)
    twin = clone(cal)
    assert twin is not cal and twin.get_params() == cal.get_params()
    X_nT = np.column_stack([data.b_meas * 1e3, data.temperature])
    to_uT = FunctionTransformer(lambda X: X * np.array([1e-3, 1e-3, 1e-3, 1.0]))
    pipe = Pipeline([("to_uT", to_uT), ("cal", twin)]).fit(X_nT, data.b_ref)
    direct = clone(cal).fit(np.column_stack([data.b_meas, data.temperature]), data.b_ref)
    np.testing.assert_allclose(pipe.predict(X_nT)["calibrated"], direct.predict(data)["calibrated"], rtol=1e-9)
    assert pipe.score(X_nT, data.b_ref) == pytest.approx(direct.score(data), rel=1e-9)


#: The part of scikit-learn's check_estimator that applies: the checks of the estimator contract
#: (parameters, cloning, repr, tags). The rest feeds random 1-D targets and arbitrary feature counts,
#: which a magnetometer calibration (4 input columns, a (n, 3) reference) refuses by design.
SKLEARN_CHECKS = ("check_no_attributes_set_in_init", "check_get_params_invariance", "check_set_params",
                  "check_parameters_default_constructible", "check_estimator_cloneable", "check_estimator_repr",
                  "check_do_not_raise_errors_in_init_or_set_params", "check_estimator_tags_renamed")


@pytest.mark.parametrize("check", SKLEARN_CHECKS)
def test_sklearn_estimator_checks(check):
    _sklearn()
    from sklearn.utils import estimator_checks
    getattr(estimator_checks, check)("Calibrator", bayesmag.Calibrator())


# --------------------------------------------------------------------------- extension API and start-up
def test_registries_are_public_with_one_decorator_style():
    from bayesmag._src.core import catalogue, likelihoods

    assert bayesmag.register_term is catalogue.register
    assert bayesmag.register_likelihood is likelihoods.register is bayesmag.likelihoods.register
    assert bayesmag.Predictor.__name__ == "Predictor" and bayesmag.Prediction.__name__ == "Prediction"

    @dataclasses.dataclass(frozen=True)
    class Unregistered(bayesmag.likelihoods.Gaussian):
        name = "test_unregistered"

    assert "test_unregistered" not in bayesmag.likelihoods.LIKELIHOODS     # defining is not registering
    try:
        assert bayesmag.register_likelihood(Unregistered) is Unregistered
        assert bayesmag.likelihoods.get_likelihood("test_unregistered") is Unregistered
    finally:
        bayesmag.likelihoods.unregister("test_unregistered")
    with pytest.raises(TypeError, match="Likelihood"):
        bayesmag.register_likelihood(int)


def test_results_are_written_by_the_application_layer():
    from bayesmag._src.pipeline.discover import DiscoveryResult
    from bayesmag._src.pipeline.nuts import NutsResult

    assert not hasattr(NutsResult, "write") and not hasattr(DiscoveryResult, "write")
    assert callable(bayesmag.write_nuts_outputs) and callable(bayesmag.write_discovery)


def test_compile_cache_is_configured_on_first_use_not_at_import(tmp_path):
    code = ("import jax, bayesmag; a = jax.config.values['jax_compilation_cache_dir']; bayesmag.fit_physics; "
            "print(a, jax.config.values['jax_compilation_cache_dir'])")
    env = {**os.environ, "BAYESMAG_COMPILE_CACHE": str(tmp_path / "c"), "JAX_PLATFORMS": "cpu",
           "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["None", str(tmp_path / "c")]


def test_python_dash_m_bayesmag_is_the_command_line():
    r = subprocess.run([sys.executable, "-m", "bayesmag", "--version"], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)}, cwd=ROOT.parent)
    assert r.returncode == 0 and r.stdout.strip() == f"bayesmag {bayesmag.__version__}", r.stderr[-2000:]


def test_network_package_keeps_every_name_of_the_old_module():
    from bayesmag._src.core import network
    from bayesmag._src.core.network import infer, recalibration, spec, train

    assert all(hasattr(network, n) for n in network.__all__)
    assert network.NetworkSpec is spec.NetworkSpec and network.fit_residual_network is train.fit_residual_network
    assert network.mc_predict is infer.mc_predict and network.recalibrate is recalibration.recalibrate


def test_calibrate_refuses_a_series_that_does_not_hold_the_rows():
    """``series = (recording, train_index, test_index)`` must give the rows passed: swapped indices are refused."""
    import numpy as np
    d = bayesmag.simulate.simulate(600, design="campaign", seed=0)
    tr, te = np.arange(0, 500), np.arange(500, 600)
    with pytest.raises(ValueError, match="series = "):
        bayesmag.calibrate(d.subset(tr), test=d.subset(te), series=(d, te, tr))
