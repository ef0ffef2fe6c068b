"""Effect selection and the uninformed candidates' within-run variation (pipeline/sessions/hierarchical, issue 24 4a).

The mechanism Belsten run 3 left out showed (docs/sessions.md): a cross-axis term that no run sweeps is still
estimated as a shared parameter from the small within-run wobble of its input, and a run held at a large
field on that input then disagrees at its level; the model buys the disagreement with a large between-session
offset sd. Simulated here with a known truth; the reference is the truth and a grid integration of the
collapsed posterior.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bayesmag
from bayesmag._src.core.data import CalibrationData
from bayesmag._src.pipeline.sessions import hierarchical as H
from helpers import tau_grid_posterior

jax.config.update("jax_enable_x64", True)

TAU = 0.1            # true between-session offset sd, uT (every axis)
CROSS = 0.1          # the DUT's y reading picks up 0.1 of the x field (so the calibration's y-from-x term is +0.1)


def _ar1(rng, n, sd, rho):
    e = rng.normal(0.0, sd * np.sqrt(1 - rho**2), n)
    out = np.empty(n)
    out[0] = rng.normal(0.0, sd)
    for t in range(1, n):
        out[t] = rho * out[t - 1] + e[t]
    return out


def _conflict_campaign(seed: int, rows: int = 200, wobble: float = 1.0) -> CalibrationData:
    """Nine runs: one sweeps the y field (+-50 uT), one the z field, six sit near zero field, one holds x at 40
    uT; no run sweeps x. The DUT's x reading carries white noise of sd ``wobble`` uT that the reference does not
    see (errors in variables; below the selection rule's 10 % of the column's RMS, 13 uT), so the within-run slope
    of the y error on the x reading says y-from-x = 0 while the held run's level says +0.1. Session offsets
    N(0, TAU) per axis, reference noise AR(1) sd 0.02 uT, lag-1 0.8, constant temperature."""
    rng = np.random.default_rng(seed)
    parts, t0 = [], 0.0
    for r, kind in enumerate(["y", "z"] + ["zero"] * 6 + ["held_x"], start=1):
        B = rng.normal(0.0, 0.2, (rows, 3))
        if kind in ("y", "z"):
            B[:, "xyz".index(kind)] = np.linspace(-50.0, 50.0, rows)
        if kind == "held_x":
            B[:, 0] = 40.0
        meas = B + rng.normal(0.0, TAU, 3)
        meas[:, 1] -= CROSS * B[:, 0]
        meas[:, 0] += rng.normal(0.0, wobble, rows)
        ref = B + np.column_stack([_ar1(rng, rows, 0.02, 0.8) for _ in range(3)])
        parts.append((meas, ref, t0 + 0.25 * np.arange(rows), np.full(rows, r)))
        t0 += 0.25 * rows + 100.0
    m, ref, t, run = (np.concatenate(v) for v in zip(*parts))
    return CalibrationData(m, np.full(t.size, 24.0), ref, t, run)


def _fit(d):
    return bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper(t0=24.0, temperature=False))


def test_uninformed_within_lists_the_runs_that_do_not_inform_a_dropped_candidate():
    """The selection rule drops the three gains (x swept by no run, y and z by one each); the runs whose
    within-run variation is decoupled are every run but the one that sweeps the column, per output axis without
    the axis's own gain; with every candidate informed (the simulated campaigns) nothing is decoupled."""
    d = _conflict_campaign(0)
    fit = _fit(d)
    eff, dropped = H.select_effects(d, fit)
    assert eff == ("O",) and dropped == {"S_x": 0, "S_y": 1, "S_z": 1}
    w = H.uninformed_within(d, fit, list(dropped), axis=1)
    assert set(w) == {"S_x", "S_z"} and w["S_x"] == list(range(1, 10)) and 2 not in w["S_z"] and len(w["S_z"]) == 8
    from test_transfer import _session
    s = _session(0, 6, rows=60)
    sfit = bayesmag.fit_physics(s, bayesmag.PhysicsModel.paper(t0=float(np.mean(s.temperature))))
    keep, drop = H.select_effects(s, sfit)
    assert all(H.uninformed_within(s, sfit, list(drop), a) == {} for a in range(3)) or drop


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.extended
def test_decoupled_within_run_variation_recovers_the_between_session_sd(seed):
    """y axis: with the uninformed x term shared inside the runs (the old model) the posterior rms offset sd is
    spuriously large (declared: > 3 TAU; measured 1.08 / 1.10 uT against the true 0.1, the y-from-x term 0.002 /
    0.004: the noisy reading's attenuated slope); with the within-run variation decoupled (the default) it is
    within 0.5-2 TAU (measured 0.122 / 0.105), and the y-from-x term comes from the held run's level: within 0.01
    of the true +0.1 (measured 0.096 / 0.099). Not addressed: the x axis's own gain is not decoupled
    (uninformed_within), and the same noise in its own reading gives the x axis an offset sd of 4.2 uT under
    both models."""
    d = _conflict_campaign(seed)
    fit = _fit(d)
    old = H.fit_sessions(d, fit, within_uninformed=False, uninformed="fixed", mode_search=True)
    new = H.fit_sessions(d, fit, uninformed="fixed", mode_search=True)
    assert old.tau[1, 0] > 3 * TAU, old.tau[1]
    assert 0.5 * TAU < new.tau[1, 0] < 2 * TAU, new.tau[1]
    assert new.mu[1, list(fit.model.param_names).index("S_x")] == pytest.approx(CROSS, abs=0.01)


