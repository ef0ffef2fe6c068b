"""The hierarchical session model (pipeline/sessions): closed forms, recovery, Laplace vs NUTS, the job option."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

import bayesmag
from bayesmag._src.pipeline.sessions import hierarchical as H
from test_transfer import _session
from helpers import tau_grid_posterior

jax.config.update("jax_enable_x64", True)


def _ar1_cov(n, sigma, rho):
    i = np.arange(n)
    return sigma**2 / (1 - rho**2) * rho ** np.abs(i[:, None] - i[None, :])


@pytest.mark.parametrize("rho", [0.0, 0.6, -0.3])
def test_run_loglik_equals_the_dense_gaussian_density(rho):
    """Lag moments + Woodbury against scipy's multivariate normal with the full covariance
    J L L^T J^T + AR(1)(sigma, rho), on one random run; tolerance 1e-8 relative."""
    rng = np.random.default_rng(1)
    n, p, k = 40, 4, 2
    X = rng.normal(size=(n, p))
    y = rng.normal(size=n)
    mu, L, sigma = rng.normal(size=p), rng.normal(size=(p, k)) * 0.5, 0.7
    z = np.column_stack([X, y])
    m0 = z[1:].T @ z[1:]
    m1 = z[1:].T @ z[:-1]
    m2 = z[:-1].T @ z[:-1]
    first = np.outer(z[0], z[0])
    G = H.whitened_gram(m0, m1, m2, first, rho)
    got = float(H.run_loglik(jnp.asarray(G), n, jnp.asarray(mu), jnp.asarray(L), sigma**2, rho))
    cov = X @ L @ L.T @ X.T + _ar1_cov(n, sigma, rho)
    want = scipy.stats.multivariate_normal(X @ mu, cov).logpdf(y)
    np.testing.assert_allclose(got, want, rtol=1e-8)


def test_student_t_match_of_the_variance_mixture():
    """The row-wise Student-t (two moments of v matched to a scaled inverse chi-square) against the
    mixture it stands for, sampled: v ~ scaled-inv-chi2(nu=7, s^2=0.04) exactly; the 95 % half-width
    of N(0, v) mixed over v must equal the matched t's within 1 % (Monte Carlo, 400 000 draws)."""
    rng = np.random.default_rng(0)
    nu, s2 = 7.0, 0.04
    v = nu * s2 / rng.chisquare(nu, 400_000)
    m, var = nu * s2 / (nu - 2), 2 * nu**2 * s2**2 / ((nu - 2) ** 2 * (nu - 4))
    post = H.SessionPosterior(w_mean=np.tile([0.0, m], (3, 1)), w_cov=np.tile(np.diag([0.0, var]), (3, 1, 1)),
                              mu_cov=np.zeros((3, 1, 1)), scale=np.ones((3, 1)), effects=("O",), level=0.95,
                              n_runs=5, method="laplace", mu=np.zeros((3, 1)), effect_index=(0,))
    df, sc = post.predictive_t(np.ones((3, 1, 1)))
    np.testing.assert_allclose(df, nu, rtol=1e-9)
    np.testing.assert_allclose(sc, np.sqrt(s2), rtol=1e-9)
    mc = np.quantile(np.abs(rng.normal(size=v.size) * np.sqrt(v)), 0.95)
    half = np.sqrt(post.new_session_variance(np.ones((3, 1, 1)))) * scipy.stats.norm.ppf(0.975)
    np.testing.assert_allclose(half, mc, rtol=0.01)


def test_transfer_grows_with_the_field_when_gains_move():
    """A gain random effect makes the transfer sd row-dependent: larger at a larger field on that axis
    (closed form: the effect's variance times the squared scaled Jacobian)."""
    post = H.SessionPosterior(w_mean=np.tile([0.01, 0.04, 1e-4], (3, 1)), w_cov=np.zeros((3, 3, 3)),
                              mu_cov=np.zeros((3, 2, 2)), scale=np.tile([1.0, 20.0], (3, 1)), effects=("O", "S_x"),
                              level=0.95, n_runs=30, method="laplace", mu=np.zeros((3, 2)), effect_index=(0, 1))
    J = np.zeros((3, 2, 2))
    J[:, :, 0] = 1.0
    J[:, :, 1] = [0.0, 40.0]                # B_x = 0 and 40 uT
    sd = post.transfer_sd(J)
    np.testing.assert_allclose(sd[:, 0], np.sqrt([0.01, 0.01 + 0.04 * 4]), rtol=1e-3)   # df -> large: Gaussian


@pytest.mark.extended
def test_recovers_a_simulated_between_session_sd():
    """30 simulated sessions (offsets N(0, 0.3) uT, cross-axis N(0, 0.003)): the posterior rms offset sd
    within 0.18-0.45 uT on every axis (30 groups: the sd of an sd estimate is ~13 %, three axes, so a
    +-50 % band is loose but not vacuous) and the diagonal gain sd (true 0) under 0.03 uT."""
    d = _session(0, 30, rows=100)
    model = bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature)))
    fit = bayesmag.fit_physics(d, model)
    post = H.fit_sessions(d, fit)
    assert post.effects == ("O", "Ko", "S_x", "S_y", "S_z")
    tau = post.tau
    assert np.all((tau[:, 0] > 0.18) & (tau[:, 0] < 0.45)), tau
    assert np.all(np.diag(tau[:, 2:]) < 0.03), tau


