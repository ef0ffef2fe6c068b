"""Field calibration (core/measurement.py, core/field.py, core/field_sim.py) against simulated ground truth.

Tolerances: invariants within 4 posterior sd of the truth and within a stated absolute bound;
heading RMSE below 0.3 degrees at 0.05 uT noise in a 25 uT horizontal field (0.05/25 rad = 0.11 deg per
row); coverage over seeds inside a declared band (the quick test 6 seeds, the slow one 20).
"""

import numpy as np
import pytest
import scipy.stats
from scipy.spatial.transform import Rotation

import jax.numpy as jnp

from bayesmag.field import (INVARIANT_NAMES, Constant, Scalar, Vector, fit_field, field_target, gauge_form,
                            heading, heading_with_uncertainty, invariants, measurement_from_spec)
from bayesmag.simulate import simulate_field
from bayesmag._src.core.field import wrap_deg


# --------------------------------------------------------------------------- measurement models


@pytest.mark.parametrize("meas, target, extra, want", [
    (Scalar(), [5.5], [], [-0.5]),
    (Constant(4.0), [0.0], [], [1.0]),
    (Constant(None), [0.0], [6.0], [-1.0]),
])
def test_magnitude_residuals_closed_form(meas, target, extra, want):
    B = jnp.array([[3.0, 4.0, 0.0]])
    r = meas.residual(B, jnp.asarray(target), jnp.asarray(extra, dtype=float))
    assert np.allclose(np.asarray(r), want)


def test_vector_residual_is_componentwise():
    B, ref = jnp.array([[1.0, 2.0, 3.0]]), jnp.array([[0.5, 2.0, 4.0]])
    assert np.allclose(np.asarray(Vector().residual(B, ref, jnp.zeros(0))), [0.5, 0.0, -1.0])


@pytest.mark.parametrize("kind, field, msg", [("magnitude", None, "not known"), ("constant", -5.0, "positive")])
def test_measurement_spec_errors_name_the_value(kind, field, msg):
    with pytest.raises(ValueError, match=msg):
        measurement_from_spec(kind, field)


# --------------------------------------------------------------------------- the gauge


@pytest.mark.parametrize("seed", range(4))
def test_gauge_form_is_rotation_times_upper(seed):
    M = np.eye(3) + 0.2 * np.random.default_rng(seed).normal(size=(3, 3))
    R, U = gauge_form(M)
    assert np.allclose(R @ U, M) and np.allclose(R.T @ R, np.eye(3)) and np.allclose(np.tril(U, -1), 0)
    assert np.all(np.diag(U) > 0)


@pytest.mark.parametrize("seed", range(4))
def test_invariants_do_not_see_a_rotation(seed):
    rng = np.random.default_rng(seed)
    S, Ks = np.eye(3) + 0.1 * rng.normal(size=(3, 3)), 1e-3 * rng.normal(size=(3, 3))
    O, Ko = rng.normal(size=3), 0.01 * rng.normal(size=3)
    R = Rotation.random(random_state=seed).as_matrix()
    a = np.asarray(invariants(S, Ks, O, Ko))
    b = np.asarray(invariants(R @ S, R @ Ks, R @ O, R @ Ko))
    assert np.allclose(a, b, rtol=1e-10, atol=1e-12)


def test_magnitude_fit_is_in_the_gauge_and_ignores_a_rotated_reference():
    """A scalar fit is upper-triangular, and rotating the reference field changes nothing it can see."""
    c = simulate_field("dance", n=1200, seed=3, vehicle=True)
    d = c.data
    R = Rotation.random(random_state=1).as_matrix()
    f1 = fit_field(d.b_meas, d.temperature, field_target(Scalar(), b_ref=d.b_ref), Scalar(), temperature_terms=False)
    f2 = fit_field(d.b_meas, d.temperature, field_target(Scalar(), b_ref=d.b_ref @ R.T), Scalar(),
                   temperature_terms=False)
    S1 = f1.matrices()[0]
    assert np.allclose(np.tril(S1, -1), 0)
    assert np.allclose(f1.theta, f2.theta, atol=1e-9)
    v = fit_field(d.b_meas, d.temperature, d.b_ref, Vector(), temperature_terms=False)   # sees every entry
    Rv, Uv = gauge_form(v.matrices()[0])
    assert np.allclose(Uv, S1, atol=5e-3)          # the vector fit's S is the rotation times the gauge form


