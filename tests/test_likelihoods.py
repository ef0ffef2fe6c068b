"""Likelihood families against scipy.stats, numerical CRPS integrals and published values."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.stats

import bayesmag  # noqa: F401  (enables float64)
from bayesmag import metrics
from bayesmag.likelihoods import LIKELIHOODS, Gaussian, Laplace, StudentT, get_likelihood, moment_match
from helpers import Logistic

FAMILIES = ["gaussian", "laplace", "student_t"]
SHAPES = [(), (4, 3)]
DTYPES = [jnp.float64, jnp.float32]
SHAPES_DTYPES = [((), jnp.float64), ((4, 3), jnp.float64), ((4, 3), jnp.float32)]
# Agreement with scipy per dtype: float64 is near round-off (t CDF/quantile go through jax's
# betainc and a Newton solve, ~1e-12); float32 is limited by its 6e-8 resolution.
RTOL = {jnp.float64: 1e-9, jnp.float32: 2e-5}
ATOL = {jnp.float64: 1e-12, jnp.float32: 2e-6}
# quad of the CRPS integral is run to ~1e-13; the closed forms then agree to float64 round-off.
CRPS_INTEGRAL_RTOL = 1e-8
# sample(): each moment must lie within N_SIGMA estimated standard errors of the exact value.
# With a fixed key the test is deterministic; for a fresh key the two-sided false-failure rate
# per check is ~6e-7 (normal approximation of the sample mean / sample variance).
N_SIGMA = 5.0
N_DRAWS = 200_000


def _params(family, shape, dtype, seed=0, df_range=(1.5, 30.0)):
    rng = np.random.default_rng(seed)
    p = {"loc": rng.normal(0.0, 2.0, shape), "scale": np.exp(rng.uniform(-1.0, 1.0, shape))}
    if family == "student_t":
        p["df"] = rng.uniform(*df_range, shape)
    return {k: jnp.asarray(v, dtype) for k, v in p.items()}


def _scipy(dist):
    loc, scale = np.asarray(dist.loc, np.float64), np.asarray(dist.scale, np.float64)
    if isinstance(dist, Gaussian):
        return scipy.stats.norm(loc, scale)
    if isinstance(dist, Laplace):
        return scipy.stats.laplace(loc, scale)
    if isinstance(dist, StudentT):
        return scipy.stats.t(np.asarray(dist.df, np.float64), loc, scale)
    if isinstance(dist, Logistic):
        return scipy.stats.logistic(loc, scale)
    raise TypeError(type(dist))


def _maybe_jit(fn, jit):
    return jax.jit(fn) if jit else fn


def _crps_integral(sdist, y):
    """CRPS = int_{-inf}^y F^2 dz + int_y^inf (1 - F)^2 dz, by adaptive quadrature."""
    kw = dict(epsabs=1e-14, epsrel=1e-13, limit=500)
    lo = scipy.integrate.quad(lambda z: sdist.cdf(z) ** 2, -np.inf, y, **kw)[0]
    hi = scipy.integrate.quad(lambda z: sdist.sf(z) ** 2, y, np.inf, **kw)[0]
    return lo + hi


# The fourth family (tests/helpers.py): the worked example of docs/extending.md.
# Registered only while this module's tests run (helpers unregisters it at import).
from bayesmag._src.core import likelihoods as _likelihoods_src  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _logistic_registered():
    _likelihoods_src._REGISTRY["logistic"] = Logistic
    yield
    _likelihoods_src._REGISTRY.pop("logistic", None)

# -- densities, CDFs, quantiles ------------------------------------------------------------------

QS = np.array([1e-6, 0.025, 0.3, 0.5, 0.8, 0.975, 1.0 - 1e-5])


@pytest.mark.parametrize("jit", [False, True])
@pytest.mark.parametrize("shape,dtype", SHAPES_DTYPES)
@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.extended
def test_nll_cdf_icdf_match_scipy(family, shape, dtype, jit):
    dist = get_likelihood(family)(**_params(family, shape, dtype))
    sdist = _scipy(dist)
    y = jnp.asarray(sdist.rvs(random_state=np.random.default_rng(1)) * 1.5, dtype)
    qs = QS.reshape((-1,) + (1,) * len(shape))
    q = jnp.asarray(np.broadcast_to(qs, qs.shape[:1] + shape), dtype)

    def evaluate(d, y, q):
        return d.nll(y), d.cdf(y), d.pit(y), jax.tree.map(lambda p: p[None], d).icdf(q)

    nll, cdf, pit, x = _maybe_jit(evaluate, jit)(dist, y, q)
    assert nll.dtype == cdf.dtype == x.dtype == dtype and nll.shape == shape and x.shape == q.shape
    y64 = np.asarray(y, np.float64)
    np.testing.assert_allclose(nll, -sdist.logpdf(y64), rtol=RTOL[dtype], atol=10 * ATOL[dtype])
    np.testing.assert_allclose(cdf, sdist.cdf(y64), rtol=RTOL[dtype], atol=ATOL[dtype])
    np.testing.assert_array_equal(pit, cdf)
    ref = sdist.ppf(np.asarray(q, np.float64))
    # float32 tails: the rounding of q, times dx/dq = 1/f(x), is a larger relative error.
    rtol = RTOL[dtype] * np.where((qs < 1e-3) | (qs > 1 - 1e-3), 5.0, 1.0)
    assert np.all(np.abs(np.asarray(x, np.float64) - ref) <= rtol * np.abs(ref) + 10 * ATOL[dtype])


@pytest.mark.parametrize("family", FAMILIES)
def test_icdf_edges(family):
    dist = get_likelihood(family)(**_params(family, (), jnp.float64))
    x = jax.jit(lambda d, q: d.icdf(q))(dist, jnp.array([0.0, 0.5, 1.0, -0.1, 1.1]))
    assert np.isneginf(x[0]) and np.isposinf(x[2]) and np.all(np.isnan(x[3:]))
    np.testing.assert_allclose(x[1], dist.loc)


def test_student_t_quantile_wide_grid():
    """The Newton quantile over tails and df far beyond what the tests above use."""
    df = np.array([0.7, 1.0, 1.5, 2.0, 2.01, 3.0, 4.5, 7.0, 30.0, 100.0, 1e3, 1e4])
    q = np.concatenate([np.logspace(-50, -1, 40), np.linspace(0.1, 0.4999, 20),
                        1.0 - np.logspace(-15, -1, 15)])
    Q, DF = np.meshgrid(q, df)
    x = StudentT(0.0, 1.0, jnp.asarray(DF)).icdf(jnp.asarray(Q))
    np.testing.assert_allclose(x, scipy.stats.t.ppf(Q, DF), rtol=1e-9)
    # float32, where q itself is rounded: compare at the rounded q.
    Q32 = Q.astype(np.float32)
    x32 = StudentT(0.0, 1.0, jnp.asarray(DF, jnp.float32)).icdf(jnp.asarray(Q32))
    ref32 = scipy.stats.t.ppf(Q32.astype(np.float64), DF)
    # Documented range: |x| < sqrt(finfo.max) (1.8e19 in float32); float32 betainc also loses
    # digits for df >~ 1e3.
    # XLA flushes float32 subnormals to zero, so q < finfo.tiny reads as q = 0.
    keep = (np.abs(ref32) < 1e18) & (DF <= 100) & (Q32 >= np.finfo(np.float32).tiny)
    np.testing.assert_allclose(np.asarray(x32)[keep], ref32[keep], rtol=2e-4)


@pytest.mark.parametrize("family", FAMILIES)
def test_interval_has_exact_coverage(family):
    levels = jnp.array([0.5, 0.9, 0.95, 0.99])[:, None]
    dist = jax.tree.map(lambda p: p[None], get_likelihood(family)(**_params(family, (5,), jnp.float64)))
    def evaluate(d):
        lo, hi = d.interval(levels)
        return lo, hi, d.cdf(hi) - d.cdf(lo)

    lo, hi, covered = jax.jit(evaluate)(dist)
    assert lo.shape == (4, 5) and np.all(lo < dist.loc) and np.all(hi > dist.loc)
    np.testing.assert_allclose(covered, np.broadcast_to(levels, (4, 5)), rtol=1e-10)


# -- CRPS ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("jit", [False, True])
@pytest.mark.parametrize("family", FAMILIES + ["logistic"])
def test_crps_nonnegative_on_draws(family, jit):
    dist = get_likelihood(family)(**_params(family if family != "logistic" else "gaussian", (4, 3),
                                            jnp.float64))
    y = _scipy(dist).rvs(size=(40, 4, 3), random_state=np.random.default_rng(3))
    y = np.concatenate([y, np.asarray(dist.loc + 1e3 * dist.scale)[None]])  # and far in the tail
    crps = _maybe_jit(lambda d, y: d.crps(y), jit)(jax.tree.map(lambda p: p[None], dist), jnp.asarray(y))
    assert crps.shape == (41, 4, 3) and np.all(np.isfinite(crps)) and np.all(crps >= 0)


CRPS_CASES = [  # (loc, scale, df, y)
    (0.0, 1.0, 3.0, 0.5), (0.0, 1.0, 1.5, -3.0), (1.3, 0.4, 5.0, 1.1), (-2.0, 2.5, 30.0, 4.0),
    (0.5, 0.1, 2.2, 0.5), (0.0, 1.0, 1.05, 10.0),
]


@pytest.mark.parametrize("case", CRPS_CASES)
@pytest.mark.parametrize("family", FAMILIES + ["logistic"])
def test_crps_matches_integral(family, case):
    loc, scale, df, y = case
    kw = {"df": df} if family == "student_t" else {}
    dist = get_likelihood(family)(loc=jnp.asarray(loc), scale=jnp.asarray(scale), **kw)
    np.testing.assert_allclose(dist.crps(y), _crps_integral(_scipy(dist), y), rtol=CRPS_INTEGRAL_RTOL)


def test_crps_published_values():
    # Laplace(0, 1) at y = -3: 3 + exp(-3) - 3/4 (Jordan et al. 2019, crps_lapl).
    np.testing.assert_allclose(Laplace(0.0, 1.0).crps(-3.0), 2.29978707, atol=1e-7)
    # N(0, 1) at y = 0: 2 phi(0) - 1/sqrt(pi) (Gneiting & Raftery 2007, eq. 21).
    np.testing.assert_allclose(Gaussian(0.0, 1.0).crps(0.0), 0.2336949, atol=1e-7)
    np.testing.assert_allclose(Gaussian(0.0, 1.0).crps(0.0),
                               2 * scipy.stats.norm.pdf(0.0) - 1 / math.sqrt(math.pi), rtol=1e-14)
    # t_3 at y = 0.5: value of the quad integral (quad error estimate < 1e-14).
    t3 = StudentT(0.0, 1.0, 3.0)
    np.testing.assert_allclose(t3.crps(0.5), 0.3651206352219, atol=1e-12)
    np.testing.assert_allclose(t3.crps(0.5), _crps_integral(scipy.stats.t(3.0), 0.5), rtol=1e-12)


def test_student_t_tends_to_gaussian():
    y = jnp.linspace(-4, 4, 12).reshape(4, 3)
    crps_t, crps_g = jax.jit(lambda y: (StudentT(0.3, 1.2, 1e7).crps(y), Gaussian(0.3, 1.2).crps(y)))(y)
    np.testing.assert_allclose(crps_t, crps_g, rtol=1e-6)


def test_student_t_undefined_moments():
    d = StudentT(jnp.zeros(3), jnp.ones(3), jnp.array([0.9, 1.5, 2.0]))
    np.testing.assert_array_equal(d.variance, [np.inf] * 3)
    assert np.isnan(d.mean[0]) and np.all(d.mean[1:] == 0)
    c = d.crps(jnp.full(3, 0.3))
    assert np.isposinf(c[0]) and np.all(np.isfinite(c[1:]))


# -- gradients -----------------------------------------------------------------------------------

def test_student_t_gradients():
    raw = jnp.array([[0.2, -0.5, 0.3], [1.0, 20.0, -3.0]])  # second row is clipped

    def grads(nu, q, raw):
        return (jax.grad(lambda nu: StudentT(0.0, 1.0, nu).cdf(1.7))(nu),
                *jax.grad(lambda q, nu: StudentT(0.0, 1.0, nu).icdf(q), argnums=(0, 1))(q, nu),
                jax.grad(lambda r: StudentT.from_head(r).crps(jnp.array([0.0, 1.0])).sum())(raw))

    g_cdf, gq, gd, g_crps = jax.jit(grads)(3.0, 0.9, raw)
    h = 1e-5
    # dF/d(df) is a custom JVP (central difference): compare with scipy's CDF differenced.
    ref = (scipy.stats.t.cdf(1.7, 3.0 + h) - scipy.stats.t.cdf(1.7, 3.0 - h)) / (2 * h)
    np.testing.assert_allclose(g_cdf, ref, rtol=1e-6)
    # Quantile: dx/dq = 1/f(x) and dx/d(df) by implicit differentiation.
    np.testing.assert_allclose(gq, 1 / scipy.stats.t.pdf(scipy.stats.t.ppf(0.9, 3.0), 3.0), rtol=1e-10)
    ref = (scipy.stats.t.ppf(0.9, 3.0 + h) - scipy.stats.t.ppf(0.9, 3.0 - h)) / (2 * h)
    np.testing.assert_allclose(gd, ref, rtol=1e-6)
    # CRPS is differentiable in every head output, including learned df; zero past the clip.
    assert np.all(np.isfinite(g_crps)) and g_crps[1, 1] == 0.0 and np.all(g_crps[0] != 0.0)


# -- sampling, moments ---------------------------------------------------------------------------

@pytest.mark.parametrize("family", FAMILIES + ["logistic"])
def test_sample_moments(family):
    # df in [8, 30]: the sample variance needs a finite 4th moment to have a standard error.
    params = _params(family if family != "logistic" else "gaussian", (2,), jnp.float64,
                     df_range=(8.0, 30.0))
    dist = get_likelihood(family)(**params)
    x = np.asarray(jax.jit(lambda d, k: d.sample(k, (N_DRAWS,)))(dist, jax.random.key(0)))
    assert x.shape == (N_DRAWS, 2)
    m, v = x.mean(0), x.var(0, ddof=1)
    se_mean = np.sqrt(v / N_DRAWS)
    se_var = np.sqrt((np.mean((x - m) ** 4, 0) - v ** 2) / N_DRAWS)
    assert np.all(np.abs(m - dist.mean) < N_SIGMA * se_mean)
    assert np.all(np.abs(v - dist.variance) < N_SIGMA * se_var)
    np.testing.assert_allclose(dist.std, np.sqrt(dist.variance))


@pytest.mark.parametrize("dtype", DTYPES)
def test_sample_shape_and_dtype(dtype):
    dist = Laplace(**_params("laplace", (4, 3), dtype))
    x = dist.sample(jax.random.key(1), (2, 5))
    assert x.shape == (2, 5, 4, 3) and x.dtype == dtype and np.all(np.isfinite(x))
    assert Laplace(0.0, jnp.ones(2, dtype)).sample(jax.random.key(2)).shape == (2,)


@pytest.mark.parametrize("family", FAMILIES + ["logistic"])
def test_moment_match_round_trips(family):
    mean, var = jnp.array([0.5, -2.0, 10.0]), jnp.array([0.01, 1.0, 40.0])
    kw = {"df": jnp.array([2.5, 5.0, 50.0])} if family == "student_t" else {}
    for target in (family, get_likelihood(family)):
        d = moment_match(target, mean, var, **kw)
        assert type(d) is get_likelihood(family)
        np.testing.assert_allclose(d.mean, mean, rtol=1e-14)
        np.testing.assert_allclose(d.variance, var, rtol=1e-13)
    # An instance supplies its shape fields (df) itself.
    template = moment_match(family, mean, var, **kw)
    d = moment_match(template, mean + 1.0, 2.0 * var)
    np.testing.assert_allclose(d.variance, 2.0 * var, rtol=1e-13)


def test_moment_match_scales():
    np.testing.assert_allclose(moment_match(Laplace, 0.0, 8.0).scale, 2.0)
    np.testing.assert_allclose(moment_match(StudentT, 0.0, 3.0, df=6.0).scale, math.sqrt(2.0))
    with pytest.raises(ValueError, match="df > 2"):
        moment_match(StudentT, 0.0, 1.0, df=2.0)


# -- network head --------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("family", FAMILIES)
def test_from_head_convention(family, dtype):
    cls = get_likelihood(family)
    k = cls.n_head_params()
    assert k == (3 if family == "student_t" else 2)
    raw = jnp.asarray(np.random.default_rng(0).normal(0, 4, (6, 3, k)), dtype)
    d = jax.jit(lambda r: cls.from_head(r, log_scale_clip=(-4.0, 2.0)))(raw)
    log_s2 = np.clip(np.asarray(raw[..., 1], np.float64), -4.0, 2.0)
    np.testing.assert_allclose(d.loc, raw[..., 0])
    np.testing.assert_allclose(d.scale, np.exp(0.5 * log_s2), rtol=RTOL[dtype])
    np.testing.assert_allclose(cls.head_log_scale2(raw, log_scale_clip=(-4.0, 2.0)), log_s2,
                               rtol=RTOL[dtype])
    assert d.batch_shape == (6, 3) and d.scale.dtype == dtype
    if family == "student_t":
        np.testing.assert_allclose(d.df, 2.0 + np.logaddexp(0.0, np.asarray(raw[..., 2], np.float64)),
                                   rtol=RTOL[dtype])
        assert np.all(np.isfinite(d.variance))
        fixed = cls.from_head(raw[..., :2], df=5.0)
        assert cls.n_head_params(df=5.0) == 2 and fixed.df.dtype == dtype
        np.testing.assert_allclose(fixed.df, 5.0)
    else:
        assert cls.from_head(raw, df=None).batch_shape == (6, 3)  # None = "not fixed": ignored
        with pytest.raises(TypeError, match="has no parameter 'df'"):
            cls.from_head(raw, df=5.0)
    with pytest.raises(ValueError, match=rf"\(\.\.\., {k}\)"):
        cls.from_head(raw[..., :1])


def test_default_clip_is_log_variance_for_gaussian():
    raw = jnp.array([[0.0, -20.0], [0.0, 1.0], [0.0, 9.0]])
    np.testing.assert_allclose(Gaussian.from_head(raw).variance, np.exp([-10.0, 1.0, 3.0]), rtol=1e-14)
    np.testing.assert_allclose(Laplace.from_head(raw).scale ** 2, np.exp([-10.0, 1.0, 3.0]), rtol=1e-14)
    with pytest.raises(ValueError, match="lo < hi"):
        Gaussian.from_head(raw, log_scale_clip=(3.0, -10.0))


@pytest.mark.parametrize("family", FAMILIES)
def test_float32_under_strict_promotion(family):
    """Inside, nothing relies on implicit dtype or rank promotion."""
    cls = get_likelihood(family)
    raw = jnp.ones((5, 3, cls.n_head_params()), jnp.float32)
    y = jnp.zeros((5, 3), jnp.float32)
    def evaluate(raw, y, key):
        d = cls.from_head(raw)
        return [d.nll(y), d.crps(y), d.cdf(y), *d.interval(0.9), d.mean, d.variance,
                d.sample(key, (2,))]

    with jax.numpy_dtype_promotion("strict"), jax.numpy_rank_promotion("raise"):
        outs = jax.jit(evaluate)(raw, y, jax.random.key(0))
    assert all(o.dtype == jnp.float32 for o in outs)
    assert all(np.all(np.isfinite(o)) for o in outs)


# -- interface, registry, pytrees ----------------------------------------------------------------

def test_registry_and_bad_name():
    assert {"gaussian", "laplace", "student_t"} <= set(LIKELIHOODS)
    assert get_likelihood("student_t") is StudentT and get_likelihood(Laplace) is Laplace
    with pytest.raises(ValueError, match=r"likelihood 'nope' is not known; it must be one of \["):
        get_likelihood("nope")
    with pytest.raises(ValueError) as err:
        get_likelihood("nope")
    assert str(sorted(LIKELIHOODS)) in str(err.value)


def test_fourth_family_works_everywhere():
    assert get_likelihood("logistic") is Logistic and "logistic" in LIKELIHOODS
    assert Logistic.n_head_params() == 2
    d = Logistic.from_head(jnp.array([[0.3, 0.2], [-1.0, -1.5], [2.0, 0.0]]))
    y = jnp.array([0.0, -1.2, 5.0])
    sdist = _scipy(d)
    np.testing.assert_allclose(d.nll(y), -sdist.logpdf(y), rtol=1e-12)
    np.testing.assert_allclose(d.icdf(jnp.array([0.1, 0.5, 0.99])), sdist.ppf([0.1, 0.5, 0.99]), rtol=1e-12)
    np.testing.assert_allclose(d.variance, sdist.var(), rtol=1e-12)
    np.testing.assert_allclose(metrics.nll(d, y), np.mean(-sdist.logpdf(y)), rtol=1e-12)
    ref = np.mean([_crps_integral(scipy.stats.logistic(l, s), yi)
                   for l, s, yi in zip(np.asarray(d.loc), np.asarray(d.scale), np.asarray(y))])
    np.testing.assert_allclose(metrics.crps(d, y), ref, rtol=CRPS_INTEGRAL_RTOL)
    assert jax.jit(lambda d: d.interval(0.9))(d)[0].shape == (3,)


def test_pytree_jit_vmap():
    d = StudentT(**_params("student_t", (4, 3), jnp.float64))
    leaves, treedef = jax.tree.flatten(d)
    assert len(leaves) == 3 and jax.tree.unflatten(treedef, leaves).df is d.df
    y = jnp.ones((4, 3))
    per_row, direct = jax.jit(lambda d, y: (jax.vmap(lambda d, y: d.crps(y))(d, y), d.crps(y)))(d, y)
    np.testing.assert_allclose(per_row, direct, rtol=1e-14)
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(d)[0]]
    assert paths == [".loc", ".scale", ".df"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        d.loc = 0.0


def test_subclass_must_be_a_dataclass():
    class NotDecorated(Gaussian):
        pass

    with pytest.raises(TypeError, match="must be decorated"):
        NotDecorated(0.0, 1.0)


# --------------------------------------------------------------------------- adding a family (docs/extending.md)

#: Logistic checks against scipy: float64 round-off of the closed forms.
LOGISTIC_RTOL = 1e-10


def test_a_registered_family_is_known_everywhere():
    logistic = Logistic
    """One class: the registry, the network head, moment matching, numpyro -- against scipy."""
    from bayesmag._src.app.config import _choices
    from bayesmag._src.core.network import NetworkSpec
    assert get_likelihood("logistic") is logistic and "logistic" in _choices("nuts.likelihood")
    loc, scale = np.array([0.3, -1.0]), np.array([0.5, 2.0])
    d = logistic(jnp.asarray(loc), jnp.asarray(scale))
    y = np.array([0.1, 3.0])
    ref = scipy.stats.logistic(loc, scale)
    np.testing.assert_allclose(d.log_prob(y), ref.logpdf(y), rtol=LOGISTIC_RTOL)
    np.testing.assert_allclose(d.cdf(y), ref.cdf(y), rtol=LOGISTIC_RTOL)
    np.testing.assert_allclose(d.icdf(np.array([0.05, 0.9])), ref.ppf([0.05, 0.9]), rtol=LOGISTIC_RTOL)
    np.testing.assert_allclose(d.variance, ref.var(), rtol=LOGISTIC_RTOL)
    for i in range(2):
        F = scipy.stats.logistic(loc[i], scale[i]).cdf
        num = (scipy.integrate.quad(lambda z: F(z) ** 2, -np.inf, y[i], epsabs=1e-13)[0]
               + scipy.integrate.quad(lambda z: (1 - F(z)) ** 2, y[i], np.inf, epsabs=1e-13)[0])
        np.testing.assert_allclose(float(d.crps(y)[i]), num, rtol=CRPS_INTEGRAL_RTOL)
    m = moment_match("logistic", 1.0, 4.0)
    np.testing.assert_allclose([float(m.mean), float(m.variance)], [1.0, 4.0], rtol=1e-12)
    np.testing.assert_allclose(d.to_numpyro().log_prob(jnp.asarray(y)), ref.logpdf(y), rtol=LOGISTIC_RTOL)
    spec = NetworkSpec(likelihood="logistic")
    assert spec.n_out == 2 and spec.fixed_shape == {}


def _toy_config(nuts: bool):
    from bayesmag._src.app.config import config_from_dict
    return config_from_dict({
        "name": "toy_family",
        "data": {"source": "simulated", "simulate": {"design": "iid", "n": 1200, "seed": 0, "noise_sd": 0.05}},
        "split": {"kind": "random", "test_fraction": 0.2, "seed": 0},
        "uq": {"n_params": 16, "n_qmc": 16, "method": "analytic"},
        "network": {"enabled": True, "likelihoods": ["logistic"], "hidden_layers": 1, "width": 8,
                    "batch_size": 64, "max_epochs": 5, "mc_passes": 4},
        "nuts": {"enabled": nuts, "likelihood": "logistic", "chains": 2, "warmup": 60, "draws": 60},
        "output": {"figures": False, "progress": False},
    })


@pytest.mark.extended
def test_a_registered_family_runs_the_network_fusion_and_apply(tmp_path):
    """The toy family end to end with no edit outside its class: hybrid network training, fusion,
    the saved calibration and ``apply``, whose intervals are the family's (moment-matched)."""
    import csv

    import bayesmag as bm
    from bayesmag._src.app.apply import apply_calibration
    res = bm.run_job(_toy_config(nuts=False), tmp_path / "run")
    m = res["metrics"]
    assert set(m["hybrid"]) == {"logistic"} and np.isfinite(m["hybrid"]["logistic"]["nll"]["x"])
    test = res["data"].subset(res["split"].test)
    bm.write_csv(test, tmp_path / "test.csv")
    apply_calibration(tmp_path / "run", tmp_path / "test.csv", tmp_path / "out.csv", level=0.9)
    with open(tmp_path / "out.csv") as f:
        rows = list(csv.DictReader(f))
    for row in rows[:20]:
        pred, sd = float(row["x_calibrated"]), float(row["x_total"])
        want = scipy.stats.logistic(pred, sd * math.sqrt(3) / math.pi).interval(0.9)
        np.testing.assert_allclose([float(row["x_lower"]), float(row["x_upper"])], want, atol=1e-5)   # CSV: 8 digits


