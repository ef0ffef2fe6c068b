"""The learned Student-t dof of the hierarchical session model (``[uq] transfer_df = "learned"``, issue 24):
prior, evidence, recovery, the mixture predictive, the saved form and the config key."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.special
import scipy.stats

from bayesmag._src.pipeline.sessions import hierarchical as H

jax.config.update("jax_enable_x64", True)

R, N, P = 40, 50, 2          # runs, rows per run, parameters (offset, gain): one shape, one compilation


def _stats(seed: int, df: float, tau=0.3, sigma=0.1, rho=0.5) -> H.RunStats:
    """Lag moments of R simulated runs per axis from the model itself: y = mu + u_r + g x_t + e_t, the run's
    offset ``u_r = tau z / sqrt(w_r)`` and AR(1) noise (innovation sd ``sigma / sqrt(w_r)``) sharing one
    precision ``w_r ~ Gamma(df/2, rate df/2)`` (``df`` inf: w = 1, Gaussian)."""
    rng = np.random.default_rng(seed)
    m0, m1, m2, first = (np.zeros((3, R, P + 1, P + 1)) for _ in range(4))
    for a in range(3):
        for r in range(R):
            w = 1.0 if math.isinf(df) else rng.gamma(df / 2, 2 / df)
            x = np.cumsum(rng.normal(0, 0.3, N))
            e = np.zeros(N)
            e[0] = rng.normal(0, sigma / np.sqrt(w * (1 - rho**2)))
            for t in range(1, N):
                e[t] = rho * e[t - 1] + rng.normal(0, sigma / np.sqrt(w))
            y = 1.0 + tau * rng.normal() / np.sqrt(w) + 0.5 * x + e
            z = np.column_stack([np.ones(N), x, y])
            m0[a, r], m1[a, r], m2[a, r] = z[1:].T @ z[1:], z[1:].T @ z[:-1], z[:-1].T @ z[:-1]
            first[a, r] = np.outer(z[0], z[0])
    return H.RunStats(m0, m1, m2, first, np.full(R, float(N)), np.ones((3, P)), np.array([0]), np.arange(R))


NAMES = ("O", "S")


def test_df_prior_is_the_discretised_truncated_gamma():
    """Each grid dof's prior mass is the Gamma(2, rate 0.1) density integrated over its cell (edges at the
    geometric means of neighbours, 2 below, 100 between 50 and the Gaussian limit), truncated to df > 2:
    against scipy.integrate.quad of the density, to 1e-9."""
    g = np.array([2.5, 3, 4, 6, 10, 20, 50])
    edges = [2.0, *np.sqrt(g[1:] * g[:-1]), 100.0, np.inf]
    pdf = scipy.stats.gamma(2.0, scale=10.0).pdf
    mass = np.array([scipy.integrate.quad(pdf, lo, hi)[0] for lo, hi in zip(edges[:-1], edges[1:])])
    np.testing.assert_allclose(H.df_prior_weights(), mass / mass.sum(), rtol=1e-9, atol=1e-12)
    assert H.DF_GRID[-1] == math.inf and H.df_prior_weights()[-1] == pytest.approx(11 * math.exp(-10) / (1.2 * math.exp(-0.2)))


def test_gaussian_limit_of_the_grid_is_the_gaussian_model():
    """The grid's inf dof (a traced dof, :func:`_mix_log_g`) gives the Gaussian collapsed posterior exactly: log
    posterior, mu and its covariance against :func:`_collapsed` (REML) at random hyperparameters, to 1e-9."""
    st = _stats(0, math.inf)
    args = (tuple(jnp.asarray(v[0]) for v in (st.m0, st.m1, st.m2, st.first))
            + (jnp.asarray(st.n), jnp.asarray(st.effects), 0.5, 1.0, 1.0))
    hs = np.random.default_rng(1).normal([-1.2, -2.3, 0.5], 0.3, (H.N_PROPOSALS_LEARNED, 3))   # the fit's shape
    got = H._lp_mu_cov_grid(jnp.asarray(hs), jnp.full(len(hs), jnp.inf), *args)
    for i, h in enumerate(hs[:5]):
        want = H._collapsed(jnp.asarray(h), *args[:-1], reml=1.0)
        for g, w in zip(got, want):
            np.testing.assert_allclose(np.asarray(g[i]), np.asarray(w), rtol=1e-9, atol=1e-12)


def _grid_log_evidence(st, a, n=17, half=8.0):
    """Per grid dof, the log of the integral of exp(collapsed log posterior) over h = (log tau, log sigma,
    atanh rho) by a tensor trapezoid grid of n^3 points (spacing 1 sd: the trapezoid rule is spectrally
    accurate on a smooth, decaying integrand) over +-``half`` sds along the eigenvectors of the Hessian at the
    mode (scipy BFGS to gtol 1e-8 on the compiled gradient; the same compiled shapes as the fit)."""
    import scipy.optimize
    args = (jnp.asarray(st.m0[a]), jnp.asarray(st.m1[a]), jnp.asarray(st.m2[a]), jnp.asarray(st.first[a]),
            jnp.asarray(st.n), jnp.asarray(st.effects), 0.5, 1.0, 1.0)
    grid = np.array(H.DF_GRID)
    K = grid.size
    dfs = jnp.asarray(grid)

    def fg(x):
        v, g, _ = H._neg_lp_grad_grid(jnp.asarray(x.reshape(K, 3)), dfs, *args)
        return float(v), np.asarray(g).ravel()

    x = scipy.optimize.minimize(fg, np.tile([-1.0, -2.0, 0.3], K), jac=True, method="BFGS",
                                options={"gtol": 1e-8, "maxiter": 5000}).x.reshape(K, 3)
    Hs = np.zeros((K, 3, 3))
    for j in range(3):
        e = np.zeros((K, 3))
        e[:, j] = 1e-5
        Hs[:, :, j] = (fg((x + e).ravel())[1] - fg((x - e).ravel())[1]).reshape(K, 3) / 2e-5
    u = np.linspace(-half, half, n)
    U = np.stack(np.meshgrid(u, u, u, indexing="ij"), -1).reshape(-1, 3)
    out = np.zeros(K)
    chunk = H.N_PROPOSALS_LEARNED
    for k in range(K):
        w, V = np.linalg.eigh(0.5 * (Hs[k] + Hs[k].T))
        hs = x[k] + (U / np.sqrt(w)) @ V.T
        pad = np.concatenate([hs, np.repeat(hs[:1], -len(hs) % chunk, axis=0)])
        lp = np.concatenate([np.asarray(H._lp_mu_cov_grid(jnp.asarray(c), jnp.full(chunk, grid[k]), *args)[0])
                             for c in pad.reshape(-1, chunk, 3)])[:len(hs)]
        lp = np.where(np.isfinite(lp), lp, -np.inf).reshape(n, n, n)
        m = lp.max()
        integral = scipy.integrate.trapezoid(scipy.integrate.trapezoid(scipy.integrate.trapezoid(
            np.exp(lp - m), u), u), u)
        out[k] = m + np.log(integral) - 0.5 * np.sum(np.log(w))
    return out


@pytest.mark.extended
def test_each_dofs_evidence_matches_numerical_integration():
    """Each dof's log marginal likelihood (importance sampled, :func:`_fit_learned_df`) against a 17^3-point
    trapezoid integral of the same collapsed posterior over the three hyperparameters (one random effect), on
    40 simulated runs with df 4, x axis: within 0.1 nats for every dof the screen keeps (the importance noise
    of 100-2000 proposals is ~0.05 nats), and the posterior weights of the dofs within 0.03 of the grid's."""
    st = _stats(2, 4.0)
    post = H.fit_laplace(st, NAMES, likelihood="student_t", df="learned", seed=0)
    got = post.df_log_evidence[0]
    grid = np.array(H.DF_GRID)
    kept = np.flatnonzero(np.isfinite(got))
    assert kept.size >= 3
    ref = _grid_log_evidence(st, 0)
    np.testing.assert_allclose(got[kept], ref[kept], atol=0.1)
    assert np.all(ref[kept].max() - ref[np.setdiff1d(np.arange(grid.size), kept)] > 12)   # the screen's drops
    lw = np.log(H.df_prior_weights()) + ref
    np.testing.assert_allclose(post.df_weight[0], np.exp(lw - np.logaddexp.reduce(lw)), atol=0.03)