def test_learned_dof_with_decoupled_columns_drops_their_margin():
    """The learned-dof path (``transfer_df = "learned"``) on data with decoupled within-run columns: its posterior
    is over the model's parameters only, as the fixed-dof path's (the decoupled coefficients' margin dropped; before,
    the learned path kept them and the job failed on Belsten-like data with a shape mismatch in ``_take_axes``),
    the y-from-x term comes from the held run's level as with the Gaussian (within 0.01 of the true +0.1), and the
    row-wise transfer sd is finite, positive on y and z (x: the noisy own reading, above, puts the learned dof at
    2.5, whose 95 % interval is inside the within-session noise's Gaussian one: transfer sd 0, by construction)."""
    d = _conflict_campaign(0)
    fit = _fit(d)
    p = len(fit.model.param_names)
    post = H.fit_sessions(d, fit, likelihood="student_t", df="learned", uninformed="fixed")
    assert post.scale.shape == (3, p) and post.mu.shape == (3, p) and post.mu_cov.shape == (3, p, p)
    assert post.mu[1, list(fit.model.param_names).index("S_x")] == pytest.approx(CROSS, abs=0.01)
    sd = post.transfer_sd_for(fit, d)
    assert sd.shape == (d.b_ref.shape[0], 3) and np.isfinite(sd).all() and (sd[:, 1:] > 0).all()


@pytest.mark.slow
def test_decoupled_posterior_matches_grid_integration():
    """The importance-corrected Laplace posterior of the decoupled model against numerical integration of the
    same collapsed posterior (y axis, seed 0): a grid in log tau (step 0.2) and at each tau an 11 x 11 grid over
    +-6 conditional sds of (log sigma, atanh rho). Declared: E tau^2 within 10 %, P(tau > 0.2 uT) within 0.03;
    the posterior is unimodal (BFGS from both starts finds one mode)."""
    d = _conflict_campaign(0)
    fit = _fit(d)
    eff, dropped = H.select_effects(d, fit)
    st = H.run_stats(d, fit, eff, within=H.uninformed_within(d, fit, list(dropped), axis=1))
    a = 1
    args = tuple(jnp.asarray(x) for x in (st.m0[a], st.m1[a], st.m2[a], st.first[a], st.n, st.effects))
    lp = lambda h: H._collapsed(h, *args, H.TAU_PRIOR_SCALE, H.SIGMA_PRIOR_SCALE, H.REML)[0]  # noqa: E731
    fg = lambda h: tuple(np.asarray(v, np.float64) for v in H._neg_lp_and_grad(  # noqa: E731
        jnp.asarray(h), *args, H.TAU_PRIOR_SCALE, H.SIGMA_PRIOR_SCALE, H.REML))
    fg = (lambda f: lambda h: (float(f(h)[0]), f(h)[1]))(fg)
    found = H._modes(fg, H._init_h(st, a, H.TAU_PRIOR_SCALE), 1, H.TAU_PRIOR_SCALE)
    assert len(found) == 1
    w, tau = tau_grid_posterior(lp, found[0][0][1:], np.arange(-5.0, 1.5, 0.2), np.linspace(-6.0, 6.0, 11))
    e_tau2, p_big = float(w @ tau**2), float(w[tau > 0.2].sum())
    post = H.fit_laplace(st, fit.model.param_names, seed=0)
    assert post.w_mean[a, 0] == pytest.approx(e_tau2, rel=0.10)
    hs, _, _ = H._importance_draws(np.random.default_rng(0), *found[0], lambda x: H._lp_mu_cov(
        jnp.asarray(x), *args, H.TAU_PRIOR_SCALE, H.SIGMA_PRIOR_SCALE, H.REML), 1200)
    assert np.mean(np.exp(hs[:, 0]) > 0.2) == pytest.approx(p_big, abs=0.03)


def test_belsten_run_3_left_out_y_offset_sd_is_no_longer_the_conflict_mode():
    """Real data (issue 24 item 4a): Belsten with run 3 left out, y axis. The old model (uninformed terms shared
    inside the runs) puts most of the offset sd's posterior on the conflict mode (grid: E tau^2 2.34 uT^2, rms
    1.53 uT; measured here 1.36 rms); decoupled (the default) it is declared below 0.3 uT rms (measured 0.11; grid
    of the decoupled posterior E tau^2 0.015, rms 0.12, benchmarks/bench_hierarchical.py belsten_tau)."""
    from bayesmag._src.core.datasets import load_dataset

    d = load_dataset("belsten2023")
    train = d.subset(np.flatnonzero(d.run != 3))
    fit = bayesmag.fit_physics(train, bayesmag.PhysicsModel.paper(t0=0.0))
    assert H.fit_sessions(train, fit, within_uninformed=False, uninformed="fixed").tau[1, 0] > 1.0
    assert H.fit_sessions(train, fit, uninformed="fixed").tau[1, 0] < 0.3