def test_effects_that_too_few_runs_inform_are_dropped():
    """On the Belsten recordings each field axis is swept in one or two runs: the gains' session changes
    cannot be learned from them and are left out; the offset, seen by every run, stays."""
    from bayesmag._src.core.datasets import load_dataset
    d = load_dataset("belsten2023")
    fit = bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper())
    keep, dropped = H.select_effects(d, fit)
    assert keep == ("O",) and set(dropped) == {"Ko", "S_x", "S_y", "S_z"} and max(dropped.values()) < 3


@pytest.mark.slow
def test_laplace_agrees_with_nuts_on_a_small_case():
    """10 sessions x 60 rows, the default candidate effects (O, Ko, S_x, S_y, S_z): the row-wise transfer sd
    of the Laplace path within 10 % of NUTS's (non-centred explicit effects, 500 + 500 draws), and the
    noise variance within 2 %. Measured: Laplace / NUTS 0.93-1.01 with mu integrated (the default); with mu
    profiled (reml = 0, before issue 24's follow-up) 0.82-0.94 (docs/sessions.md)."""
    d = _session(3, 10, rows=60)
    model = bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature)))
    fit = bayesmag.fit_physics(d, model)
    st = H.run_stats(d, fit)
    lap = H.fit_laplace(st, model.param_names)
    nuts = H.fit_nuts(st, model.param_names, fit)
    new = _session(10_000, 1)
    J = H._jacobian(fit, new)
    np.testing.assert_allclose(lap.transfer_sd(J), nuts.transfer_sd(J), rtol=0.10)
    np.testing.assert_allclose(lap.w_mean[:, -1], nuts.w_mean[:, -1], rtol=0.02)


@pytest.mark.extended
def test_config_option_end_to_end(tmp_path):
    """`[uq] transfer = "hierarchical"`: the job fits it, saves it in the calibration, and apply gives the
    same row-dependent transfer column as the job's predictor; a damaged saved array is refused."""
    from bayesmag._src.app.artifact import ArtifactError, load
    from bayesmag._src.app.config import config_from_dict
    from bayesmag._src.app.job import run_job
    from bayesmag._src.core.data import write_csv

    d = _session(2, 6, rows=120)
    csv = tmp_path / "d.csv"
    write_csv(d, csv)
    cfg = config_from_dict({"name": "h", "data": {"path": str(csv)}, "split": {"kind": "by_run", "test_runs": [6]},
                            "physics": {"t0": "mean"}, "uq": {"method": "analytic", "transfer": "hierarchical"},
                            "output": {"figures": False}})
    res = run_job(cfg, tmp_path / "out")
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["transfer"]["method"] == "hierarchical_laplace"
    pr = res["predictor"]
    assert pr.sessions is not None and pr.transfer_sd is None
    test = d.subset(np.flatnonzero(d.run == 6))
    cal = load(tmp_path / "out")
    out = cal.predict(test)
    want = pr.transfer_part(test)
    np.testing.assert_allclose(out["transfer"], want, rtol=1e-10)
    assert np.ptp(want[:, 0]) > 0                       # row-dependent
    _check_condition_table(tmp_path / "out", m, res)
    arrays = dict(np.load(tmp_path / "out" / "calibration.npz"))
    arrays["sessions/w_cov"] = arrays["sessions/w_cov"][:, :1]
    np.savez(tmp_path / "out" / "calibration.npz", **arrays)
    with pytest.raises(ArtifactError, match="sessions/w_cov"):
        load(tmp_path / "out")


@pytest.mark.extended
def test_hybrid_predictor_carries_the_session_model(tmp_path):
    """Network enabled with `transfer = "hierarchical"`: the hybrid predictor keeps the session posterior,
    its new-session variance is the within-session hybrid variance plus the row-dependent transfer sd
    squared (closed form of the composition), and the saved calibration (network + sessions) reloads to
    the same transfer column and the same totals."""
    import csv

    from bayesmag._src.app.artifact import load
    from bayesmag._src.app.config import config_from_dict
    from bayesmag._src.app.job import run_job
    from bayesmag._src.core.data import write_csv

    d = _session(2, 6, rows=120)
    csv_path = tmp_path / "d.csv"
    write_csv(d, csv_path)
    cfg = config_from_dict({"name": "hh", "data": {"path": str(csv_path)},
                            "split": {"kind": "by_run", "test_runs": [6]}, "physics": {"t0": "mean"},
                            "uq": {"method": "analytic", "transfer": "hierarchical"},
                            "network": {"enabled": True, "likelihoods": ["gaussian"], "hidden_layers": 1, "width": 8,
                                        "batch_size": 128, "max_epochs": 4, "mc_passes": 4, "seed": 2},
                            "output": {"figures": False, "progress": False}})
    res = run_job(cfg, tmp_path / "out")
    run = res["run"]
    pr = res["predictor"]
    assert pr.network is not None and pr.sessions is not None and pr.transfer_sd is None
    assert run.hybrid.predictors["gaussian"].sessions is pr.sessions
    test = d.subset(np.flatnonzero(d.run == 6))
    want = pr.transfer_part(test)
    assert np.ptp(want[:, 0]) > 0                                        # row-dependent, not an axis constant
    pred = run.hybrid.predictions["gaussian"]
    np.testing.assert_allclose(pred.parts["transfer"], want, rtol=1e-8)
    comp = pr.components(test)
    same = pr.compose(comp, new_session=False)
    np.testing.assert_allclose(pred.total**2, same.total**2 + want**2, rtol=1e-6)
    cal = load(tmp_path / "out")
    assert cal.sessions is not None and cal.network is not None
    out = cal.predict(test)
    np.testing.assert_allclose(out["transfer"], want, rtol=1e-10)
    rows = list(csv.DictReader(open(tmp_path / "out" / "predictions.csv")))
    for a, ax in enumerate("xyz"):
        np.testing.assert_allclose(out["total"][:, a], [float(r[f"{ax}_hybrid_total"]) for r in rows], rtol=1e-6)