# --------------------------------------------------------------------------- recovery of the truth


@pytest.mark.parametrize("meas", [Constant(50.0), Scalar()], ids=["constant", "scalar"])
@pytest.mark.extended
def test_dance_with_temperature_ramp_recovers_every_invariant(meas):
    c = simulate_field("dance", n=2000, seed=11, temperature=(15.0, 40.0))
    d = c.data
    f = fit_field(d.b_meas, d.temperature, field_target(meas, b_ref=d.b_ref, f_ref=c.f_ref, n=d.n), meas)
    inv, truth = f.invariants(), c.truth.invariants(f.model.t0)
    assert f.converged and inv["identified"].all(), f.notes
    z = (inv["value"] - truth) / inv["sd"]
    assert np.all(np.abs(z) < 4), dict(zip(INVARIANT_NAMES, np.round(z, 2)))
    err = np.abs(inv["value"] - truth)
    assert err[:6].max() < 2e-3 and err[12:15].max() < 0.05      # Q (1) and d (uT)
    # held-out-free check of the magnitude: residual sd close to the simulated noise (0.05 uT per axis)
    assert 0.04 < np.sqrt(f.s2) < 0.065


def test_free_field_fixes_the_scale_and_keeps_the_shape():
    c = simulate_field("dance", n=1500, seed=5)
    d = c.data
    f = fit_field(d.b_meas, d.temperature, field_target(Constant(None), n=d.n), Constant(None), temperature_terms=False)
    S, _, _, _, extra = f.matrices()
    assert abs(np.trace(S) - 3.0) < 1e-12
    inv, truth = f.invariants()["value"], c.truth.invariants(f.model.t0)
    assert np.allclose(inv[:6] / inv[0], truth[:6] / truth[0], atol=2e-3)     # the shape of Q
    k = 50.0 / extra[0]                                                        # the scale the gauge took
    assert np.allclose(inv[12:15] , truth[12:15], atol=0.05)                  # d is in reading units: no scale
    assert np.allclose(k**2 * inv[:6], truth[:6], atol=2e-3)


def test_heading_error_on_level_turns_is_small_and_covered():
    c = simulate_field("level_turns", n=2000, seed=2)
    d = c.data
    f = fit_field(d.b_meas, d.temperature, field_target(Constant(50.0), n=d.n), Constant(50.0))
    lv = c.truth.level
    h = heading_with_uncertainty(f, d.b_meas[lv], d.temperature[lv], c.truth.alignment(d.temperature[lv]))
    e = wrap_deg(h["heading"] - c.truth.heading[lv])
    assert np.sqrt(np.mean(e**2)) < 0.3
    assert 0.9 <= np.mean(np.abs(e) <= 1.96 * h["sd"]) <= 1.0


def test_heading_convention():
    assert np.allclose(heading(np.array([[20.0, 0, 40], [0, -20.0, 40], [0, 20.0, 40]])), [0, 90, -90])


# --------------------------------------------------------------------------- identifiability naming


def test_level_turns_name_the_vertical_and_identify_nothing_in_3d():
    c = simulate_field("level_turns", n=1500, seed=4)
    d = c.data
    f = fit_field(d.b_meas, d.temperature, field_target(Constant(50.0), n=d.n), Constant(50.0))
    assert any("sensor axis z" in n and "tilt" in n for n in f.notes), f.notes
    assert not f.invariants()["identified"].any()


