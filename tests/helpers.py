"""Shared test data: a thermo-affine sensor with known parameters (close to the paper's Table 2)."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

import bayesmag
from bayesmag import CalibrationData, PhysicsModel, PhysicsUQ, inputs_from_data
from bayesmag._src.core import likelihoods as _likelihoods_src
from bayesmag._src.core.network import MCPrediction
from bayesmag.likelihoods import Likelihood, sample_by_inversion

TRUE_THETA = np.array([[1.02, -0.16, -0.21, 0.003, 0.004, 0.008, -1.2, 0.036],
                       [-0.16, 2.37, 0.04, 0.0027, -0.05, -0.0028, -0.07, -0.0009],
                       [-0.086, 0.096, 1.21, 0.0046, -0.0011, -0.004, 4.32, -0.16]])


def affine_data(n: int, seed: int, noise: float):
    """(data, design matrix): fields uniform +-50 uT, T uniform 0-40 C, reference = model + Gaussian noise."""
    r = np.random.default_rng(seed)
    b = r.uniform(-50, 50, (n, 3))
    t = r.uniform(0, 40, n)
    X = np.asarray(PhysicsModel.paper().features(inputs_from_data(CalibrationData(b, t, None))))
    y = X @ TRUE_THETA.T + noise * r.standard_normal((n, 3))
    return CalibrationData(b, t, y, time=np.arange(n) * 0.25), X


def uq_parts(seed=0, n=50):
    """Random physics UQ and MC-network outputs for ``n`` rows (fusion and predictor tests)."""
    rng = np.random.default_rng(seed)
    phys = PhysicsUQ(mean=rng.normal(size=(n, 3)), aleatoric=rng.uniform(0.01, 0.02, (n, 3)),
                     epistemic=rng.uniform(0.001, 0.003, (n, 3)), epistemic_mc=np.zeros((n, 3)),
                     epistemic_jac=np.zeros((n, 3)))
    nn = MCPrediction(mean=rng.normal(0, 0.02, (n, 3)), aleatoric=rng.uniform(0.01, 0.03, (n, 3)),
                      epistemic=rng.uniform(0.001, 0.005, (n, 3)), shape={"df": rng.uniform(3, 9, (n, 3))})
    return phys, nn


# A fourth family, defined in the tests and nowhere else, registered by its decorator. It is the worked
# example of docs/extending.md; test_likelihoods checks it against scipy and runs it through the
# network, fusion, NUTS and apply; test_extending registers it under a test-only name.
@bayesmag.register_likelihood
@dataclasses.dataclass(frozen=True)
class Logistic(Likelihood):
    r"""Logistic(loc, scale); CRPS = s (z - 2 log F(z) - 1) (Jordan et al. 2019, crps_logis)."""

    name = "logistic"

    def _z(self, y):
        return (jnp.asarray(y) - self.loc) / self.scale

    def log_prob(self, y):
        z = self._z(y)
        return -z - 2.0 * jax.nn.softplus(-z) - jnp.log(self.scale)

    def cdf(self, y):
        return jax.nn.sigmoid(self._z(y))

    def icdf(self, q):
        return self.loc + self.scale * (jnp.log(q) - jnp.log1p(-q))

    def crps(self, y):
        z = self._z(y)
        return self.scale * (z + 2.0 * jax.nn.softplus(-z) - 1.0)  # -log F(z) = softplus(-z)

    def sample(self, key, sample_shape=()):
        return sample_by_inversion(self, key, sample_shape)

    @property
    def mean(self):
        return jnp.broadcast_to(self.loc, self.batch_shape)

    @property
    def variance(self):
        return jnp.broadcast_to(jnp.square(self.scale) * math.pi ** 2 / 3.0, self.batch_shape)

    @classmethod
    def from_moments(cls, mean, variance):
        return cls(loc=mean, scale=jnp.sqrt(3.0 * jnp.asarray(variance)) / math.pi)

    def to_numpyro(self):                          # for NUTS
        import numpyro.distributions as nd
        return nd.Logistic(self.loc, self.scale)


# Defining the class registered it; a test module that uses it registers it only while its tests run,
# so "logistic" does not leak into every other module's valid-name lists.
_likelihoods_src._REGISTRY.pop("logistic", None)


#: A small physics job on a CSV (``{data}``: its path): analytic UQ, no figures, no progress (the safety tests).
SMALL_JOB_CONFIG = """name = "t"
[data]
path = "{data}"
[split]
kind = "random"
test_fraction = 0.2
[uq]
method = "analytic"
n_params = 10
n_qmc = 16
[output]
figures = false
progress = false
"""


def tau_grid_log_marginal(lp, start, lt, u):
    """Log marginal posterior (unnormalised, NaN where the Newton step failed) of a between-session sd on the grid
    ``log tau = lt``, by numerical integration: the collapsed log posterior ``lp(h)``, ``h = (log tau, log sigma,
    atanh rho)``, integrated over its other two coordinates at every grid point on a tensor grid ``u x u`` (in sds)
    around their conditional mode (12 Newton steps from ``start``), scaled by the Laplace covariance there. The
    independent reference of the session model's Laplace / importance-sampling path (tests/test_hierarchical*.py,
    benchmarks/bench_hierarchical.py belsten_tau)."""
    u = np.asarray(u, np.float64)
    grid = jnp.asarray(np.stack(np.meshgrid(u, u, indexing="ij"), -1).reshape(-1, 2))

    @jax.jit
    def log_marginal(t):
        f = lambda sr: lp(jnp.r_[t, sr])  # noqa: E731
        x = jax.lax.fori_loop(0, 12, lambda _, x: x - jnp.linalg.solve(jax.hessian(f)(x), jax.grad(f)(x)),
                              jnp.asarray(start))
        L = jnp.linalg.cholesky(jnp.linalg.inv(-jax.hessian(f)(x)))
        vals = jax.vmap(f)(x + grid @ L.T)
        return jax.scipy.special.logsumexp(jnp.where(jnp.isfinite(vals), vals, -jnp.inf)) + jnp.log(jnp.linalg.det(L))

    return np.asarray(jax.lax.map(log_marginal, jnp.asarray(lt)))


def tau_grid_posterior(lp, start, lt, u):
    """``(weights, tau)`` on the grid ``log tau = lt`` (:func:`tau_grid_log_marginal`, non-finite points left out)."""
    logm = tau_grid_log_marginal(lp, start, lt, u)
    logm = np.where(np.isfinite(logm), logm, -np.inf)
    w = np.exp(logm - logm.max())
    return w / w.sum(), np.exp(lt)