def _check_condition_table(out, m, res):
    """report.md's per-condition U for a new session (issue 24 item 6): the six corners (training min / zero /
    max field x min / max temperature) with the predictor's transfer sd there, and U = k sqrt(u_same^2 + sd^2),
    k from Welch-Satterthwaite with the transfer at infinite dof (recomputed here with scipy's t quantile)."""
    import re

    from bayesmag._src.core.data import CalibrationData

    train = res["data"].subset(res["split"].train)
    conds = m["transfer"]["per_run"]["conditions"]
    assert len(conds) == 6
    lo, hi = train.b_meas.min(0), train.b_meas.max(0)
    np.testing.assert_allclose(conds[0]["field"], lo)
    np.testing.assert_allclose(conds[5]["field"], hi)
    assert conds[0]["temperature"] == pytest.approx(train.temperature.min())
    assert conds[5]["temperature"] == pytest.approx(train.temperature.max())
    b = np.array([c["field"] for c in conds])
    t = np.array([c["temperature"] for c in conds])
    sd = res["predictor"].transfer_part(CalibrationData(b, t, None, np.arange(6.0), np.zeros(6, int)))
    got = np.array([[c["transfer_sd"][a] for a in "xyz"] for c in conds])
    np.testing.assert_allclose(got, sd, rtol=1e-9)
    assert np.ptp(got[:, 0]) > 0                                       # differs between the corners
    text = (out / "report.md").read_text()
    assert "U new session x / y / z" in text
    table = [ln for ln in text.splitlines() if re.match(r"\| -?[0-9.]+ / -?[0-9.]+ / -?[0-9.]+ \| ", ln)]
    assert len(table) == 6, table
    ex = bayesmag._src.app.report.expanded_uncertainties(m, json.loads((out / "params.json").read_text()))
    for row, c in zip(table, got):
        U = [float(v) for v in row.split("|")[4].split("/")]
        for a, ax in enumerate("xyz"):
            same = ex["same_session"][ax]
            uc2 = same["u_c"] ** 2 + c[a] ** 2
            nu = uc2**2 / (same["u_c"] ** 4 / same["nu_eff"])      # Welch-Satterthwaite, transfer dof inf
            k = scipy.stats.t.ppf(0.975, nu)
            want = k * np.sqrt(uc2)             # the table rounds to 2 significant digits: half its last digit
            half = 0.5 * max(10.0 ** (np.floor(np.log10(abs(v))) - 1) for v in (want, U[a]))
            assert abs(U[a] - want) <= half * (1 + 1e-9), (U[a], want)


@pytest.mark.parametrize("rho,df", [(0.0, 3.0), (0.6, 5.0), (-0.3, 30.0)])
def test_student_t_run_density_equals_scipy_multivariate_t(rho, df):
    """The Student-t likelihood (issue 24 item 5): one run's log density, effects integrated, against scipy's
    multivariate t with shape J L L^T J^T + AR(1)(sigma, rho) and ``df`` dof; tolerance 1e-8 relative."""
    rng = np.random.default_rng(2)
    n, p, k = 30, 3, 2
    X = rng.normal(size=(n, p))
    y = rng.normal(size=n) * 2
    mu, L, sigma = rng.normal(size=p), rng.normal(size=(p, k)) * 0.5, 0.7
    z = np.column_stack([X, y])
    G = H.whitened_gram(z[1:].T @ z[1:], z[1:].T @ z[:-1], z[:-1].T @ z[:-1], np.outer(z[0], z[0]), rho)
    got = float(H.run_loglik(jnp.asarray(G), n, jnp.asarray(mu), jnp.asarray(L), sigma**2, rho, df))
    want = scipy.stats.multivariate_t(X @ mu, X @ L @ L.T @ X.T + _ar1_cov(n, sigma, rho), df=df).logpdf(y)
    np.testing.assert_allclose(got, want, rtol=1e-8)


@pytest.mark.extended
def test_student_t_collapsed_posterior_is_the_profile_at_the_mode():
    """``_collapsed_t`` (profile over mu by reweighted GLS): its log posterior minus the priors equals the sum of
    the runs' multivariate-t densities at its mu (1e-9), and that mu is the maximum (gradient ~ 0)."""
    d = _session(4, 8, rows=60, session_params=lambda g: _heavy_params(g))
    fit = bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature))))
    st = H.run_stats(d, fit, ("O",))
    a, df = 0, 4.0
    h = jnp.asarray([np.log(0.2), np.log(0.02), np.arctanh(0.5)])
    args = [jnp.asarray(x) for x in (st.m0[a], st.m1[a], st.m2[a], st.first[a], st.n)]
    lp, mu, cov = H._collapsed_t(h, *args, jnp.asarray(st.effects), 1.0, 1.0, 0.0, df)
    tau, sigma, rho = np.exp(h[0]), np.exp(h[1]), np.tanh(h[2])
    p = mu.shape[0]
    L = jnp.zeros((p, 1)).at[int(st.effects[0]), 0].set(tau)
    G = H.whitened_gram(*args[:4], rho)

    def total(m):
        return sum(H.run_loglik(G[r], st.n[r], m, L, sigma**2, rho, df) for r in range(st.n.size))

    prior = -0.5 * (tau / 1.0) ** 2 + h[0] - 0.5 * sigma**2 + h[1] + np.log1p(-rho**2)
    np.testing.assert_allclose(float(lp) - float(prior), float(total(mu)), rtol=1e-9)
    g = np.asarray(jax.grad(total)(mu))
    assert np.abs(g).max() < 1e-6 * np.abs(np.asarray(jax.hessian(total)(mu))).max(), g


