"""The discovery catalogue: registration, exact linear features, transforms, validation."""

import jax.numpy as jnp
import numpy as np
import pytest

import bayesmag
from bayesmag._src.core import catalogue as C
from bayesmag._src.core.catalogue import make_extra
from bayesmag._src.core.physics import EXTRA_TERMS, PhysicsModel
from bayesmag.simulate import get_effect, simulate

#: Timing delay recovered within this many seconds on a 2000-row campaign (a tenth of a 4 Hz sample).
DELTA_TOL_S = 0.05
#: Thermal time constant recovered within this relative error.
TAU_RTOL = 0.1


@pytest.fixture(scope="module")
def campaign():
    return simulate(2000, design="campaign", seed=1)


def test_every_entry_registered_with_explanation():
    required = {"cross_axis_quadratic", "cubic_nonlinearity", "temperature_quadratic", "thermal_lag",
                "timing_offset", "hysteresis", "offset_drift"}
    assert required <= set(C.CATALOGUE)
    for name, cls in C.CATALOGUE.items():
        assert EXTRA_TERMS[name] is cls
        assert isinstance(cls.explanation, str) and len(cls.explanation) > 20
        assert make_extra(name, t0=20.0).name == name


@pytest.mark.parametrize("name", [n for n, c in C.CATALOGUE.items() if issubclass(c, bayesmag.Term)])
def test_linear_terms_call_equals_features(name, campaign):
    term = make_extra(name, t0=24.0)
    inputs = bayesmag.inputs_from_data(campaign)
    p = np.arange(1, len(term.param_names()) + 1, dtype=np.float64)
    X = np.asarray(term.features(inputs))
    assert X.shape == (campaign.n, p.size)
    np.testing.assert_allclose(np.asarray(term(jnp.asarray(p), inputs)), X @ p, rtol=1e-12)


def test_timing_offset_zero_is_identity_and_shift_interpolates(campaign):
    inputs = bayesmag.inputs_from_data(campaign)
    tr = C.TimingOffset()
    same = tr(jnp.array([0.0]), inputs)
    np.testing.assert_allclose(np.asarray(same.b), campaign.b_meas, atol=1e-12)
    one = tr(jnp.array([0.25]), inputs)                       # exactly one 4 Hz sample ahead
    inner = np.flatnonzero(np.r_[campaign.run[1:] == campaign.run[:-1], False])
    np.testing.assert_allclose(np.asarray(one.b)[inner], campaign.b_meas[inner + 1], atol=1e-9)


def test_hysteresis_state_and_validation(campaign):
    s = np.asarray(C.Hysteresis(axis="x", threshold=10.0).state(bayesmag.inputs_from_data(campaign)))
    assert set(np.unique(s)) <= {-1.0, 0.0, 1.0} and (s != 0).mean() > 0.5
    with pytest.raises(ValueError, match="must be one of"):
        C.Hysteresis(mode="sideways")
    with pytest.raises(ValueError, match="must be one of"):
        C.Hysteresis(axis="w")
    with pytest.raises(ValueError, match="rate=true, steps=true"):
        C.OffsetDrift(rate=False, steps=False)


def test_config_spec_with_parameters():
    t = make_extra({"name": "hysteresis", "axis": "y", "mode": "direction", "min_step": 1.5}, t0=0.0)
    assert (t.axis, t.mode, t.min_step) == ("y", "direction", 1.5)
    with pytest.raises(ValueError, match="has no parameter"):
        make_extra({"name": "cubic_nonlinearity", "power": 3})


@pytest.mark.extended
def test_timing_and_lag_recovered_by_lm():
    d = simulate(2000, design="campaign", seed=2, effects=[get_effect("thermal_lag", tau=30.0),
                                                           get_effect("timing_offset", delta=0.5)])
    m = PhysicsModel.paper(t0=24.0, extra=(C.ThermalLag(tau0=20.0), C.TimingOffset(delta0=0.25)))
    fit = bayesmag.fit_physics(d, m)
    names = list(m.param_names)
    delta = fit.theta[:, names.index("delta")]
    tau = np.exp(fit.theta[:, names.index("log_tau")])
    assert np.all(np.abs(delta - 0.5) < DELTA_TOL_S), delta
    # the y and z axes carry most of the thermal signal
    assert abs(tau[1] / 30.0 - 1) < TAU_RTOL and abs(tau[2] / 30.0 - 1) < TAU_RTOL, tau


