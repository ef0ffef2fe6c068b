"""Metrics against NumPy / scipy.stats references."""

import json

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

import bayesmag  # noqa: F401  (enables float64)
from bayesmag import metrics
from bayesmag.likelihoods import Gaussian, Laplace, StudentT

# calibration_curve on N_CALIB draws: a binomial coverage estimate has sd <= 0.5/sqrt(N) =
# 0.0016, so CALIB_ATOL = 0.01 is > 6 sd; the draws come from a fixed seed.
N_CALIB = 100_000
CALIB_ATOL = 0.01


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.mark.parametrize("shape,axis", [((50,), 0), ((50,), None), ((40, 3), 0), ((40, 3), None),
                                        ((40, 3), 1)])
def test_rmse_mae_match_numpy(rng, shape, axis):
    y, yhat = rng.normal(size=shape), rng.normal(size=shape)
    np.testing.assert_allclose(metrics.rmse(y, yhat, axis=axis), np.sqrt(np.mean((y - yhat) ** 2, axis=axis)),
                               rtol=1e-14)
    np.testing.assert_allclose(metrics.mae(y, yhat, axis=axis), np.mean(np.abs(y - yhat), axis=axis),
                               rtol=1e-14)
    assert np.shape(metrics.rmse(y, yhat)) == shape[1:]
    assert isinstance(metrics.rmse(y[:, 0] if len(shape) == 2 else y, y[:, 0] if len(shape) == 2 else y), float)


def test_coverage_and_width():
    y = np.array([[0.0, 1.0], [2.0, 5.0], [1.0, -1.0], [3.0, 0.0]])
    lo, hi = np.zeros_like(y), np.full_like(y, 2.0)  # inclusive bounds
    np.testing.assert_array_equal(metrics.coverage(y, lo, hi), [0.75, 0.5])
    assert metrics.coverage(y, lo, hi, axis=None) == 0.625
    np.testing.assert_array_equal(metrics.interval_width(lo, hi + y), [2.0 + 1.5, 2.0 + 1.25])
    with pytest.raises(ValueError, match="same shape"):
        metrics.coverage(y, lo[:2], hi)


@pytest.mark.parametrize("dist_cls", [Gaussian, Laplace, StudentT])
def test_nll_crps_pit_are_row_means(rng, dist_cls):
    n = 30
    kw = {"df": jnp.asarray(rng.uniform(3, 10, (n, 3)))} if dist_cls is StudentT else {}
    d = dist_cls(jnp.asarray(rng.normal(size=(n, 3))), jnp.asarray(rng.uniform(0.5, 2, (n, 3))), **kw)
    y = rng.normal(size=(n, 3))
    np.testing.assert_allclose(metrics.nll(d, y), np.mean(d.nll(jnp.asarray(y)), axis=0), rtol=1e-14)
    np.testing.assert_allclose(metrics.crps(d, y), np.mean(d.crps(jnp.asarray(y)), axis=0), rtol=1e-14)
    np.testing.assert_allclose(metrics.pit(d, y), d.cdf(jnp.asarray(y)), rtol=1e-14)
    assert metrics.nll(d, y).shape == (3,) and isinstance(metrics.crps(d, y, axis=None), float)


def test_float32_distribution_accepts_float64_observations(rng):
    d = Gaussian(jnp.zeros((10, 3), jnp.float32), jnp.ones((10, 3), jnp.float32))
    y = rng.normal(size=(10, 3))  # float64 NumPy
    ref = -scipy.stats.norm.logpdf(y).mean(0)
    np.testing.assert_allclose(metrics.nll(d, y), ref, rtol=1e-5)


def test_dist_checks(rng):
    d = Gaussian(jnp.zeros(5), 1.0)
    with pytest.raises(ValueError, match="batch shape"):
        metrics.nll(d, np.zeros(4))
    with pytest.raises(TypeError, match="must be a Likelihood"):
        metrics.crps(scipy.stats.norm(), np.zeros(5))