@pytest.mark.parametrize("df, low, high", [(3.0, 0.5, 1.0), (math.inf, 0.0, 0.2)])
def test_learned_df_recovers_the_tails(df, low, high):
    """40 sessions drawn from the model with df 3 (every session's offset and noise sharing one Gamma(1.5, 1.5)
    precision) vs Gaussian sessions: the posterior mass on df <= 6 is above 0.5 on every axis for the df-3
    data and below 0.2 for the Gaussian data (the issue's declared thresholds)."""
    post = H.fit_laplace(_stats(10, df), NAMES, likelihood="student_t", df="learned", seed=1)
    small = np.array(H.DF_GRID) <= 6
    mass = post.df_weight[:, small].sum(1)
    assert np.all((mass >= low) & (mass <= high) & ((mass > low) | (low == 0))), (mass, post.df_weight)
    assert post.likelihood == "student_t" and post.meta()["df"] == "learned"


def _mixture_post(weights):
    """A learned-dof posterior with one effect: dof 3 and the Gaussian limit, per-dof variance moments."""
    K = len(H.DF_GRID)
    W = np.zeros((3, K))
    W[:, 1], W[:, -1] = weights
    mm = np.zeros((3, K, 2))
    mm[:, :, 0], mm[:, :, 1] = 0.09, 0.01
    mm[:, 1] *= 2.0                                 # the heavy-tailed dof has a larger variance too
    mc = np.zeros((3, K, 2, 2))
    mc[:, :, 0, 0] = 0.002
    base = H.SessionPosterior(w_mean=mm[:, 0], w_cov=mc[:, 0], mu_cov=np.zeros((3, 1, 1)), scale=np.ones((3, 1)),
                              effects=("O",), level=0.95, n_runs=40, method="laplace", mu=np.zeros((3, 1)),
                              effect_index=(0,), df_grid=H.DF_GRID, df_weight=W)
    comps = [H.dataclasses.replace(base, w_mean=mm[:, k], w_cov=mc[:, k], df=float(d), df_grid=(), df_weight=None)
             for k, d in enumerate(H.DF_GRID)]
    return H._pool_components(base, comps)