def _heavy_params(rng):
    from test_transfer import _shifted_params
    return _shifted_params(rng, lambda g: 0.3 * g.standard_t(2.5, 3) / np.sqrt(5.0))


@pytest.mark.extended
def test_student_t_transfer_from_the_config(tmp_path):
    """`[uq] transfer_likelihood = "student_t"`, `transfer_df = 5`: the job's session posterior is the Student-t
    one, saved and reloaded (same transfer column), its row-wise predictive dof at most 5 (the likelihood's
    own tails bound the moment-matched t's), and a bad df is refused naming the key."""
    from bayesmag._src.app.artifact import load
    from bayesmag._src.app.config import ConfigError, config_from_dict
    from bayesmag._src.app.job import run_job
    from bayesmag._src.core.data import write_csv

    d = _session(5, 6, rows=80, session_params=_heavy_params)
    csv_path = tmp_path / "d.csv"
    write_csv(d, csv_path)
    raw = {"name": "ht", "data": {"path": str(csv_path)}, "split": {"kind": "by_run", "test_runs": [6]},
           "physics": {"t0": "mean"}, "output": {"figures": False},
           "uq": {"method": "analytic", "transfer": "hierarchical", "transfer_likelihood": "student_t",
                  "transfer_df": 5.0}}
    res = run_job(config_from_dict(raw), tmp_path / "out")
    post = res["predictor"].sessions
    assert post.likelihood == "student_t" and post.df == 5.0
    test = d.subset(np.flatnonzero(d.run == 6))
    df_rows, _ = post.predictive_t(H._jacobian(res["predictor"].fit, test))
    assert np.all(df_rows <= 5.0 + 1e-9)
    cal = load(tmp_path / "out")
    assert cal.sessions.df == 5.0
    np.testing.assert_allclose(cal.predict(test)["transfer"], res["predictor"].transfer_part(test), rtol=1e-7)
    with pytest.raises(ConfigError, match="uq.transfer_df"):
        config_from_dict({**raw, "uq": {**raw["uq"], "transfer_df": 2.0}})