def test_one_heated_orientation_separates_no_thermal_terms():
    """A dance at one temperature, then a static heated hold: Ks and Ko are named not separable."""
    a = simulate_field("dance", n=1200, seed=6, temperature=(20.0, 20.0))
    b = simulate_field("few_orientations", n=600, seed=6, n_orient=1, temperature=(25.0, 45.0))
    # same sensor and vehicle (same seed draws them first); stack the two recordings
    u = np.vstack([a.data.b_meas, b.data.b_meas])
    t = np.concatenate([a.data.temperature, b.data.temperature])
    f = fit_field(u, t, np.full(len(t), 50.0), Constant(50.0), temperature_terms=True)
    inv = f.invariants()
    thermal = np.array([n.startswith(("dQ", "dd")) for n in INVARIANT_NAMES])
    assert not inv["identified"][thermal].any() and inv["identified"][~thermal].all()
    assert any("second temperature" in n for n in f.notes), f.notes


# --------------------------------------------------------------------------- coverage over seeds


def _coverage(kind, seeds, meas, n=1500, **kw):
    k = scipy.stats.norm.ppf(0.975)
    hits = []
    for s in seeds:
        c = simulate_field(kind, n=n, seed=s, **kw)
        d = c.data
        f = fit_field(d.b_meas, d.temperature, field_target(meas, b_ref=d.b_ref, f_ref=c.f_ref, n=d.n), meas)
        inv, truth = f.invariants(), c.truth.invariants(f.model.t0)
        ok = inv["identified"]
        hits.append(np.abs(inv["value"][ok] - truth[ok]) <= k * inv["sd"][ok])
    return float(np.mean(np.concatenate(hits)))


@pytest.mark.parametrize("kind, meas, cov", [("two_temperature", Constant(50.0), "white"),
                                             ("few_orientations", Scalar(), "ar1")])
@pytest.mark.extended
def test_estimate_is_the_posterior_mode(kind, meas, cov):
    """The returned theta is a stationary point of the posterior it reports (noise level and priors as stored):
    the gradient of the negative log posterior, times the posterior sd, is ~0 (a Newton step of < 0.01 sd).

    Fails with prior weights from a stale noise level (two fixed passes: 0.30 on the first campaign)."""
    c = simulate_field(kind, n=600, seed=0)
    d = c.data
    y = field_target(meas, b_ref=d.b_ref, f_ref=c.f_ref, n=d.n)
    f = fit_field(d.b_meas, d.temperature, y, meas, covariance=cov, run=d.run)
    u, t, yy = jnp.asarray(d.b_meas), jnp.asarray(d.temperature), jnp.asarray(y)

    def neg_log_post(th):
        r = f.model.residual(th, u, t, yy)
        return 0.5 * jnp.sum(r * r) / (f.s2 * f.inflation) + 0.5 * jnp.sum(((th - f.prior_mean) / f.prior_sd) ** 2)

    import jax
    g = np.asarray(jax.grad(neg_log_post)(jnp.asarray(f.theta)))
    assert np.max(np.abs(f.cov @ g) / f.std) < 0.01


def test_parameter_coverage_quick():
    """4 dance campaigns x 18 invariants: 95 % intervals cover at least 85 % (below the binomial 3-sd band at n=72)."""
    cov = _coverage("dance", range(100, 104), Constant(50.0), n=1000, temperature=(15.0, 40.0))
    assert 0.85 <= cov <= 1.0


@pytest.mark.slow
@pytest.mark.parametrize("kind, kw", [("dance", {"temperature": (15.0, 40.0)}), ("two_temperature", {}),
                                      ("few_orientations", {})])
def test_parameter_coverage_20_campaigns(kind, kw):
    """20 campaigns per kind: coverage of the identified invariants in [0.90, 0.99] (declared). two_temperature and
    few_orientations failed it (0.88-0.89) until the estimate was made the posterior mode (fixed-point passes)."""
    cov = _coverage(kind, range(200, 220), Scalar(), **kw)
    assert 0.90 <= cov <= 0.99