def test_calibration_curve_of_calibrated_gaussian(rng):
    loc, scale = rng.normal(size=(N_CALIB, 3)), np.exp(rng.uniform(-1, 1, (N_CALIB, 3)))
    y = loc + scale * rng.standard_normal((N_CALIB, 3))
    d = Gaussian(jnp.asarray(loc), jnp.asarray(scale))
    nominal, observed = metrics.calibration_curve(d, y)
    assert len(nominal) >= 10 and nominal[-1] == 0.99 and observed.shape == (len(nominal), 3)
    np.testing.assert_allclose(nominal, metrics.DEFAULT_LEVELS)
    np.testing.assert_allclose(observed, np.broadcast_to(nominal[:, None], observed.shape), atol=CALIB_ATOL)
    _, pooled = metrics.calibration_curve(d, y, levels=[0.5, 0.9], axis=None)
    assert pooled.shape == (2,)
    np.testing.assert_allclose(pooled, [0.5, 0.9], atol=CALIB_ATOL)
    # The PIT shortcut equals counting hits of the explicit central interval.
    lo, hi = d.interval(0.9)
    np.testing.assert_allclose(pooled[1], metrics.coverage(y, lo, hi, axis=None), atol=1e-12)
    # A forecast twice too narrow covers far less than nominal.
    _, narrow = metrics.calibration_curve(Gaussian(jnp.asarray(loc), jnp.asarray(scale / 2)), y,
                                          levels=[0.9], axis=None)
    np.testing.assert_allclose(narrow, 2 * scipy.stats.norm.cdf(scipy.stats.norm.ppf(0.95) / 2) - 1,
                               atol=CALIB_ATOL)
    with pytest.raises(ValueError, match=r"in \(0, 1\)"):
        metrics.calibration_curve(d, y, levels=[0.5, 1.0])


@pytest.mark.parametrize("n,shift", [(50, 0.0), (2000, 0.1), (500, -0.3)])
def test_paired_test_matches_scipy(rng, n, shift):
    err_b = rng.normal(size=n)
    err_a = err_b * 1.1 + rng.normal(0.0, 0.3, n) + shift
    out = metrics.paired_test(err_a, err_b)
    rel = scipy.stats.ttest_rel(err_a ** 2, err_b ** 2, alternative="greater")
    d = err_a ** 2 - err_b ** 2
    one = scipy.stats.ttest_1samp(d, 0.0)
    np.testing.assert_allclose(out["t"], rel.statistic, rtol=1e-10)
    np.testing.assert_allclose(out["p"], rel.pvalue, rtol=1e-8, atol=1e-300)
    np.testing.assert_allclose(out["p_two_sided"], one.pvalue, rtol=1e-8, atol=1e-300)
    ci = one.confidence_interval(0.95)
    np.testing.assert_allclose(out["ci95"], [ci.low, ci.high], rtol=1e-10)
    np.testing.assert_allclose(out["mean_diff"], d.mean(), rtol=1e-12)
    np.testing.assert_allclose(out["cohens_d"], d.mean() / d.std(ddof=1), rtol=1e-12)
    assert out["n"] == n
    json.dumps(out)  # plain Python numbers


def test_paired_test_per_column_and_checks(rng):
    a, b = rng.normal(size=(100, 3)), rng.normal(size=(100, 3))
    out = metrics.paired_test(a, b)
    assert out["t"].shape == (3,) and out["ci95"].shape == (2, 3)
    for j in range(3):
        col = metrics.paired_test(a[:, j], b[:, j])
        np.testing.assert_allclose(out["t"][j], col["t"], rtol=1e-14)
        np.testing.assert_allclose(out["ci95"][:, j], col["ci95"], rtol=1e-14)
    with pytest.raises(ValueError, match="at least 2 pairs"):
        metrics.paired_test(a[:1], b[:1])
    with pytest.raises(ValueError, match="same shape"):
        metrics.paired_test(a, b[:50])


def test_summarize(rng):
    n = 200
    d = StudentT(jnp.asarray(rng.normal(size=(n, 3))), jnp.ones((n, 3)), 5.0)
    y = rng.normal(size=(n, 3))
    out = metrics.summarize(y, d, level=0.9)
    assert list(out) == ["x", "y", "z"]
    assert set(out["x"]) == {"rmse", "mae", "coverage", "width", "nll", "crps"}
    json.dumps(out)
    lo, hi = d.interval(0.9)
    np.testing.assert_allclose([out[a]["rmse"] for a in "xyz"], metrics.rmse(y, d.mean))
    np.testing.assert_allclose([out[a]["coverage"] for a in "xyz"], metrics.coverage(y, lo, hi))
    np.testing.assert_allclose([out[a]["width"] for a in "xyz"], 2 * scipy.stats.t.ppf(0.95, 5.0), rtol=1e-10)
    np.testing.assert_allclose([out[a]["crps"] for a in "xyz"], metrics.crps(d, y))
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        metrics.summarize(y[:, :2], d)