def test_mixture_predictive_interval_matches_monte_carlo():
    """The learned-dof predictive is the weighted mixture of every dof's row-wise Student-t: its equivalent 95 %
    half-width against 10^6 draws of that mixture (within 0.5 %) and scipy's cdf of the mixture at it (0.975 to
    1e-12, four mixtures x 50 rows); with all weight on one dof it is that dof's fixed-dof predictive exactly."""
    post = _mixture_post((0.3, 0.7))
    J = np.ones((3, 1, 1))
    half = np.sqrt(post.new_session_variance(J))[0, 0] * scipy.stats.norm.ppf(0.975)
    rng = np.random.default_rng(0)
    comps = post.components()
    (nu3, s3), (nug, sg) = (tuple(float(v[0, 0]) for v in comps[k].predictive_t(J)) for k in (1, -1))
    n = 1_000_000
    pick = rng.uniform(size=n) < 0.3
    x = np.where(pick, s3 * rng.standard_t(nu3, n), sg * rng.standard_t(nug, n))
    np.testing.assert_allclose(half, np.quantile(np.abs(x), 0.95), rtol=0.005)
    # and exactly: the mixture's cdf (scipy's t) at the half-width is 0.975, over a range of rows and mixtures
    for wts in ((0.3, 0.7), (0.5, 0.5), (0.9, 0.1), (0.02, 0.98)):
        p = _mixture_post(wts)
        Jr = np.geomspace(0.1, 30.0, 50)[None, :, None] * np.ones((3, 1, 1))
        h = np.sqrt(p.new_session_variance(Jr)) * scipy.stats.norm.ppf(0.975)           # (50, 3)
        cdf = sum(wk * scipy.stats.t.cdf(h / s, nu) for wk, (nu, s) in
                  zip(wts, (p.components()[k].predictive_t(Jr) for k in (1, -1))))
        np.testing.assert_allclose(cdf, 0.975, atol=1e-12)
    one = _mixture_post((1.0, 0.0))
    np.testing.assert_allclose(one.new_session_variance(J), one.components()[1].new_session_variance(J), rtol=1e-12)
    with pytest.raises(ValueError, match="mixture"):
        post.predictive_t(J)