def test_uninformed_effects_keep_their_prior_about_the_training_mean():
    """`with_prior_effects` (issue 24 item 1): a parameter too few runs sweep adds its prior second moment
    s^2 (f - f_bar)^2 to the mean new-session variance of a row (closed form; f the scaled Jacobian column,
    f_bar its training mean), nothing at f = f_bar, and Var tau^2 = 2 s^4 to the variance moments; the
    default ("pooled") gives each uninformed effect the learned offset's moments of tau^2."""
    from bayesmag._src.core.datasets import load_dataset
    d = load_dataset("belsten2023")
    fit = bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper())
    fixed = H.fit_sessions(d, fit, uninformed="fixed")
    assert fixed.effects == ("O",) and fixed.prior_only == ()
    post = H.with_prior_effects(fixed, fit, d, ["S_x"], tau_scale=0.5)
    assert post.effects == ("O", "S_x") and post.prior_only == ("S_x",)
    j = list(fit.model.param_names).index("S_x")
    J = H._jacobian(fit, d)
    f = J[:, :, j] / fixed.scale[:, None, j]                              # (3, n)
    fbar = f.mean(axis=1)
    m0, v0, _ = fixed.variance_moments(J)
    m1, v1, _ = post.variance_moments(J)
    np.testing.assert_allclose(m1 - m0, (0.25 * (f - fbar[:, None]) ** 2).T, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(v1 - v0, (2 * 0.5**4 * (f - fbar[:, None]) ** 4).T, rtol=1e-9, atol=1e-15)
    pooled = H.fit_sessions(d, fit)                     # default: exchangeable with the learned offset
    assert pooled.prior_only == ("Ko", "S_x", "S_y", "S_z")
    np.testing.assert_allclose(pooled.w_mean[:, 1:5], np.repeat(pooled.w_mean[:, :1], 4, axis=1), rtol=1e-12)
    np.testing.assert_allclose(np.diagonal(pooled.w_cov, axis1=1, axis2=2)[:, 1:5],
                               np.repeat(pooled.w_cov[:, :1, 0], 4, axis=1), rtol=1e-12)
    at_mean = J[:, :1].copy()
    at_mean[:, 0, j] = fbar * fixed.scale[:, j]
    np.testing.assert_allclose(post.variance_moments(at_mean)[0], fixed.variance_moments(at_mean)[0], rtol=1e-12)


def test_belsten_run_3_left_out_is_covered_or_flagged():
    """Real data, the case issue 24 found short (y 88 % with the offset-only model): with run 3 left out (the
    only run that sweeps the x field), the default hierarchical transfer (restricted likelihood, uninformed gains
    carried) covers or flags at least 95 % of run 3's rows on every axis. Measured: 100 / 98.1 / 100 %
    (uninformed effects pooled with the offset; with their half-normal prior 100 / 100 / 100, with none 100 / 93.5 / 100)."""
    from bayesmag._src.core.datasets import load_dataset
    from bayesmag._src.core.domain import Domain
    from bayesmag._src.core.predictor import Predictor, UQOptions

    d = load_dataset("belsten2023")
    train, test = d.subset(np.flatnonzero(d.run != 3)), d.subset(np.flatnonzero(d.run == 3))
    fit = bayesmag.fit_physics(train, bayesmag.PhysicsModel.paper(t0=0.0))
    from bayesmag._src.pipeline.settings import UQSettings
    from bayesmag._src.pipeline.stages import residual_variance

    sin = bayesmag.estimate_input_noise(d)                  # as benchmarks/bench_hierarchical.py belsten
    resid = np.sqrt(residual_variance(UQSettings(method="analytic"), fit, train, sin))
    tr, post = H.hierarchical_transfer(train, fit)          # the job's call: fit_sessions' defaults, and its checks
    pr = Predictor(fit=fit, sigma_in=sin, residual_sd=resid, domain=Domain.from_data(train),
                   uq=UQOptions(method="analytic"), sessions=post)
    p = pr.predict(test)
    lo, hi = p.interval(0.95)
    ok = ((test.b_ref >= lo) & (test.b_ref <= hi)) | ~p.in_domain[:, None]
    assert np.all(ok.mean(0) >= 0.95), ok.mean(0)
    # Covered, but x and z far wider than loro's (18.6 and 9.2 uT: run 6's x level read as session change,
    # docs/sessions.md "And run 3's x axis"): the job says so on exactly those two axes (measured 120x and 27x loro's
    # sd; y 0.74x); on runs 1 and 2 left out it says nothing (bench_hierarchical.py belsten: no 4(d) failure there).
    said = [w for w in tr.warning.split(". ") if "leave-one-run-out's" in w]
    assert len(said) == 1 and " on x (" in said[0] and " on z (" in said[0] and " on y (" not in said[0], tr.warning
    assert "the only heated run" in tr.warning
    # ... and, with the default transfer_check = "loro", those two axes take leave-one-run-out's sd (the model
    # failed its check there), y keeps the model's row-wise one
    assert post.checked_axes == ("x", "z") and "failed its check" in tr.warning


@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_laplace_run_density_equals_scipy(rho):
    """The Laplace session likelihood (issue 24 item 1): one run's rows jointly N(0, w V), w ~ Exp(1). One row:
    scipy.stats.laplace with variance V (1e-5 relative: the 32-node quadrature is least exact for one row); 5 and 30 rows: the closed form with scipy's Bessel K
    (``kve``) and the dense V (1e-8 relative), and for 5 rows scipy's numerical integral over w of
    scipy.stats.multivariate_normal (1e-6 relative)."""
    import scipy.integrate
    import scipy.special

    rng = np.random.default_rng(3)
    p, k, sigma = 3, 2, 0.7
    for n in (1, 5, 30):
        X = rng.normal(size=(n, p))
        y = rng.normal(size=n) * 1.5
        mu, L = rng.normal(size=p), rng.normal(size=(p, k)) * 0.5
        z = np.column_stack([X, y])
        G = H.whitened_gram(z[1:].T @ z[1:], z[1:].T @ z[:-1], z[:-1].T @ z[:-1], np.outer(z[0], z[0]), rho)
        got = float(H.run_loglik(jnp.asarray(G), n, jnp.asarray(mu), jnp.asarray(L), sigma**2, rho, "laplace"))
        V = X @ L @ L.T @ X.T + _ar1_cov(n, sigma, rho)
        r = y - X @ mu
        if n == 1:
            want = scipy.stats.laplace(0.0, np.sqrt(V[0, 0] / 2)).logpdf(r[0])
            np.testing.assert_allclose(got, want, rtol=1e-5)
            continue
        Q = r @ np.linalg.solve(V, r)
        nu = 1 - n / 2
        want = (-n / 2 * np.log(2 * np.pi) - 0.5 * np.linalg.slogdet(V)[1] + np.log(2) + nu / 2 * np.log(Q / 2)
                + np.log(scipy.special.kve(nu, np.sqrt(2 * Q))) - np.sqrt(2 * Q))
        np.testing.assert_allclose(got, want, rtol=1e-8)
        if n == 5:
            dens = lambda w: scipy.stats.multivariate_normal(np.zeros(n), w * V).pdf(r) * np.exp(-w)  # noqa: E731
            num = scipy.integrate.quad(dens, 0, np.inf, epsabs=0, epsrel=1e-10, limit=200)[0]
            np.testing.assert_allclose(got, np.log(num), rtol=1e-6)


def test_importance_draws_recover_an_inverse_chi_square_variance():
    """The importance correction of the Laplace draws (``_importance_draws``): for a variance with the posterior of
    few groups, tau^2 ~ scaled-Inv-chi^2(nu = 10, 1), in x = log tau^2 the Gaussian approximation at the mode
    (mean 0, sd sqrt(2/nu)) gives E tau^2 = 1.105 and Var/mean^2 = 0.221; the exact values are nu/(nu-2) = 1.25
    and 2/(nu-4) = 0.333. Resampled draws: within 3 % and 0.05 (20 000 draws; the seed-to-seed sd of the
    ratio is about 0.015)."""
    nu = 10.0

    def lp(xs):
        x = xs[:, 0]
        return (-(nu / 2) * x - nu / (2 * np.exp(x)),)

    rng = np.random.default_rng(0)
    hs, _, ess = H._importance_draws(rng, np.zeros(1), np.array([[2 / nu]]), lp, 20_000, proposals=60_000)
    t2 = np.exp(hs[:, 0])
    assert ess > 20_000
    assert t2.mean() == pytest.approx(nu / (nu - 2), rel=0.03)
    assert t2.var() / t2.mean() ** 2 == pytest.approx(2 / (nu - 4), abs=0.05)


@pytest.mark.slow
@pytest.mark.parametrize("df", [4.0, "laplace"])
def test_scale_mixture_gradient_carries_the_mode_derivative(df):
    """``_collapsed_t`` finds mu by reweighting outside the gradient and one differentiable Newton step: its
    gradient in h (REML term included, which depends on d mu / d h) equals central differences of its value
    (1e-5 relative), for the Student-t and the Laplace likelihood."""
    d = _session(4, 6, rows=50, session_params=lambda g: _heavy_params(g))
    fit = bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature))))
    st = H.run_stats(d, fit, ("O", "S_x"))
    args = [jnp.asarray(x) for x in (st.m0[1], st.m1[1], st.m2[1], st.first[1], st.n)]
    f = lambda h: H._collapsed_t(h, *args, jnp.asarray(st.effects), 0.5, 1.0, 1.0, df)[0]  # noqa: E731
    h = jnp.asarray([np.log(0.2), np.log(0.05), np.log(0.03), np.arctanh(0.6)])
    g = np.asarray(jax.grad(f)(h))
    eps = 1e-3                      # five-point stencil: truncation ~eps^4, the mode's stopping rule's noise / eps
    v = lambda i, k: float(f(h.at[i].add(k * eps)))  # noqa: E731
    fd = np.array([(v(i, -2) - 8 * v(i, -1) + 8 * v(i, 1) - v(i, 2)) / (12 * eps) for i in range(h.size)])
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_laplace_posterior_is_saved_and_its_interval_is_never_below_the_laplace_one():
    """A Laplace session posterior: saved (meta + arrays) and read back as Laplace; its new-session equivalent
    variance is at least the Laplace's own at the mean variance (the moment-matched t, 6 dof for exact
    hyperparameters, has a 95 % interval 5.7 % shorter: scipy.stats.laplace against scipy.stats.t); a Gaussian
    meta with a df, or an unknown likelihood, is refused naming the field."""
    q, p = 1, 4
    post = H.SessionPosterior(np.array([[0.04, 0.01]] * 3), np.zeros((3, 2, 2)), np.zeros((3, p, p)), np.ones((3, p)),
                              ("O",), 0.95, 8, "laplace", np.zeros((3, p)), effect_index=(3,), laplace=True)
    meta, arrays = post.meta(), post.as_arrays()
    assert meta["likelihood"] == "laplace" and meta["df"] is None
    back = H.posterior_from_artifact(json.loads(json.dumps(meta)), arrays, ("S_x", "S_y", "S_z", "O"))
    assert back.laplace and back.likelihood == "laplace"
    J = np.zeros((3, 2, p))
    J[:, :, 3] = 1.0
    v = back.new_session_variance(J)
    z = scipy.stats.norm.ppf(0.975)
    lap = (scipy.stats.laplace(0, np.sqrt(0.05 / 2)).ppf(0.975) / z) ** 2
    np.testing.assert_allclose(v, lap, rtol=1e-9)
    t6 = scipy.stats.t.ppf(0.975, 6) * np.sqrt(4 / 6) / scipy.stats.laplace(0, np.sqrt(1 / 2)).ppf(0.975)
    assert t6 == pytest.approx(1 - 0.057, abs=0.002)
    for bad, field in (({**meta, "likelihood": "gaussian", "df": 3.0}, "sessions.df"),
                       ({**meta, "likelihood": "cauchy"}, "sessions.likelihood")):
        with pytest.raises(ValueError, match=field):
            H.posterior_from_artifact(bad, arrays, ("S_x", "S_y", "S_z", "O"))