@pytest.mark.slow
def test_nuts_agrees_with_the_laplace_posterior():
    """NUTS on the same likelihood and priors: means within 0.5 NUTS sd, sds within 25 % (about 90 s loaded)."""
    from bayesmag._src.pipeline.field_nuts import field_nuts
    c = simulate_field("two_temperature", n=1000, seed=0)
    d = c.data
    f = fit_field(d.b_meas, d.temperature, c.f_ref, Scalar())
    r = field_nuts(f, d.b_meas, d.temperature, c.f_ref, chains=2, warmup=200, draws=200)
    assert r["max_rhat"] < 1.05 and r["min_ess"] > 100
    assert r["max_mean_shift_sd"] < 0.5 and 0.75 < r["sd_ratio_min"] and r["sd_ratio_max"] < 1.25


# --------------------------------------------------------------------------- interval calibration (cross-conformal)


def test_conformal_scale_is_one_when_the_noise_model_is_right_quick():
    """The quick version (the full one below is slow): a 500-row dance at 20 C (9 parameters), 4 folds of 10 %:
    c within the declared band 0.8-1.25 (wider: 200 fold rows) and every fold row scored once."""
    from bayesmag._src.pipeline.conformal import conformal_folds
    from bayesmag._src.pipeline.field_stage import magnitude_interval_scale
    c = simulate_field("dance", n=500, seed=5)
    d = c.data
    y = field_target(Constant(50.0), n=d.n)
    f = fit_field(d.b_meas, d.temperature, y, Constant(50.0), diagnostics=False)
    white = magnitude_interval_scale(d, Constant(50.0), y, fraction=0.1, folds=4, start=f)
    assert 0.8 <= white["scale"] <= 1.25
    assert white["n"] == int(np.sum(conformal_folds(d.run, fraction=0.1, folds=4, seed=0) >= 0)) == 200


@pytest.mark.slow
def test_conformal_scale_is_one_when_the_noise_model_is_right():
    """White reading noise (the Laplace predictive is right): the fold scale c is ~1 (declared band 0.85-1.2)
    and every training row of a fold is scored once. (On the Belsten recordings c = 1.27:
    tests/test_field_job.py::test_scalar_belsten_against_vector_fit.)"""
    from bayesmag._src.pipeline.conformal import conformal_folds
    from bayesmag._src.pipeline.field_stage import magnitude_interval_scale
    c = simulate_field("dance", n=1000, seed=5, temperature=(15.0, 35.0))
    d = c.data
    f = fit_field(d.b_meas, d.temperature, c.f_ref, Scalar())
    white = magnitude_interval_scale(d, Scalar(), c.f_ref, fraction=0.08, folds=5, start=f)
    assert 0.85 <= white["scale"] <= 1.2
    assert white["n"] == int(np.sum(conformal_folds(d.run, fraction=0.08, folds=5, seed=0) >= 0)) == 400


@pytest.mark.extended
def test_fit_with_keep_equals_the_fit_of_the_kept_rows():
    """``keep`` (rows carried with weight 0) gives the same fit as the subset (one compiled solver for all folds)."""
    c = simulate_field("dance", n=800, seed=6, temperature=(15.0, 35.0))
    d = c.data
    keep = np.ones(d.n, bool)
    keep[200:300] = False
    a = fit_field(d.b_meas, d.temperature, c.f_ref, Scalar(), keep=keep)
    b = fit_field(d.b_meas[keep], d.temperature[keep], c.f_ref[keep], Scalar())
    assert a.n == b.n == 700 and a.model.t0 == b.model.t0
    assert np.allclose(a.theta, b.theta, rtol=1e-7, atol=1e-9) and np.allclose(a.cov, b.cov, rtol=1e-6, atol=1e-14)


# --------------------------------------------------------------------------- training domain of held-out rows


