"""Transfer (between-session) uncertainty and the dynamic domain, on simulated session shifts."""

import numpy as np
import pytest

import bayesmag
from bayesmag import CalibrationData
from bayesmag._src.core.domain import Domain, rates
from bayesmag._src.app.job import _residual_variance
from bayesmag._src.core.predictor import Predictor, UQOptions, estimate_transfer
from bayesmag._src.core.simulate import TrueParams

SIGMA_IN = np.diag([0.02**2] * 3 + [1e-4])
OFFSET_SD, CROSS_SD = 0.3, 0.003          # session-to-session change: offsets (uT), off-diagonal S terms


def _shifted_params(rng, offset=lambda rng: rng.normal(0, OFFSET_SD, 3), cross_sd: float = CROSS_SD) -> TrueParams:
    """The paper's parameters with a session's change: offsets + ``offset(rng)`` (uT), each off-diagonal
    S term + N(0, ``cross_sd``)."""
    p = TrueParams.paper()
    s = p.S + np.where(np.eye(3) == 1, 0.0, rng.normal(0, cross_sd, (3, 3)))
    return TrueParams(s, p.Ks, p.O + offset(rng), p.Ko)


def _session(seed: int, n_runs: int, rows: int = 200, first_run: int = 1, kind: int = 0,
             session_params=_shifted_params, noise_sd: float = 0.02, effects=()) -> CalibrationData:
    """``n_runs`` campaigns (runs), each a session with its own offsets and cross-axis terms
    (``session_params(rng)``, default Gaussian offsets sd 0.3 uT and cross-axis sd 0.003); heated and
    room-temperature runs alternate, starting with heated (``kind`` even) or room (odd); ``effects``:
    distortions every session shares (``simulate``'s)."""
    rng = np.random.default_rng(seed)
    parts = []
    for k in range(n_runs):
        d = bayesmag.simulate.simulate(rows, design="campaign", seed=seed * 100 + k, params=session_params(rng),
                                       noise_sd=noise_sd, n_runs=1,
                                       run_kinds=["thermal" if (k + kind) % 2 == 0 else "room"], field_range=40.0,
                                       effects=effects)
        parts.append((d, first_run + k))
    t_off = 0.0
    cols = {"b_meas": [], "temperature": [], "b_ref": [], "time": [], "run": []}
    for d, r in parts:
        cols["b_meas"].append(d.b_meas)
        cols["temperature"].append(d.temperature)
        cols["b_ref"].append(d.b_ref)
        cols["time"].append(d.time + t_off)
        cols["run"].append(np.full(d.n, r))
        t_off += d.time.max() + 100.0
    return CalibrationData(*(np.concatenate(cols[k]) for k in ("b_meas", "temperature", "b_ref", "time", "run")))


def _new_sessions(draw: int, n: int, session_params=_shifted_params) -> list[CalibrationData]:
    """The ``n`` new one-run sessions of training draw ``draw`` (seeds 10000 + 1000 draw + s; heated and
    room alternate), drawn afresh for every draw."""
    return [_session(10_000 + 1000 * draw + s, 1, kind=s, session_params=session_params) for s in range(n)]


def _stacked(sessions: list[CalibrationData]) -> CalibrationData:
    """The sessions as one recording, session k as run k + 1: one predict call, row for row the same intervals
    and domain flags as a call per session (every row-wise quantity, and the rates within runs)."""
    return CalibrationData(np.concatenate([s.b_meas for s in sessions]), np.concatenate([s.temperature for s in sessions]),
                           np.concatenate([s.b_ref for s in sessions]), np.concatenate([s.time for s in sessions]),
                           np.concatenate([np.full(s.n, k + 1) for k, s in enumerate(sessions)]))


def test_stacked_sessions_predict_as_the_sessions_one_by_one():
    pr = _calibrate(_session(1, 30, rows=100))
    news = _new_sessions(1, 6)
    p = pr.predict(_stacked(news))
    one = [pr.predict(n) for n in news]
    np.testing.assert_array_equal(p.interval(0.95), np.concatenate([o.interval(0.95) for o in one], axis=1))
    np.testing.assert_array_equal(p.in_domain, np.concatenate([o.in_domain for o in one]))


