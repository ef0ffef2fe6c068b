"""The hierarchical session model (pipeline/sessions): closed forms, recovery, Laplace vs NUTS, the job option."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

import bayesmag
from bayesmag._src.pipeline.sessions import hierarchical as H
from test_transfer import _session

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
            assert U[a] == pytest.approx(k * np.sqrt(uc2), rel=0.03)  # the table rounds to 2 significant digits


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
    pr = Predictor(fit=fit, sigma_in=sin, residual_sd=resid, domain=Domain.from_data(train),
                   uq=UQOptions(method="analytic"), sessions=H.fit_sessions(train, fit))
    p = pr.predict(test)
    lo, hi = p.interval(0.95)
    ok = ((test.b_ref >= lo) & (test.b_ref <= hi)) | ~p.in_domain[:, None]
    assert np.all(ok.mean(0) >= 0.95), ok.mean(0)