@pytest.mark.parametrize("dt, scale, reason", [(20.0, 1.0, "temperature"), (0.0, 1.2, "magnitude"), (0.0, 1.0, "")])
def test_field_domain_check_flags_rows_outside_the_training_ranges(dt, scale, reason):
    """Held-out rows of the same campaign (every 4th row of a 15 -> 25 C dance) lie inside; moved 20 C warmer, or
    predicted at 1.2 times the field, every row is flagged with that reason. The temperature limit is the rule's
    (5 % of the span plus 0.5 C below the training minimum)."""
    import dataclasses
    from bayesmag._src.pipeline.field_stage import field_domain_check
    d = simulate_field("dance", n=400, seed=1, temperature=(15.0, 25.0)).data
    held = np.arange(400) % 4 == 0
    tr, te = d.subset(np.flatnonzero(~held)), d.subset(np.flatnonzero(held))
    te = dataclasses.replace(te, temperature=te.temperature + dt)
    r = field_domain_check(tr, np.linalg.norm(tr.b_ref, axis=1), te, scale * np.linalg.norm(te.b_ref, axis=1))
    if reason:
        assert not r["in_domain"].any() and set(r["reason"]) == {reason} and r["by_reason"] == {reason: 100}
    else:
        assert r["in_domain"].all() and r["n_outside"] == 0 and set(r["reason"]) == {""}
    lo, hi = r["training_ranges"]["temperature"]
    assert np.isclose(lo, tr.temperature.min() - 0.05 * np.ptp(tr.temperature) - 0.5)


# --------------------------------------------------------------------------- a noisy scalar reference