def _calibrate(train: CalibrationData) -> Predictor:
    model = bayesmag.PhysicsModel.paper(t0=float(np.mean(train.temperature)))
    fit = bayesmag.fit_physics(train, model)
    tr = estimate_transfer(train, fit)        # the job's path: all folds in one compiled fit (fit_folds)
    assert tr.method == "leave_one_run_out" and tr.warning is None

    class _Cfg:      # the settings _residual_variance reads
        class uq:
            method, n_params, n_qmc, seed, chunk_size = "analytic", 50, 64, 0, 256
    resid = np.sqrt(_residual_variance(_Cfg, fit, train, SIGMA_IN))
    return Predictor(fit=fit, sigma_in=SIGMA_IN, residual_sd=resid, transfer_sd=tr.sd, domain=Domain.from_data(train),
                     uq=UQOptions(method="analytic"))


@pytest.mark.extended
def test_session_shift_is_covered_or_flagged():
    """Fit on 30 simulated sessions (one run each), apply to 40 new sessions with shifted offsets and
    cross-axis terms; repeated for 20 training draws, each with its own new sessions.

    Declared bands, the issue's: in-domain coverage of the 95 % intervals 90-98 % per axis and at
    least 95 % of the rows covered or flagged out of domain, both pooled over the 20 draws: the
    coverage a calibration procedure promises is marginal over the training data and the new
    session. One draw says little: a session's shift is constant over its rows, so the sessions,
    not the rows, are the sample, and the transfer sd from 30 runs is noisy; one draw's coverage has
    an sd of 3-4 % per axis (``benchmarks/bench_transfer.py --draws 30 --sessions 40``, the same
    draws: mean 97.1 / 96.4 / 96.4 %, docs/uncertainty.md), the mean of 20 draws about 0.8 %. Fresh
    sessions per draw: one shared set of 40 moves every draw the same way (98.2 / 94.3 / 96.4 % over
    the same 30 training draws with the sessions 1000-1039, ``--shared``).
    """
    covered, in_dom, bare_covered, taus = [], [], [], []
    for draw in range(20):
        pr = _calibrate(_session(draw, 30, rows=100))
        taus.append(pr.transfer_sd)
        bare = Predictor(fit=pr.fit, sigma_in=pr.sigma_in, residual_sd=pr.residual_sd, uq=pr.uq)
        new = _stacked(_new_sessions(draw, 40))                       # bench_transfer.py's fresh sessions
        p = pr.predict(new)
        lo, hi = p.interval(0.95)
        covered.append((new.b_ref >= lo) & (new.b_ref <= hi))
        in_dom.append(p.in_domain)
        assert np.all(p.transfer == pr.transfer_sd)
        lo, hi = bare.predict(new).interval(0.95)
        bare_covered.append((new.b_ref >= lo) & (new.b_ref <= hi))
    # The pooled fit's residual sd already holds part of the between-session scatter (the sessions'
    # offsets differ by OFFSET_SD = 0.3 uT); tau is the excess of the leave-one-run-out error over it.
    taus = np.array(taus)
    assert np.all((taus > 0.05) & (taus < 0.6)), taus
    covered, in_dom = np.concatenate(covered), np.concatenate(in_dom)
    assert in_dom.mean() > 0.5
    cov_in = covered[in_dom].mean(axis=0)
    ok = (covered | ~in_dom[:, None]).mean(axis=0)
    print(f"in-domain coverage {cov_in}, rows in domain {in_dom.mean():.4f}, covered or flagged {ok}")  # pytest -s
    assert np.all((cov_in >= 0.90) & (cov_in <= 0.98)), cov_in
    assert np.all(ok >= 0.95), ok
    # without the transfer part the within-session intervals under-cover new sessions
    bare_in = np.concatenate(bare_covered)[in_dom].mean(axis=0)
    assert np.all(bare_in < cov_in - 0.02), (bare_in, cov_in)


def test_fewer_than_three_runs_widen_to_the_largest_offset_change_with_a_warning():
    d = _session(5, 2)
    model = bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature)))
    fit = bayesmag.fit_physics(d, model)
    tr = estimate_transfer(d, fit, lambda x: bayesmag.fit_physics(x, model))
    assert tr.method == "largest_offset_change" and "cannot be estimated" in tr.warning
    r = d.b_ref - np.asarray(fit.predict(bayesmag.inputs_from_data(d)))
    want = np.abs(r[d.run == 1].mean(0) - r[d.run == 2].mean(0))
    np.testing.assert_allclose(tr.sd, want, rtol=1e-12)
    one = d.subset(np.flatnonzero(d.run == 1))
    tr1 = estimate_transfer(one, bayesmag.fit_physics(one, model), None)
    assert np.all(tr1.sd == 0) and "no between-session term" in tr1.warning