def test_temperature_quadratic_cubic_option(campaign):
    inputs = bayesmag.inputs_from_data(campaign)
    t = C.TemperatureQuadratic(t0=24.0, cubic=True, scale=True)
    assert t.param_names() == ("Ko2", "Ko3", "Ks2_x", "Ks2_y", "Ks2_z")
    X = np.asarray(t.features(inputs))
    tc = campaign.temperature - 24.0
    np.testing.assert_allclose(X[:, 0], tc**2, rtol=1e-12)
    np.testing.assert_allclose(X[:, 1], tc**3, rtol=1e-12)
    np.testing.assert_allclose(X[:, 2:], tc[:, None] ** 2 * campaign.b_meas, rtol=1e-12)
    # the default is unchanged (one Ko2 column), and the option travels through a config spec
    assert C.TemperatureQuadratic().param_names() == ("Ko2",)
    assert make_extra({"name": "temperature_quadratic", "cubic": True}, t0=24.0).cubic


def test_temperature_quadratic_is_linear_in_its_parameters(campaign):
    """Its field ``linear`` (first-order columns) hid ``Term.linear``: with the default ``linear=False`` the model
    was taken as nonlinear (the analytic UQ refused, ``auto`` took PS-QMC). Now linear either way: ``auto`` is the
    exact analytic method, and its mean is the plug-in prediction plus the closed-form input-noise bias of
    ``Ko2 (T + e)^2``, ``Ko2 sd_T^2`` (the model is otherwise linear in T and B)."""
    from bayesmag._src.core.physics_uq import physics_uncertainty, resolve_method
    assert PhysicsModel.paper(extra=(C.TemperatureQuadratic(linear=True, scale=True),)).is_linear
    model = bayesmag.PhysicsModel.paper(t0=24.0, extra=(C.TemperatureQuadratic(),))
    assert model.is_linear and model.degree == 2 and resolve_method("auto", model) == "analytic"
    fit = bayesmag.fit_physics(campaign, model)
    inputs = bayesmag.inputs_from_data(campaign)
    sd_t = 0.3
    uq = physics_uncertainty(fit, inputs, sigma_in=np.diag([0.0, 0.0, 0.0, sd_t**2]))
    ko2 = fit.theta[:, list(model.param_names).index("Ko2")]
    np.testing.assert_allclose(uq.mean, fit.predict(inputs) + ko2 * sd_t**2, rtol=0, atol=1e-10)


def test_thermal_slopes_and_calibrated_hysteresis(campaign):
    inputs = bayesmag.inputs_from_data(campaign)
    tc = campaign.temperature - 24.0
    q = C.AxisQuadratic(t0=24.0, thermal=True)
    assert q.param_names() == ("q_xx", "q_yy", "q_zz", "q_xx_T", "q_yy_T", "q_zz_T") and q.degree == 3
    X = np.asarray(q.features(inputs))
    np.testing.assert_allclose(X[:, 3:], X[:, :3] * tc[:, None], rtol=1e-12)
    assert C.AxisQuadratic().param_names() == ("q_xx", "q_yy", "q_zz") and C.AxisQuadratic().degree == 2
    # hysteresis driven by the calibrated field: with cal = the identity row it is the measured one
    ident = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    a = np.asarray(C.Hysteresis(axis="x", threshold=10.0).state(inputs))
    b = np.asarray(C.Hysteresis(axis="x", threshold=10.0, t0=24.0, cal=list(ident)).state(inputs))
    np.testing.assert_array_equal(a, b)
    h = C.Hysteresis(axis="y", thermal=True, t0=24.0, cal=ident)
    assert h.param_names() == ("h", "h_T") and isinstance(h.cal, tuple) and hash(h)
    with pytest.raises(ValueError, match="cal has 3 values"):
        C.Hysteresis(cal=(1.0, 0.0, 0.0))
    assert make_extra({"name": "hysteresis", "axis": "y", "cal": list(ident), "thermal": True}, t0=24.0).thermal