def test_learned_posterior_round_trips_through_the_saved_form():
    """meta() / as_arrays() through JSON and posterior_from_artifact give the same predictive; a damaged weight
    array or grid is refused naming it."""
    post = _mixture_post((0.3, 0.7))
    meta = json.loads(json.dumps(post.meta()))
    arrays = post.as_arrays()
    back = H.posterior_from_artifact(meta, arrays, ("O",))
    J = np.ones((3, 4, 1)) * np.array([0.5, 1, 2, 3])[None, :, None]
    np.testing.assert_allclose(back.new_session_variance(J), post.new_session_variance(J), rtol=1e-12)
    assert back.df_grid == H.DF_GRID and meta["df"] == "learned" and meta["df_grid"][-1] is None
    bad = {**arrays, "df_weight": arrays["df_weight"] * 2}
    with pytest.raises(ValueError, match="sessions/df_weight"):
        H.posterior_from_artifact(meta, bad, ("O",))
    with pytest.raises(ValueError, match="sessions.df_grid"):
        H.posterior_from_artifact({**meta, "df_grid": [1.5] + meta["df_grid"][1:]}, arrays, ("O",))
    with pytest.raises(ValueError, match="sessions/mix_w_mean"):
        H.posterior_from_artifact(meta, {k: v for k, v in arrays.items() if k != "mix_w_mean"}, ("O",))


def test_config_accepts_learned_and_names_bad_values():
    """`[uq] transfer_df = "learned"` is valid; another string, or "learned" with hierarchical_nuts, is refused
    with a message naming the key, the value and what is valid."""
    from bayesmag._src.app.config import ConfigError, config_from_dict
    raw = {"name": "t", "data": {"path": "x.csv"}, "uq": {"transfer": "hierarchical", "transfer_likelihood": "student_t",
                                                   "transfer_df": "learned"}}
    assert config_from_dict(raw).uq.transfer_df == "learned"
    with pytest.raises(ConfigError, match=r"uq.transfer_df' = 'learnt'.*number > 2.*\"learned\""):
        config_from_dict({**raw, "uq": {**raw["uq"], "transfer_df": "learnt"}})
    with pytest.raises(ConfigError, match=r"uq.transfer_df' = \"learned\".*Laplace path"):
        config_from_dict({**raw, "uq": {**raw["uq"], "transfer": "hierarchical_nuts"}})
    with pytest.raises(ValueError, match="Laplace path"):
        H.fit_nuts(_stats(0, math.inf), NAMES, None, likelihood="student_t", df="learned")


def test_uninformed_effects_are_carried_by_every_dof():
    """`with_prior_effects` on a learned-dof posterior adds the effect to every dof's component with that dof's
    prior moments (closed form: E tau^2 = s^2 df/(df-2), Var = 2 E^2; the Gaussian limit s^2), and the mixture's
    interval lies between its components' at every row."""
    import bayesmag
    from test_transfer import _session
    d = _session(0, 3, rows=40)
    fit = bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature))))
    names = list(fit.model.param_names)
    p, o = len(names), names.index("O")
    K = len(H.DF_GRID)
    W = np.zeros((3, K))
    W[:, 1], W[:, 4], W[:, -1] = 0.2, 0.5, 0.3
    mm = np.tile([0.09, 0.01], (3, K, 1))
    mc = np.zeros((3, K, 2, 2))
    base = H.SessionPosterior(w_mean=mm[:, 0], w_cov=mc[:, 0], mu_cov=np.zeros((3, p, p)), scale=np.ones((3, p)),
                              effects=("O",), level=0.95, n_runs=3, method="laplace", mu=np.zeros((3, p)),
                              effect_index=(o,), df_grid=H.DF_GRID, df_weight=W)
    post = H._pool_components(base, [H.dataclasses.replace(base, w_mean=mm[:, k], w_cov=mc[:, k], df=float(g),
                                                           df_grid=(), df_weight=None) for k, g in enumerate(H.DF_GRID)])
    out = H.with_prior_effects(post, fit, d, ["S_x"], tau_scale=0.5)
    assert out.effects == ("O", "S_x") and out.prior_only == ("S_x",) and out.df_grid == H.DF_GRID
    g = np.array(H.DF_GRID)
    want = 0.25 * np.where(np.isfinite(g), g / np.where(np.isfinite(g), g - 2, 1.0), 1.0)
    np.testing.assert_allclose(out.mix_w_mean[0, :, 1], want, rtol=1e-12)
    np.testing.assert_allclose(out.mix_w_cov[0, :, 1, 1], 2 * want**2, rtol=1e-12)
    J = H._jacobian(fit, d)
    var = out.new_session_variance(J)
    comp = np.stack([c.new_session_variance(J) for k, c in enumerate(out.components()) if W[0, k] > 0])
    assert np.all(var >= comp.min(0) * (1 - 1e-9)) and np.all(var <= comp.max(0) * (1 + 1e-9))