def _level_turn_heading_coverage(seed, ref_sd):
    c = simulate_field("level_turns", n=2000, seed=seed)
    d, tr = c.data, c.truth
    test = np.zeros(d.n, bool)
    for b in range(4):                                        # bench_field's held-out time blocks
        s = int((0.1 + 0.22 * b) * d.n)
        test[s:s + d.n // 20] = True
    f = fit_field(d.b_meas[~test], d.temperature[~test], c.f_ref[~test], Scalar(ref_sd))
    lv = tr.level & test
    h = heading_with_uncertainty(f, d.b_meas[lv], d.temperature[lv], tr.alignment(d.temperature[lv]))
    e = wrap_deg(h["heading"] - tr.heading[lv])
    return np.abs(e) <= scipy.stats.norm.ppf(0.975) * h["sd"], f, h


@pytest.mark.extended
def test_noisy_scalar_reference_heading_intervals_cover_on_level_turns():
    """Level turns, scalar reference with 0.01 uT noise (its sd given): heading intervals pooled over 6 seeds not
    used to develop the weight (200-205) cover >= 0.85 (declared; measured 0.937). The old 1/g weight (ref_sd
    not given, ``Scalar(0.0)``) covers 0.454 on the same rows: the reference's noise divided by g pulled the
    vertical scale (docs/field.md, Heading)."""
    hits, fits = [], []
    for seed in range(200, 206):
        ok, f, h = _level_turn_heading_coverage(seed, 0.01)
        hits.append(ok)
        fits.append(f)
        assert h["flagged"] == (f.weighting != "total")      # flagged only where the refit was rejected
    assert np.mean(np.concatenate(hits)) >= 0.85
    assert sum(f.weighting == "total" for f in fits) >= 5       # the reference-noise refit was kept
    ok0, f0, h0 = _level_turn_heading_coverage(200, 0.0)
    assert f0.weighting == "gain" and f0.kappa2 == 0.0 and not h0["flagged"]


def test_total_weight_is_the_residual_sd_in_reading_units():
    """At the true parameters, magnitude residual / sqrt(g^2 + kappa^2) has the reading noise's variance (closed
    form: var = s^2 g^2 + ref^2); the old weight 1/g leaves ref^2 / g^2 on top. 40,000 rows of a dance, no vehicle,
    noise 0.05 uT, reference noise 0.03 uT: the variance ratio's standard error is 0.7 %."""
    from bayesmag._src.core.field import FieldModel
    c = simulate_field("dance", n=40000, seed=3, ref_sd=0.03, vehicle=False)
    tr, d = c.truth, c.data
    m = FieldModel(Scalar(0.03), t0=20.0, temperature=False)       # the campaign is at 20 C (+- 0.05 C)
    R, U = gauge_form(tr.M(20.0))
    th = m.pack(U, None, R.T @ tr.o(20.0), None)
    u, t, y = (jnp.asarray(a) for a in (d.b_meas, d.temperature, c.f_ref))
    k2 = (0.03 / 0.05) ** 2
    new = np.var(np.asarray(m.residual(th, u, t, y, k2))) / 0.05**2
    old = np.var(np.asarray(m.residual(th, u, t, y))) / 0.05**2
    assert abs(new - 1) < 0.03 and old > 1.2


def test_degenerate_reference_noise_refit_is_rejected_and_flagged():
    """Level turns, seed 10: the total-sd refit slides to M -> 0 (gains 0.31, 0.31, 0.09; offset error 528 uT), outside
    the prior's 99.9 % gain range: it is rejected, the 1/g fit kept, and the heading flagged with a note."""
    _, f, h = _level_turn_heading_coverage(10, 0.01)
    assert f.weighting.startswith("gain (") and f.kappa2 == 0.0 and h["flagged"]
    assert any("degenerate solution" in n for n in f.notes)
    assert np.all(np.abs(np.diag(f.matrices()[0]) - 1.0) < 0.5)


def test_refit_from_a_total_weight_fit_keeps_its_weight():
    """A cross-validation refit (``start=``) of a reference-noise fit uses the same weight and kappa, and reports
    the sandwich covariance (symmetric, positive definite)."""
    c = simulate_field("level_turns", n=1200, seed=1)
    d = c.data
    f = fit_field(d.b_meas, d.temperature, c.f_ref, Scalar(0.01))
    keep = np.arange(d.n) % 5 != 0
    g = fit_field(d.b_meas, d.temperature, c.f_ref, Scalar(0.01), keep=keep, start=f, diagnostics=False)
    assert f.weighting == g.weighting == "total" and g.kappa2 == f.kappa2 > 0
    assert np.allclose(g.cov, g.cov.T) and np.linalg.eigvalsh(g.cov)[0] > 0


@pytest.mark.parametrize("case, match", [
    ("nan_u", r"fit_field: u has 2 row\(s\) with non-finite values \(NaN or inf\) at row\(s\) 4, 9 \(counting from 1\)"),
    ("nan_target", r"fit_field: target has 1 row\(s\) with non-finite values \(NaN or inf\) at row\(s\) 6 "),
    ("12_rows", r"fit_field: 12 rows but the field model has 18 parameters: a fit needs more rows than parameters"),
    ("12_vector_rows", r"fit_field: 8 rows \(24 residuals\) but the field model has 24 parameters"),
])
def test_fit_field_refuses_nan_rows_and_too_few_rows(case, match):
    """From Python: NaN rows are a DataError naming them (they were a LinAlgError from the covariance), and rows
    that do not exceed the parameters are refused (12 rows for 18 parameters reported s = 2e-14 uT). No fit runs."""
    from bayesmag._src.core.data import DataError
    c = simulate_field("dance", n=40, seed=0, temperature=(15.0, 35.0))
    u, t, f = c.data.b_meas.copy(), c.data.temperature.copy(), c.f_ref.copy()
    meas = Scalar()
    if case == "nan_u":
        u[[3, 8], 1] = np.nan
    elif case == "nan_target":
        f[5] = np.inf
    elif case == "12_rows":
        u, t, f = u[:12], t[:12], f[:12]
    else:
        u, t, f, meas = u[:8], t[:8], c.data.b_ref[:8], Vector()
    with pytest.raises(DataError, match=match):
        fit_field(u, t, f, meas)


def test_level_turns_without_tilt_are_refused_as_planar():
    """Level turns with no tilt: the readings span a plane, and a magnitude fit shrank the field to a constant
    (gains 0.03 / 0.03 / 0.001, heading error 24 deg, magnitude 'RMSE' 8e-5 uT, coverage 100 %) without a word.
    ``fit_field`` now refuses it (``PLANAR_RATIO``): the readings' spread along their thinnest direction, net of
    temperature-driven change, is 1.0-1.1x the noise for flat turns (constant or ramped temperature), and 1.8x with
    0.25 deg of tilt, which fits well (heading 0.12 deg in simulation)."""
    from bayesmag._src.core.data import DataError
    from bayesmag._src.core.field import PLANAR_ASPECT, PLANAR_RATIO, planar_spread
    from bayesmag._src.core.field_sim import field_campaign_from_config
    for temps in ([20.0, 20.0], [15.0, 40.0]):
        flat = field_campaign_from_config({"kind": "level_turns", "n": 1500, "tilt_deg": 0.0, "seed": 1,
                                           "temperature": temps}).data
        ratio, _, _, aspect = planar_spread(flat.b_meas, flat.temperature, flat.run)
        assert ratio < PLANAR_RATIO and aspect > PLANAR_ASPECT
        with pytest.raises(DataError, match="span a plane"):
            fit_field(flat.b_meas, flat.temperature, np.full(flat.n, 50.0), Constant(50.0))
        tilted = field_campaign_from_config({"kind": "level_turns", "n": 1500, "tilt_deg": 0.25, "seed": 1,
                                             "temperature": temps}).data
        assert planar_spread(tilted.b_meas, tilted.temperature, tilted.run)[0] > 1.5


# --------------------------------------------------------------------------- the declared field against the readings


@pytest.fixture(scope="module")
def two_temperature_50():
    """The outside tester's campaign: two temperatures, 50 uT site field (the readings' |B| median is 48.8 uT)."""
    return simulate_field("two_temperature", n=1000, sensor_seed=7, seed=1)


@pytest.mark.parametrize("field, match", [
    (5.0, r"The declared field F = 5 uT is 0\.1\d*x the field the readings support \(49\.\d uT after the fitted "
          r"hard-iron offset\): the calibration it implies has gains .*not a sensor but a wrong field\. Likely cause: "
          r"the horizontal intensity H given for the total intensity F.*a typo \(a missing digit is /10\)"),
    (25.0, r"F = 25 uT is 0\.5\d*x the field .*Likely cause: the horizontal intensity H given for the total intensity "
           r"F.*these readings support about 49\.\d uT"),
    (500.0, r"F = 500 uT is 10\.\dx the field .*Likely cause: a typo \(an extra digit is x10\)"),
    (50000.0, r"fit_field: constant field 50000\.0 is not a magnitude in uT .* looks like nT \(x1000\)"),
])
@pytest.mark.extended
def test_fit_field_refuses_a_declared_field_off_by_a_factor(two_temperature_50, field, match):
    """From Python: Constant(5.0) converged to S_xx = -0.105 with no note, Constant(25.0) (H typed for F) to gains
    0.52 / 0.49 / 0.50 with a magnitude RMSE half the reading noise, Constant(500.0) to S_yy 0.0004, O_y 498 uT,
    Constant(50000.0) to S_zz 11.7 (the command line refused 50000 as nT). Now each is a DataError naming the
    declared field, the field the readings support and the likely cause (FIELD_SCALE_REFUSE, GAIN_REFUSE)."""
    from bayesmag._src.core.data import DataError
    d = two_temperature_50.data
    with pytest.raises(DataError, match=match):
        fit_field(d.b_meas, d.temperature, field_target(Constant(field), n=d.n), Constant(field))


def test_a_declared_field_in_the_warning_band_warns_and_notes(two_temperature_50):
    """F = 37 uT for the 49.4 uT the readings support: overall gain 0.75, between the refusal (2/3) and warning (0.8)
    limits. The fit is returned, with a CalibrationWarning at the caller's line and the same text in its notes."""
    from bayesmag._src.core.data import CalibrationWarning
    d = two_temperature_50.data
    with pytest.warns(CalibrationWarning, match=r"F = 37 uT is 0\.7\d*x .*\(overall 0\.7\d.* horizontal intensity H") as w:
        f = fit_field(d.b_meas, d.temperature, field_target(Constant(37.0), n=d.n), Constant(37.0))
    assert [x.filename for x in w if issubclass(x.category, CalibrationWarning)] == [__file__]
    assert f.notes[0].startswith("The declared field F = 37 uT")


@pytest.mark.parametrize("meas", [Constant(50.0), Scalar()], ids=["constant", "scalar"])
@pytest.mark.extended
def test_a_large_hard_iron_offset_and_10_percent_gains_do_not_warn(meas):
    """Against false alarms (an independent check): the right field, readings with a 30-40 uT hard-iron offset and
    gains 10 % off (diag 1.1, 0.9, 1.1). The raw |B| median is far from 50 uT (a naive comparison would cry wolf);
    the fitted gains are 0.91-1.11, overall 0.96-1.0: no warning, no refusal."""
    import warnings
    from bayesmag._src.core.data import CalibrationWarning
    from bayesmag._src.core.field import field_scale_check, supported_field
    c = simulate_field("dance", n=1200, seed=4, temperature=(15.0, 35.0))
    d = c.data
    u = d.b_meas @ np.diag([1.1, 0.9, 1.1]) + np.array([30.0, -40.0, 35.0])
    assert abs(np.median(np.linalg.norm(u, axis=1)) / 50.0 - 1.0) > 0.3
    with warnings.catch_warnings():
        warnings.simplefilter("error", CalibrationWarning)
        f = fit_field(u, d.temperature, field_target(meas, f_ref=c.f_ref, n=d.n), meas)
    sv = np.linalg.svd(f.matrices()[0], compute_uv=False)
    assert 0.85 < sv.min() and sv.max() < 1.2, sv
    assert field_scale_check(f, u, c.f_ref) == ("ok", "") and not any("declared field" in n for n in f.notes)
    assert abs(supported_field(u) / 50.0 - 1.0) < 0.1                 # the offset removed, gains averaging ~1


def test_a_level_turn_fit_whose_vertical_drifted_is_no_evidence_of_a_wrong_field():
    """Level turns, scalar reference with noise (seed 103): the vertical gain is the prior's answer and the refit
    drifted to gains 0.52 / 0.51 / 0.24 (overall 0.40) while its heading intervals still cover (docs/field.md).
    Judged on the point estimate alone it would be refused as 'a wrong field'; the limits count only beyond GAIN_Z
    posterior sds (sd of log k here about 1.1), so it passes without a warning."""
    import warnings
    from bayesmag._src.core.data import CalibrationWarning
    from bayesmag._src.core.field import gain_check, log_gain_sd
    with warnings.catch_warnings():
        warnings.simplefilter("error", CalibrationWarning)
        _, f, _ = _level_turn_heading_coverage(103, 0.01)
    g = gain_check(f.matrices()[0], f.model.measurement)
    assert g["verdict"] == "refuse" and g["overall"] < 0.6                 # the point estimate alone: refused
    assert gain_check(f.matrices()[0], f.model.measurement, log_gain_sd(f))["verdict"] == "ok"


def test_a_saved_calibration_with_a_wrong_field_is_refused_when_read(two_temperature_50):
    """A field_params.json written before the check, from a fit at H for F (gains 0.5): FieldCalibration.from_json
    (what `bayesmag apply` and bayesmag.load_field read) refuses it, naming the gains and the declared field."""
    from bayesmag._src.core.field_calibration import DOMAIN_KEYS, FieldCalibration
    d = two_temperature_50.data
    f = fit_field(d.b_meas, d.temperature, field_target(Constant(50.0), n=d.n), Constant(50.0), diagnostics=False)
    doc = FieldCalibration(f, 1.0, 0.95, {k: (-1e3, 1e3) for k in DOMAIN_KEYS}).to_json()
    assert FieldCalibration.from_json(doc).fit.model.measurement == Constant(50.0)
    n_s = sum(name.startswith("S_") for name in f.param_names)
    doc = {**doc, "theta": [0.5 * v for v in doc["theta"][:n_s]] + doc["theta"][n_s:],
           "measurement": {**doc["measurement"], "field": 25.0}}
    with pytest.raises(ValueError, match=r"gains \(singular values of S\) 0\.5.* are not a magnetometer's .*declared "
                                         r"field F = 25 uT was probably wrong \(H given for the total intensity F"):
        FieldCalibration.from_json(doc)