def test_laplace_likelihood_from_the_config():
    """`[uq] transfer_likelihood = "laplace"` is accepted; an unknown family is refused naming the key and the
    choices."""
    from bayesmag._src.app.config import ConfigError, config_from_dict

    raw = {"name": "hl", "data": {"path": "d.csv"}, "uq": {"transfer": "hierarchical", "transfer_likelihood": "laplace"}}
    assert config_from_dict(raw).settings().uq.transfer_likelihood == "laplace"
    with pytest.raises(ConfigError, match="uq.transfer_likelihood.*laplace"):
        config_from_dict({**raw, "uq": {**raw["uq"], "transfer_likelihood": "cauchy"}})


def test_bimodal_between_session_sd_matches_grid_integration():
    """Real data, Belsten with run 3 left out, y axis (issue 24): the collapsed posterior of the offset's
    between-session sd is bimodal (a mode near 0.05 uT and one near 1.5 uT, which holds most of the mass), and
    BFGS from the small start found only the small mode; the importance draws then rested on an effective
    sample of 28-61 and E tau^2 moved 0.8-2.5 with the seed. ``fit_laplace(mode_search=True)`` (modes from two
    starts, mixture proposal) against numerical integration of the same posterior: a grid in log tau (step
    0.15), and at each tau a 15 x 15 grid over +-6 conditional sds of (log sigma, atanh rho) around their
    conditional mode.
    Declared: E tau^2 within 10 % and P(tau > 0.3 uT) within 0.03 of the grid's (measured: grid 2.34 and
    0.97, seeds 0 / 1 / 2 2.44 / 2.32 / 2.31), and an effective sample of at least 300 of 1200."""
    from bayesmag._src.core.datasets import load_dataset

    d = load_dataset("belsten2023")
    train = d.subset(np.flatnonzero(d.run != 3))
    fit = bayesmag.fit_physics(train, bayesmag.PhysicsModel.paper(t0=0.0))
    st = H.run_stats(train, fit, ("O",))
    a = 1
    args = tuple(jnp.asarray(x) for x in (st.m0[a], st.m1[a], st.m2[a], st.first[a], st.n, st.effects))
    lp = lambda h: H._collapsed(h, *args, H.TAU_PRIOR_SCALE, H.SIGMA_PRIOR_SCALE, H.REML)[0]  # noqa: E731
    w, tau = tau_grid_posterior(lp, [-3.4, 0.9], np.arange(-6.0, 2.5, 0.15), np.linspace(-6.0, 6.0, 15))
    e_tau2, p_big = float(w @ tau**2), float(w[tau > 0.3].sum())
    assert 0.5 < p_big < 0.995                      # the reference itself: mass on both sides of 0.3 uT
    post = H.fit_laplace(st, fit.model.param_names, seed=0, mode_search=True)
    assert post.w_mean[a, 0] == pytest.approx(e_tau2, rel=0.10)
    assert post.ess[a] >= 300
    rng = np.random.default_rng(0)
    fg = lambda h: tuple(np.asarray(v, np.float64) for v in H._neg_lp_and_grad(   # noqa: E731
        jnp.asarray(h), *args, H.TAU_PRIOR_SCALE, H.SIGMA_PRIOR_SCALE, H.REML))
    fg = (lambda f: lambda h: (float(f(h)[0]), f(h)[1]))(fg)
    found = H._modes(fg, H._init_h(st, a, H.TAU_PRIOR_SCALE), 1, H.TAU_PRIOR_SCALE)
    assert len(found) == 2
    hs, _, _ = H._importance_draws(rng, *found[0], lambda x: H._lp_mu_cov(jnp.asarray(x), *args, H.TAU_PRIOR_SCALE,
                                   H.SIGMA_PRIOR_SCALE, H.REML), 1200, more=found[1:])
    assert np.mean(np.exp(hs[:, 0]) > 0.3) == pytest.approx(p_big, abs=0.03)