def test_rates_are_difference_quotients_within_runs():
    t = np.r_[np.arange(5.0), np.arange(5.0)]
    run = np.r_[np.ones(5, int), np.full(5, 2)]
    b = np.zeros((10, 3))
    b[:5, 0] = 2.0 * t[:5]                  # 2 uT/s ramp in run 1
    b[5:, 1] = np.r_[0, 0, 3, 3, 3]         # a 3 uT step in run 2 at t = 2
    temp = np.r_[20 + 0.1 * t[:5], np.full(5, 20.0)]
    d = CalibrationData(b, temp, None, t, run)
    r = rates(d)
    np.testing.assert_allclose(r[:5, 0], 2.0)
    np.testing.assert_allclose(r[5:, 1], [0, 3, 3, 0, 0])
    np.testing.assert_allclose(r[:5, 3], 0.1)
    order = np.r_[9, 3, 0, 7, 5, 1, 8, 2, 6, 4]   # row order does not matter: time order within each run
    np.testing.assert_allclose(rates(d.subset(order)), r[order])


def test_fast_rows_are_flagged_with_their_reason():
    train = _session(7, 3)
    dom = Domain.from_data(train)
    new = _session(8, 1)
    fast = CalibrationData(new.b_meas.copy(), new.temperature.copy(), None, new.time / 50.0, new.run)  # 50x faster
    out = dom.outside(fast)
    why = dom.reasons(out)
    assert out.shape == (new.n, 8)
    too_fast = (rates(fast)[:, :3] > np.asarray(dom.rate_high[:3])).any(axis=1)
    assert too_fast.mean() > 0.05                         # the steps between held fields, 50x faster
    np.testing.assert_array_equal(["field_rate" in w for w in why], too_fast)
    assert set(";".join(why).replace(";", " ").split()) <= {"field_range", "temperature", "field_rate",
                                                           "temperature_rate"}
    slow = dom.reasons(dom.outside(new))
    assert not any("rate" in w for w in slow)
    hot = CalibrationData(new.b_meas, new.temperature + np.linspace(0, 5, new.n) * (new.time > 0),
                          None, new.time, new.run)
    assert any("temperature" in w for w in dom.reasons(dom.outside(hot)))


@pytest.mark.parametrize("n_runs", [4])
def test_fold_fits_equal_separate_fits(n_runs):
    """fit_folds (weight-0 rows, one compile) gives each fold's own LM solution and the same transfer sd
    as refitting every fold separately with fit_physics.

    Tolerance: the two are different float programs stopped by the same LM rule (relative cost change
    < 1e-12), which pins a weakly determined parameter only to ~sqrt(1e-12) of its scale, so the
    parameters must agree to 1e-4 of their posterior sd (seen: at most 5e-10 absolute,
    2e-7 sd) and the transfer sd to 1e-6 relative."""
    from bayesmag._src.core.fit import fit_folds
    d = _session(7, n_runs, rows=150)
    model = bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature)))
    keep = np.stack([d.run != r for r in np.unique(d.run)])
    theta, ok = fit_folds(d, model, keep)
    assert ok.all()
    for k in range(keep.shape[0]):
        sep = bayesmag.fit_physics(d.subset(np.flatnonzero(keep[k])), model)
        sd = sep.std
        assert np.all(np.abs(theta[k] - np.asarray(sep.theta)) <= 1e-4 * sd), (theta[k] - sep.theta) / sd
    fit = bayesmag.fit_physics(d, model)
    np.testing.assert_allclose(estimate_transfer(d, fit).sd,
                               estimate_transfer(d, fit, lambda x: bayesmag.fit_physics(x, model)).sd, rtol=1e-6)


def test_transfer_sd_is_the_chi_square_bound_on_the_whole_new_session_variance():
    """estimate_transfer against the formula written out here: separate leave-one-run-out fits, the
    in-domain rows of each left-out run, q = the 95 % quantile of (e / z)^2 - s^2 with every run
    weighted equally (inverted CDF), and tau^2 = (s^2 + q) (R - 1) / chi2_{R-1}(0.2) - s^2 (scipy)."""
    import scipy.stats
    d = _session(11, 5, rows=120)
    model = bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature)))
    fit = bayesmag.fit_physics(d, model)
    z, s2 = scipy.stats.norm.ppf(0.975), np.asarray(fit.s2)
    values, weights = [], []
    for r in np.unique(d.run):
        other, left = d.subset(np.flatnonzero(d.run != r)), d.subset(np.flatnonzero(d.run == r))
        rows = left.subset(np.flatnonzero(~Domain.from_data(other, rates=False).outside(left).any(axis=1)))
        e = rows.b_ref - bayesmag.fit_physics(other, model).predict(bayesmag.inputs_from_data(rows))
        values.append((e / z) ** 2 - s2)
        weights.append(np.full(rows.n, 1.0 / rows.n))
    v, w = np.concatenate(values), np.concatenate(weights)
    q = np.empty(3)
    for a in range(3):
        order = np.argsort(v[:, a], kind="stable")
        q[a] = v[order[np.cumsum(w[order]) >= 0.95 * w.sum() - 1e-12][0], a]
    bound = (len(values) - 1) / scipy.stats.chi2.ppf(0.2, len(values) - 1)
    want = np.sqrt(np.maximum((s2 + q) * bound - s2, 0.0))
    tr = estimate_transfer(d, fit)
    assert tr.method == "leave_one_run_out" and len(values) == 5
    np.testing.assert_allclose(tr.sd, want, rtol=1e-6)
    assert np.all(want > np.sqrt(np.maximum(q, 0.0) * bound))       # wider than the bound on q alone