def test_registry_entry_carries_grid_requirements_and_description():
    """Adding a term is one class: discovery reads everything from the entry itself."""
    ctx = C.SearchContext(t0=25.0, dt=0.25, runs=(0, 1, 2), run_span=600.0, reach=(40.0, 40.0, 40.0),
                          heated_span=600.0, run_bounds=((0, 0.0, 600.0), (1, 700.0, 1300.0), (2, 1400.0, 2000.0)))
    for name, cls in C.CATALOGUE.items():
        assert set(cls.requires) <= {"time", "temperature", "runs", "increasing_time"}, name
        assert cls.scope in ("channel", "sensor"), name
        grid = cls.grid(ctx, None if cls.scope == "sensor" else 1)
        assert grid and all(isinstance(s.component, cls) for s in grid), name
        assert all((s.nl is not None) == (cls.scope == "sensor") for s in grid), name
        assert isinstance(grid[0].component.describe(grid[0].cols), str)
    assert C.SIMULATOR_NAMES["cubic"] == "cubic_nonlinearity" and "run_offset" not in C.SIMULATOR_NAMES.values()


def test_run_step_features_sit_inside_one_run():
    """run_step: 1 from time ``at`` to the end of run ``run_id``, 0 elsewhere (other runs, before ``at``)."""
    run = np.array([0, 0, 0, 1, 1, 1, 1])
    time = np.array([0.0, 1, 2, 10, 11, 12, 13])
    inputs = bayesmag.Inputs(jnp.zeros((7, 3)), jnp.zeros(7), jnp.asarray(time), jnp.asarray(run))
    X = np.asarray(C.RunStep(run_id=1, at=11.5).features(inputs))
    np.testing.assert_array_equal(X[:, 0], [0, 0, 0, 0, 0, 1, 1])
    ctx = C.SearchContext(run_bounds=((0, 0.0, 2.0), (1, 10.0, 13.0)))
    ats = [s.component.at for s in C.RunStep.grid(ctx, 0) if s.component.run_id == 1]
    assert all(10.0 < a < 13.0 for a in ats) and len(ats) == len(C.RunStep.FRACTIONS)
    g = C.RunStep(run_id=1, at=11.5).located_grid(ctx)
    assert g.min() >= 10.0 and g.max() <= 13.0 and g.size == 41


def test_run_offset_features_and_validation():
    d = simulate(300, design="campaign", seed=2, n_runs=3)
    t = C.RunOffset(runs=tuple(np.unique(d.run)))
    X = np.asarray(t.features(bayesmag.inputs_from_data(d)))
    runs = np.unique(d.run)
    np.testing.assert_array_equal(X, (d.run[:, None] == runs[None, 1:]).astype(float))
    assert t.param_names() == tuple(f"o_{r}" for r in runs[1:])
    with pytest.raises(ValueError, match="two or more distinct"):
        C.RunOffset(runs=(1,))