def _held_and_swept(seed: int, noise: float = 0.05) -> tuple[CalibrationData, dict]:
    """Four runs of 120 rows (reading noise ``noise`` uT on every DUT axis, reference noise 0.01 uT, a known
    truth): run 1 holds the field still, run 2 sweeps it along one line, runs 3-4 step it over all three axes;
    expected weak field directions 3, 2, 0, 0."""
    rng = np.random.default_rng(seed)
    parts, runs = [], []
    line = np.array([1.0, 2.0, -1.0]) / np.sqrt(6.0)
    for r, kind in enumerate(("held", "line", "steps", "steps"), start=1):
        steps = {"held": np.tile([10.0, -20.0, 30.0], (6, 1)),
                 "line": np.outer(np.linspace(-40, 40, 6), line) + [5.0, 0.0, 0.0],
                 "steps": rng.uniform(-40, 40, (6, 3))}[kind]
        true = np.repeat(steps, 20, axis=0)
        parts.append(true)
        runs.append(np.full(true.shape[0], r))
    true = np.concatenate(parts)
    run = np.concatenate(runs)
    meas = true + rng.normal(0.0, noise, true.shape)
    d = CalibrationData(meas, np.full(run.size, 24.0), true + rng.normal(0.0, 0.01, true.shape),
                        np.arange(run.size, dtype=float), run)
    return d, {1: 3, 2: 2, 3: 0, 4: 0}


@pytest.mark.parametrize("seed", [0, 1])
def test_weak_directions_are_the_runs_unswept_field_directions(seed):
    """A run's directions whose within-run sd is small and white (``weak_directions``): the held run all three field
    directions, the line run the two across the line, the stepped runs none; the line run's two are orthogonal to
    the line (cosine under 0.01). Without reading noise nothing varies there (no direction); rows in random order
    (an iid design) give the same directions: the swept ones vary by far more than a tenth of the RMS."""
    d, expected = _held_and_swept(seed)
    fit = bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper(temperature=False))
    names = list(fit.model.param_names)
    eff = [e for e in H.DEFAULT_EFFECTS if e in names]
    weak = H.weak_directions(d, fit, eff, axis=0)
    assert {r: W.shape[1] for r, W in weak.items()} == {r: k for r, k in expected.items() if k}
    W = weak[2][[names.index(f"S_{a}") for a in "xyz"]]                 # the field rows of the line run's directions
    line = np.array([1.0, 2.0, -1.0]) / np.sqrt(6.0)
    # J W is the direction's score: zero along the line up to the noise's tilt of the fitted line (0.05 / 30 uT)
    np.testing.assert_allclose((W / np.linalg.norm(W, axis=0)).T @ line, 0.0, atol=1e-2)
    # noise-free readings: a held run has no variation at all, so no direction (nothing to decouple); the line run's
    # two directions across the line have none either
    d0, _ = _held_and_swept(seed, noise=0.0)
    assert H.weak_directions(d0, bayesmag.fit_physics(d0, fit.model), eff, axis=0) == {}
    # rows in random order: the held run's noise stays white, the swept directions stay large
    perm = np.random.default_rng(seed).permutation(d.n)
    shuffled = H.weak_directions(d.subset(perm), fit, eff, axis=0)
    assert {r: W.shape[1] for r, W in shuffled.items()} == {r: k for r, k in expected.items() if k}


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.extended
def test_noise_only_directions_no_longer_inflate_short_campaigns(seed):
    """Clean 8-session campaigns of 100-row runs (no distortion; ``tests/test_transfer.py::_session``, reading noise
    0.05 uT): several runs hold the field still or sweep it along a line, and their reading noise along the unswept
    directions reads as a gain of about zero (errors in variables). Without the weak directions (``weak=None``) one
    axis's transfer sd is 8-13x leave-one-run-out's (seed 1 z 4.1 against 0.40 uT, seed 2 y 3.0 against 0.35, seed 3
    z 4.2 against 0.34); with them every axis is within 1.5x of it (measured 0.51-1.20x) and the job does not warn."""
    from test_transfer import _session
    from bayesmag._src.core.predictor import estimate_transfer

    d = _session(seed, 8, rows=100, noise_sd=0.05)
    fit = bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature))))
    loro = estimate_transfer(d, fit).sd
    rms = lambda post: np.sqrt(np.mean(post.transfer_sd_for(fit, d) ** 2, axis=0))     # noqa: E731
    before = rms(H.fit_sessions(d, fit, weak=None)) / loro
    tr, _ = H.hierarchical_transfer(d, fit)
    after = tr.sd / loro
    assert before.max() > 5.0, before
    assert after.max() < 1.5 and tr.warning is None, (after, tr.warning)
    # metrics.json says how many directions each run set aside (the held runs: the most)
    per_run = tr.per_run["model"]["weak_directions_per_run"]
    assert per_run and all(int(r) in set(d.run) and 1 <= k <= 4 for r, k in per_run.items()), per_run