@pytest.mark.parametrize("method", ["analytic", "psqmc"])
@pytest.mark.extended
def test_run_offsets_are_not_carried_to_a_new_session(method):
    """``run_offset`` fits an offset for each training run (fixed parameters of those runs). A new session whose
    run ids happen to equal training ids is predicted as under fresh ids (before: its run 2 got training run 2's
    offset, and the physics UQ failed on the term's columns). Leave-one-run-out refits each fold without the
    left-out run's offset and predicts that run as a new session (before: no fold was usable, and the fallback
    read 1e-11 uT, the offsets having taken the run-to-run change out of the residual means). Declared, over three
    training draws (one draw's coverage varies by several % whatever the model: test_session_shift_is_covered_or_
    flagged): the transfer sd within 0.5-2x that of the model without the term (both estimate the same session
    shift), and 8 new sessions per draw with shifted offsets (sd 0.3 uT; reading noise 0.02 uT) covered at >= 90 %
    per axis on average (measured 0.99 / 0.94 / 0.93; the model without the term 0.95 / 0.92 / 0.92)."""
    from bayesmag._src.core.catalogue import RunOffset
    covers = []
    for seed in (3, 4, 5) if method == "analytic" else (3,):
        train = _session(seed, 6, rows=200)
        t0 = float(np.mean(train.temperature))
        model = bayesmag.PhysicsModel.paper(t0=t0, extra=(RunOffset(runs=(1, 2, 3, 4, 5, 6)),))
        fit = bayesmag.fit_physics(train, model)
        tr = estimate_transfer(train, fit)
        plain = estimate_transfer(train, bayesmag.fit_physics(train, bayesmag.PhysicsModel.paper(t0=t0)))
        assert tr.method == plain.method == "leave_one_run_out" and tr.warning is None
        assert np.all((tr.sd > 0.5 * plain.sd) & (tr.sd < 2 * plain.sd)), (tr.sd, plain.sd)
        pr = Predictor(fit=fit, sigma_in=SIGMA_IN, residual_sd=np.full(3, 0.02), transfer_sd=tr.sd,
                       uq=UQOptions(method=method, n_params=40, n_qmc=64))
        new = _stacked(_new_sessions(seed, 8))                      # runs 1-8: 1-6 are training ids
        p = pr.predict(new)
        q = pr.predict(CalibrationData(new.b_meas, new.temperature, new.b_ref, new.time, new.run + 100))
        np.testing.assert_allclose(p.mean, q.mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(p.interval(0.95), q.interval(0.95), rtol=1e-12, atol=1e-12)
        lo, hi = p.interval(0.95)
        covers.append(np.mean((new.b_ref >= lo) & (new.b_ref <= hi), axis=0))
    if method == "analytic":
        assert np.all(np.mean(covers, axis=0) >= 0.9), covers


def test_with_two_runs_the_fallback_holds_the_run_offset():
    """Two runs leave leave-one-run-out nothing to fold: the fallback's run-to-run change of the mean residual is
    taken without the run offset (a new session is calibrated without it), so it holds the fitted offset (declared:
    0.7-1.3x its size); before, 1e-11 uT."""
    from bayesmag._src.core.catalogue import RunOffset
    train = _session(3, 2, rows=300)
    model = bayesmag.PhysicsModel.paper(t0=float(np.mean(train.temperature)), extra=(RunOffset(runs=(1, 2)),))
    fit = bayesmag.fit_physics(train, model)
    tr = estimate_transfer(train, fit)
    assert tr.method == "largest_offset_change" and "taken without the model's run_offset" in tr.warning
    span = np.abs(np.asarray(fit.theta)[:, model.param_names.index("o_2")])
    assert np.all((tr.sd > 0.7 * span) & (tr.sd < 1.3 * span)), (tr.sd, span)