@pytest.mark.parametrize("rho", [0.0, 0.6, 0.9])
def test_rho_start_is_the_within_run_lag_one_autocorrelation(rho):
    """``rho_start``: ten runs of 300 rows, each with its own offset and gain (sd 2 and 0.5: a pooled residual
    would read them as correlation near 1) and AR(1) noise of a known ``rho``. Declared: within 4 standard errors
    (``sqrt((1 - rho^2) / N)``, N = 3000 rows) plus 0.02 (the per-run fit's small-sample bias) of ``rho``."""
    rng = np.random.default_rng(1)
    R, n = 10, 300
    m0, m1, m2, first = (np.zeros((3, R, 3, 3)) for _ in range(4))
    for r in range(R):
        x = np.sin(np.linspace(0, 6, n) + r) * 20
        e = np.zeros(n)
        e[0] = rng.normal() / np.sqrt(1 - rho**2)
        for t in range(1, n):
            e[t] = rho * e[t - 1] + rng.normal()
        z = np.c_[np.ones(n), x, rng.normal(0, 2) + (1 + rng.normal(0, 0.5)) * x + 0.05 * e]
        m0[:, r], m1[:, r], m2[:, r] = z[1:].T @ z[1:], z[1:].T @ z[:-1], z[:-1].T @ z[:-1]
        first[:, r] = np.outer(z[0], z[0])
    st = H.RunStats(m0, m1, m2, first, np.full(R, n), np.ones((3, 2)), np.array([0]), np.arange(R))
    assert H.rho_start(st, 0) == pytest.approx(rho, abs=4 * np.sqrt((1 - rho**2) / (R * n)) + 0.02)


@pytest.mark.extended
def test_the_first_mode_is_the_higher_of_two_rho_starts():
    """12 sessions x 100 rows, white reading noise 0.1 uT (seed 7; ``bench_short_campaigns.py --runs 12 --noise
    0.1``). BFGS from ``rho`` 0.8 alone stops on z at ``rho`` 0.997 with between-session sds of 0.4-1.2 uT, 96
    nats below the mode at ``rho`` 0.04 (sds 0.07-0.23): z's transfer sd was 5.85x loro's, with the misfit
    warning. With the second start at the data's autocorrelation (0.04): measured 1.13x, no warning. Declared:
    the two starts' modes differ by > 50 nats (so the test can fail), z under 1.5x loro's, no misfit warning."""
    from bayesmag._src.core.predictor import estimate_transfer

    d = _session(7, 12, rows=100, noise_sd=0.1)
    fit = bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature))))
    eff, _ = H.select_effects(d, fit)
    a, q = 2, len(eff)
    st = H.run_stats(d, fit, eff, directions=H.weak_directions(d, fit, eff, a, H.WEAK_NOISE_MULTIPLE))
    args = tuple(jnp.asarray(x) for x in (st.m0[a], st.m1[a], st.m2[a], st.first[a], st.n, st.effects))
    f = jax.jit(lambda h: H._neg_lp_and_grad(h, *args, H.TAU_PRIOR_SCALE, H.SIGMA_PRIOR_SCALE, H.REML))
    fg = lambda h: tuple(np.asarray(v, np.float64) for v in f(jnp.asarray(h)))     # noqa: E731
    fg = (lambda g: lambda h: (float(g(h)[0]), g(h)[1]))(fg)
    h0 = H._init_h(st, a, H.TAU_PRIOR_SCALE)
    old = H._modes(fg, h0, q, H.TAU_PRIOR_SCALE, search=False)[0][0]
    new = H._modes(fg, h0, q, H.TAU_PRIOR_SCALE, search=False, rho=H.rho_start(st, a))[0][0]
    assert fg(old)[0] - fg(new)[0] > 50 and np.tanh(old[q + 1]) > 0.99 > 0.2 > np.tanh(new[q + 1])
    tr, _ = H.hierarchical_transfer(d, fit)
    assert tr.sd[a] < 1.5 * estimate_transfer(d, fit).sd[a]
    assert tr.warning is None or "leave-one-run-out's" not in tr.warning, tr.warning