def test_hysteresis_state_held_across_runs():
    b = np.zeros((6, 3))
    b[1, 0] = 30.0                                  # excursion in run 0, none in run 1
    inputs = bayesmag.Inputs(jnp.asarray(b), jnp.zeros(6), jnp.arange(6.0), jnp.array([0, 0, 0, 1, 1, 1]))
    reset = np.asarray(C.Hysteresis(axis="x", threshold=10.0).state(inputs))
    held = np.asarray(C.Hysteresis(axis="x", threshold=10.0, across_runs=True).state(inputs))
    np.testing.assert_array_equal(reset, [0, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(held, [0, 1, 1, 1, 1, 1])


def test_thermal_lag_of_a_few_samples_is_not_heat_flow():
    ctx = C.SearchContext(dt=0.25, run_span=600.0, heated_span=600.0)
    lag = C.ThermalLag()
    assert "smooths the noise" in lag.implausible(np.log(1.0), ctx)       # 4 samples
    assert lag.implausible(np.log(60.0), ctx) is None
    assert min(np.exp(s.nl) for s in C.ThermalLag.grid(ctx, None)) >= 10 * ctx.dt


def test_t0_is_the_models_one_source():
    """T0 lives on the model: every component that centres temperature takes the model's (issue #22.6)."""
    extra = make_extra({"name": "temperature_quadratic"}, t0=0.0)      # built with another T0
    model = PhysicsModel.paper(t0=27.5, extra=(extra,))
    assert model.t0 == 27.5
    assert all(c.t0 == 27.5 for c in model.components if hasattr(c, "t0"))
    # rebuilt from its components (as a saved calibration is) it is the same model, one T0
    assert PhysicsModel(model.terms, model.transforms) == model
    with pytest.raises(ValueError, match="reference temperature is the model's"):
        make_extra({"name": "temperature_quadratic", "t0": 20.0}, t0=27.5)


@pytest.mark.parametrize("mode", ["excursion", "direction"])
@pytest.mark.parametrize("across_runs", [False, True])
@pytest.mark.extended
def test_hysteresis_settled_piece_gives_the_whole_series_state(mode, across_runs):
    """``history_settled(piece)`` promises that the state at the piece's last row is the whole series' state there
    (a piece of a recording then needs no earlier rows: apply on Dask relies on it). Checked on every (start, end)
    of a random 3-run series (pieces of 4-60 rows); the predicate is also needed: some unsettled pieces do end in another state."""
    from bayesmag._src.core.physics import Inputs
    rng = np.random.default_rng(4)
    n = 150
    f = np.cumsum(rng.normal(0, 6.0, n))
    b = np.column_stack([f, rng.normal(size=n), rng.normal(size=n)])
    run = np.repeat([0, 1, 2], n // 3)
    x = Inputs(b, np.full(n, 20.0), np.arange(n, dtype=float), run)
    term = C.Hysteresis(axis="x", mode=mode, threshold=25.0, min_step=8.0, lag=3, across_runs=across_runs)
    whole = np.asarray(term.state(x))
    settled = differs = 0
    for m in (4, 12, 30, 60):                      # piece lengths (few shapes: few compilations)
        for j in range(0, n - m + 1):
            k = j + m
            piece = Inputs(b[j:k], x.t[j:k], x.time[j:k], run[j:k])
            last = float(np.asarray(term.state(piece))[-1])
            if term.history_settled(piece):
                settled += 1
                assert last == whole[k - 1], (j, k)
            else:
                differs += last != whole[k - 1]
    assert settled > 100 and differs > 10, (settled, differs)


@pytest.mark.parametrize("g", [3e-4, -4e-4])
def test_magnitude_gain_inverts_its_simulate_twin_exactly(g):
    """``magnitude_gain`` undoes simulate's ``u = (1 + g|u0|) u0`` row by row (an exact root, not a
    first-order correction), so a fit starts from the planted model; both signs."""
    clean = simulate(1500, design="campaign", seed=3, noise_sd=0.0)
    dist = simulate(1500, design="campaign", seed=3, noise_sd=0.0, effects=[get_effect("magnitude_gain", g=g)])
    back = C.MagnitudeGain()(jnp.array([g]), bayesmag.inputs_from_data(dist)).b
    np.testing.assert_allclose(np.asarray(back), clean.b_meas, rtol=0, atol=1e-10)
    assert C.SIMULATOR_NAMES["magnitude_gain"] == "magnitude_gain"


def test_magnitude_gain_recovered_by_the_run_model():
    """In a ``bayesmag run`` model (each axis its own g) the planted g = 3e-4 /uT is recovered within 3 se on every
    axis (measured: 3.00 / 2.96 / 3.04e-4, se 3.1-4.5e-6) at 0.05 uT noise."""
    d = simulate(2000, design="campaign", seed=2, noise_sd=0.05, effects=[get_effect("magnitude_gain", g=3e-4)])
    m = PhysicsModel.paper(t0=24.0, extra=(make_extra({"name": "magnitude_gain", "g0": 1e-4}, t0=24.0),))
    fit = bayesmag.fit_physics(d, m)
    i = list(m.param_names).index("g")
    se = np.sqrt(fit.cov[:, i, i])
    assert np.all(np.abs(fit.theta[:, i] - 3e-4) <= 3 * se), (fit.theta[:, i], se)


def test_magnitude_gain_grid_both_signs_and_plausibility():
    """The grid spans relative gain changes of 0.2-10 % at the field's reach, both signs; a change of 25 % or more
    across the reach is saturation (or a wrong unit), not this effect."""
    ctx = C.SearchContext(magnitude_reach=80.0)
    g = np.array([s.nl for s in C.MagnitudeGain.grid(ctx, None)])
    assert (g > 0).sum() == (g < 0).sum() == len(C.MagnitudeGain.FRACTIONS)
    np.testing.assert_allclose(sorted(np.abs(g) * 80.0)[::2], C.MagnitudeGain.FRACTIONS)
    mg = C.MagnitudeGain()
    assert mg.implausible(1e-3, ctx) is None                             # 8 % across the reach
    assert "saturation" in mg.implausible(-4e-3, ctx)                    # 32 %
    assert mg.started(1.234567e-4).g0 == pytest.approx(1.23457e-4)