@pytest.mark.slow
def test_a_registered_family_runs_in_nuts(tmp_path):
    """The toy family as NUTS's observation model in a job (its numpyro distribution): sampled, cross-checked
    and LOO-scored."""
    import warnings

    import bayesmag as bm
    from bayesmag._src.pipeline.nuts import NutsWarning
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NutsWarning)
        res = bm.run_job(_toy_config(nuts=True), tmp_path / "run")
    m = res["metrics"]["nuts"]
    assert m["settings"]["likelihood"] == "logistic"
    assert np.isfinite(m["axes"]["x"]["elpd_loo"]) and m["axes"]["x"]["max_rhat"] < 1.2


def test_a_family_whose_icdf_forgets_the_scale_is_refused_at_registration():
    """Sixth outside pass: a family whose icdf ignored ``scale`` registered, and a job ran with 7.3 uT intervals
    on every axis and 100 % coverage, no word. Registration now checks cdf(icdf(q)) = q and the moments."""
    from bayesmag._src.core.likelihoods import register

    @dataclasses.dataclass(frozen=True)
    class NoScale(Gaussian):
        name = "no_scale_test"

        def icdf(self, q):
            return self.loc + jax.scipy.special.ndtri(q)          # the scale forgotten

    with pytest.raises(ValueError, match=r"NoScale .* fails \['cdf\(icdf\(q\)\) = q at q = 0.05, 0.5, 0.95'\]"):
        register(NoScale)
    assert "no_scale_test" not in LIKELIHOODS


def test_a_family_missing_a_method_is_refused_at_registration_naming_it():
    """It registered and failed only inside run_job ("Can't instantiate abstract class")."""
    from bayesmag._src.core.likelihoods import Likelihood, register

    @dataclasses.dataclass(frozen=True)
    class Partial(Likelihood):
        name = "partial_test"

        def log_prob(self, y):
            return -0.5 * (y - self.loc) ** 2

    with pytest.raises(TypeError, match=r"Partial \('partial_test'\) does not implement \['cdf', 'crps'"):
        register(Partial)