@pytest.mark.extended
def test_a_shared_column_takes_a_common_distortion_out_of_the_session_spread():
    """``fit_sessions(shared=...)``: a distortion every session shares (the DUT's y reading gains 0.001 x^2, which
    the affine model lacks) is read as session change by the random slopes, because each run sweeps x over its
    own levels; given as a column with one coefficient for all runs (here the exact shape, x^2 less its run mean)
    it is fitted as what it is. Reference: the same sessions, noise and shifts without the distortion. Seed 0,
    root-mean-square y transfer sd over the training rows (uT): clean 0.35, distorted 1.10, distorted with the
    column 0.47 (declared: > 2x and < 1.5x the clean one); x and z move by < 20 %. The column's margin is dropped
    (the posterior is over the model's parameters)."""
    from bayesmag._src.core.simulate import get_effect

    quad = [get_effect("axis_quadratic", out="y", inp="x", coeff=0.001)]
    clean, dist = (_session(0, 8, rows=100, noise_sd=0.05, effects=e) for e in ((), quad))
    c = dist.b_meas[:, 0] ** 2
    for r in np.unique(dist.run):
        c[dist.run == r] -= c[dist.run == r].mean()

    def rms(d, shared=None):
        fit = bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature))))
        post = H.fit_sessions(d, fit, shared=shared)
        assert post.mu.shape == (3, len(fit.model.param_names))
        return np.sqrt(np.mean(post.transfer_sd_for(fit, d) ** 2, axis=0))

    ref, without, with_col = rms(clean), rms(dist), rms(dist, np.broadcast_to(c[None, :, None], (3, dist.n, 1)))
    assert without[1] > 2 * ref[1] and with_col[1] < 1.5 * ref[1], (ref, without, with_col)
    np.testing.assert_allclose(with_col[[0, 2]], ref[[0, 2]], rtol=0.2)
    with pytest.raises(ValueError, match="shared columns must have shape"):
        H.run_stats(dist, bayesmag.fit_physics(dist, bayesmag.PhysicsModel.paper(t0=30.0)), shared=c[None, :])


def test_the_job_warns_where_the_session_model_is_far_wider_than_leave_one_run_out():
    """``hierarchical_transfer`` reports leave-one-run-out's sd beside its own and warns on an axis whose transfer sd
    exceeds MISFIT_RATIO (2) times it and the residual sd. Eight sessions of 100 rows, seed 0: with the y distortion
    the affine model lacks (y gains 0.001 x^2) y is 1.10 against 0.30 uT (warned, y only); without it 0.35 against
    0.33 (no warning)."""
    from bayesmag._src.core.simulate import get_effect

    out = {}
    for name, eff in (("clean", ()), ("distorted", [get_effect("axis_quadratic", out="y", inp="x", coeff=0.001)])):
        d = _session(0, 8, rows=100, noise_sd=0.05, effects=eff)
        fit = bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature))))
        tr, post = H.hierarchical_transfer(d, fit, check="warn")
        loro = np.array([tr.per_run["model"]["loro_sd"][a] for a in "xyz"])
        out[name] = (tr.sd / loro, tr.warning, post)
    ratio, warning, post = out["distorted"]
    assert ratio[1] > H.MISFIT_RATIO and warning is not None and "on y (" in warning and "on x" not in warning
    assert "bayesmag discover" in warning and "transfer = \"loro\"" in warning and post.fallback_sd == ()
    assert out["clean"][1] is None and (out["clean"][0] < H.MISFIT_RATIO).all(), out["clean"]


@pytest.mark.parametrize("check", ["loro", "warn"])
def test_an_axis_that_fails_the_check_against_leave_one_run_out_uses_its_sd(check):
    """``transfer_check = "loro"`` (the default): on the axis the check names (y: the distortion of the test above)
    every row's transfer sd is leave-one-run-out's constant, exactly, the other axes keep the model's row-wise sd,
    and the fallback survives the calibration file's round trip; ``"warn"`` keeps the model's everywhere."""
    from bayesmag._src.core.simulate import get_effect

    d = _session(0, 8, rows=100, noise_sd=0.05,
                 effects=[get_effect("axis_quadratic", out="y", inp="x", coeff=0.001)])
    fit = bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature))))
    tr, post = H.hierarchical_transfer(d, fit, check=check)
    loro = np.array([tr.per_run["model"]["loro_sd"][a] for a in "xyz"])
    model = np.array([tr.per_run["model"]["check"]["model_rms_sd"][a] for a in "xyz"])
    assert tr.per_run["model"]["check"]["failed_axes"] == ["y"] and model[1] > H.MISFIT_RATIO * loro[1]
    sd = post.transfer_sd_for(fit, d)
    bare = dataclasses.replace(post, fallback_sd=()).transfer_sd_for(fit, d)
    np.testing.assert_allclose(sd[:, [0, 2]], bare[:, [0, 2]], rtol=0, atol=0)
    if check == "warn":
        np.testing.assert_allclose(sd, bare, rtol=0, atol=0)
        assert post.checked_axes == () and "failed its check" not in tr.warning
        return
    assert post.checked_axes == ("y",) and np.all(sd[:, 1] == loro[1]) and np.ptp(bare[:, 1]) > 0
    assert tr.sd[1] == loro[1] and "failed its check" in tr.warning and "transfer_check" in tr.warning
    back = H.posterior_from_artifact(json.loads(json.dumps(post.meta())), post.as_arrays(), fit.param_names)
    np.testing.assert_allclose(back.transfer_sd_for(fit, d), sd, rtol=1e-12)
    for bad in ([1.0, 2.0], [None, -1.0, None], [None, "x", None], [None, float("nan"), None]):
        with pytest.raises(ValueError, match="sessions.fallback_sd"):
            H.posterior_from_artifact({**post.meta(), "fallback_sd": bad}, post.as_arrays(), fit.param_names)
