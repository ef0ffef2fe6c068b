r"""Physics-stage uncertainty: nested parameter sampling x quasi-Monte-Carlo (PS-QMC).

Shetty & Marndi (2026), section 2.3. For input ``x`` (B_meas, T), ``Np`` parameter draws
:math:`\theta_i \sim N(\hat\theta, \Sigma_\theta)` and ``Nq`` scrambled-Sobol input-noise
points :math:`\epsilon_j = \Sigma_{in}^{1/2}\Phi^{-1}(u_j)`, with
:math:`y_{ij} = f(x + \epsilon_j, \theta_i)`:

* mean :math:`\bar y = \frac{1}{N_pN_q}\sum_{ij} y_{ij}`;
* aleatoric :math:`\sigma^2_{alea} = \frac1{N_p}\sum_i \frac1{N_q-1}\sum_j (y_{ij}-\hat\mu_i)^2`;
* epistemic :math:`\sigma_{epi} = \sqrt{(\sigma^2_{MC} + \sigma^2_{Jac})/2}` with
  :math:`\sigma^2_{MC} = \mathrm{var}_i(\hat\mu_i)` (ddof 1) and
  :math:`\sigma^2_{Jac} = J_\theta\Sigma_\theta J_\theta^T` at :math:`\hat\theta` and nominal ``x``.

Exact fast path: when the model is linear in its parameters, :math:`y_{ij} = \phi(x+\epsilon_j)^T\theta_i`,
so with :math:`m = \mathrm{mean}_j\,\phi`, :math:`C = \mathrm{cov}_j\,\phi` (ddof 1) and
:math:`M_2 = \mathrm{mean}_i\,\theta_i\theta_i^T`,
:math:`\hat\mu_i = m^T\theta_i` and :math:`\sigma^2_{alea} = \langle C, M_2\rangle` -- the
same nested estimator with the same draws, computed with matrix products instead of
``Np x Nq`` model evaluations per row.

``method="analytic"`` replaces both sample averages by exact expectations, for models
polynomial in the inputs: input moments by a tensor Gauss-Hermite rule with ``degree+1``
nodes per input (exact for polynomials of degree ``2*degree+1``), parameter moments in
closed form (:math:`E[\theta\theta^T] = \hat\theta\hat\theta^T + \Sigma_\theta`).
With ``d`` the largest power of any single input in the features (``PhysicsModel.degree``),
the variance integrand has per-input degree ``2d``, and ``d + 1`` nodes per input integrate it
exactly when the input noise is independent (Gauss-Hermite with ``k`` nodes is exact to
degree ``2k - 1`` in each variable): 16 nodes for the thermo-affine model; correlated noise
mixes the inputs, and ``2d + 1`` nodes are used.

Rows are processed in chunks (``chunk_size``) so memory stays bounded for any test set.
"""

from __future__ import annotations

import dataclasses
import itertools
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.special
from scipy.stats import qmc

from bayesmag._src.core.physics import Inputs, PhysicsModel, centred

__all__ = ["PhysicsUQ", "physics_uncertainty", "sobol_normal", "gauss_hermite_normal", "estimate_input_noise"]


class PhysicsUQ(NamedTuple):
    """Per-row physics prediction and its uncertainty parts, each (n, 3) in uT."""

    mean: np.ndarray
    aleatoric: np.ndarray
    epistemic: np.ndarray
    epistemic_mc: np.ndarray
    epistemic_jac: np.ndarray

    @property
    def total(self) -> np.ndarray:
        return np.sqrt(self.aleatoric**2 + self.epistemic**2)

    def rows(self, idx) -> "PhysicsUQ":
        """Rows ``idx`` of every part (of a result computed on a whole series)."""
        return PhysicsUQ(*(np.asarray(a)[idx] for a in self))


def sobol_normal(n: int, cov: np.ndarray, *, seed: int) -> np.ndarray:
    """(n, d) scrambled-Sobol points mapped to N(0, cov) by the inverse normal CDF.

    Uses ``scipy.stats.qmc.Sobol`` (Owen scrambling, seeded) and a Cholesky (or, if
    singular, eigen) square root of ``cov``.
    """
    cov = np.atleast_2d(np.asarray(cov, dtype=np.float64))
    d = cov.shape[0]
    eng = qmc.Sobol(d=d, scramble=True, seed=np.random.default_rng(seed))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)   # n not a power of 2: balance is lost, still valid
        u = eng.random(n)
    z = scipy.special.ndtri(np.clip(u, 1e-16, 1 - 1e-16))
    return z @ _sqrt_psd(cov).T


def gauss_hermite_normal(n_nodes: int, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tensor Gauss-Hermite nodes (n_nodes**d, d) and weights for N(0, cov)."""
    cov = np.atleast_2d(np.asarray(cov, dtype=np.float64))
    d = cov.shape[0]
    x, w = np.polynomial.hermite_e.hermegauss(n_nodes)
    w = w / w.sum()
    nodes = np.array(list(itertools.product(x, repeat=d)))
    weights = np.prod(np.array(list(itertools.product(w, repeat=d))), axis=1)
    return nodes @ _sqrt_psd(cov).T, weights


def _sqrt_psd(cov: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(cov)
        return V * np.sqrt(np.clip(w, 0, None))


def estimate_input_noise(data) -> np.ndarray:
    """``Sigma_in`` (4x4, diagonal) from the sensor's own noise in a recording.

    For each input channel (B_meas x, y, z and T), the white-noise standard deviation is
    estimated from within-run second differences as ``1.4826 * MAD(d2) / sqrt(6)``
    (``Var(x[t+1] - 2x[t] + x[t-1]) = 6 s^2`` for white noise): second differences remove
    held levels, ramps and slow rotations, and the median absolute deviation ignores the
    few large values at field steps. Right when the noise is white and the signal is
    piecewise smooth; biased for strongly coloured noise (then give ``sigma_in``). Only rows adjacent in the
    recording are differenced (``data.time``): the training rows of a random split skip the test rows.
    """
    from bayesmag._src.core.data import second_difference_sd
    sd = second_difference_sd(np.column_stack([data.b_meas, data.temperature]), data.run, time=data.time)
    return np.diag((np.full(4, np.nan) if sd is None else sd) ** 2)


def _perturbed(inputs: Inputs, eps: jax.Array) -> Inputs:
    """Inputs broadcast against noise ``eps`` (q, 4): leading shape (n, q)."""
    b = inputs.b[:, None, :] + eps[None, :, :3]
    t = inputs.t[:, None] + eps[None, :, 3]
    return Inputs(b, t, jnp.broadcast_to(inputs.time[:, None], t.shape), jnp.broadcast_to(inputs.run[:, None], t.shape))


def _slice_inputs(inputs: Inputs, lo: int, hi: int) -> Inputs:
    """Rows ``lo:hi``, sliced on the host (an eager slice of a JAX array compiles a program per chunk shape)."""
    return Inputs(*(jax.device_put(np.asarray(a)[lo:hi]) for a in inputs))


@dataclasses.dataclass(frozen=True)
class _Linear:
    model: PhysicsModel

    def chunk(self, inputs, eps, w, theta_draws, theta_hat, cov_theta, exact_theta, hist=None):
        """One row-chunk, one axis. eps (q, 4), w (q,) quadrature weights or None (sample mean); ``hist``: the
        chunk's rows of the history terms' columns (:meth:`PhysicsModel.history_columns`), or None."""
        phi = self.model.features(_perturbed(inputs, eps), hist)     # (n, q, p)
        q = eps.shape[0]
        if w is None:
            m = phi.mean(axis=1)
            dphi = phi - m[:, None, :]
            C = jnp.einsum("nqa,nqb->nab", dphi, dphi) / (q - 1)
        else:
            m = jnp.einsum("q,nqa->na", w, phi)
            dphi = phi - m[:, None, :]
            C = jnp.einsum("nqa,nqb->nab", dphi * w[None, :, None], dphi)   # batched matmul, no (n,q,p,p)
        phi0 = self.model.features(inputs, hist)                      # (n, p) nominal
        var_jac = jnp.einsum("na,ab,nb->n", phi0, cov_theta, phi0)
        if exact_theta:
            mean = m @ theta_hat
            M2 = jnp.outer(theta_hat, theta_hat) + cov_theta
            var_mc = jnp.einsum("na,ab,nb->n", m, cov_theta, m)
        else:
            mu = m @ theta_draws.T                                    # (n, Np)
            mean = mu.mean(axis=1)
            M2 = theta_draws.T @ theta_draws / theta_draws.shape[0]
            var_mc = jnp.var(mu, axis=1, ddof=1)
        alea = jnp.einsum("nab,ab->n", C, M2)
        return mean, alea, var_mc, var_jac


@dataclasses.dataclass(frozen=True)
class _General:
    model: PhysicsModel

    def chunk(self, inputs_full, lo, size, eps, theta_draws, theta_hat, cov_theta):
        """Brute-force nested evaluation for models nonlinear in their parameters (rows lo:lo+size)."""
        def cut(a):
            return jax.lax.dynamic_slice_in_dim(a, lo, size, axis=0)

        def per_draw(th):
            tr = self.model.transform(th, inputs_full)
            hist = self.model.history_columns(tr) if self.model.has_history else None
            hist = None if hist is None else tuple(None if h is None else cut(h) for h in hist)
            tr = Inputs(*(cut(a) for a in tr))
            y = self.model.pointwise(th, _perturbed(tr, eps), hist)   # (n, q)
            return y.mean(axis=1), jnp.var(y, axis=1, ddof=1)

        mu, var = jax.lax.map(per_draw, theta_draws)                   # (Np, n)
        J = cut(jax.jacfwd(self.model.predict)(theta_hat, inputs_full))
        var_jac = jnp.einsum("na,ab,nb->n", J, cov_theta, J)
        return mu.mean(axis=0), var.mean(axis=0), jnp.var(mu, axis=0, ddof=1), var_jac


_lin_jit = jax.jit(lambda k, *a: k.chunk(*a), static_argnums=(0, 7))
_gen_jit = jax.jit(lambda k, inp, lo, size, *a: k.chunk(inp, lo, size, *a), static_argnums=(0, 3))


def history_columns(model: PhysicsModel, inputs: Inputs) -> tuple | None:
    """The history terms' columns (:meth:`PhysicsModel.history_columns`) on the whole series ``inputs``, as NumPy
    arrays, for :func:`physics_uncertainty`'s ``history`` when the rows are predicted in pieces; None if the model
    has none (or input transforms, whose series restart with each piece)."""
    if not (model.is_linear and model.has_history):
        return None
    model, inputs = centred(model, inputs)
    return tuple(None if h is None else np.asarray(h) for h in model.history_columns(inputs))


#: The one default propagation method wherever bayesmag predicts (config ``[uq] method``, :class:`Predictor`,
#: ``Calibration.predict``, ``bayesmag apply``, :class:`~bayesmag.Calibrator`): ``"auto"`` = ``"analytic"`` (exact
#: moments) for a model linear in its parameters and polynomial in the inputs, else ``"psqmc"``.
DEFAULT_METHOD = "auto"
#: Every method name :func:`physics_uncertainty` accepts.
METHODS = ("auto", "psqmc", "mc", "analytic")


def resolve_method(method: str, model) -> str:
    """The method ``"auto"`` stands for with ``model`` (:data:`DEFAULT_METHOD`); any other name unchanged."""
    if method == "auto":
        return "analytic" if model.degree is not None and model.is_linear else "psqmc"
    return method


def physics_uncertainty(fit, inputs: Inputs, *, sigma_in: np.ndarray, method: str = DEFAULT_METHOD,
                        n_params: int = 500, n_qmc: int = 1000, seed: int = 0, chunk_size: int = 256,
                        progress: bool = False, quad_nodes: int | None = None,
                        history: tuple | None = None) -> PhysicsUQ:
    """Physics prediction and uncertainty for rows ``inputs`` (module docstring).

    Args:
      fit: a :class:`~bayesmag.PhysicsFit` (parameters (3, p) and covariances (3, p, p)).
      inputs: rows to predict.
      sigma_in: (4, 4) covariance of the input noise on (Bx, By, Bz, T) (uT^2, C^2).
      method: ``"psqmc"`` (the paper's nested sampler; Sobol inner loop), ``"mc"`` (plain
        Monte-Carlo inner loop, for comparison), ``"analytic"`` (exact moments) or ``"auto"`` (the
        default: analytic where it is exact, else psqmc; :func:`resolve_method`).
      n_params, n_qmc: Np and Nq. seed: seeds the parameter draws and the Sobol scrambling.
      chunk_size: rows per compiled chunk (bounds memory at chunk x Nq x p floats).
      quad_nodes: Gauss-Hermite nodes per input for ``"analytic"`` (default ``degree + 1``, exact).
      history: the history terms' columns for these rows, computed on a longer series they were cut from
        (:func:`history_columns`; default: computed on ``inputs``, whose first row then starts the history).
    """
    if method not in METHODS:
        raise ValueError(f"uq method {method!r} is not known; it must be one of {list(METHODS)}.")
    model = fit.model
    method = resolve_method(method, model)
    sigma_in = np.asarray(sigma_in, dtype=np.float64)
    if sigma_in.shape != (4, 4):
        raise ValueError(f"sigma_in must be a 4x4 covariance of (Bx, By, Bz, T); got shape {sigma_in.shape}.")
    n = int(inputs.b.shape[0])
    key = jax.random.PRNGKey(seed)
    w = None
    if method == "analytic":
        if model.degree is None or not model.is_linear:
            raise ValueError("uq method 'analytic' needs a model linear in its parameters and polynomial in the "
                             "inputs; use 'psqmc' for this model.")
        diagonal = np.allclose(sigma_in, np.diag(np.diag(sigma_in)))
        # Independent noise: d + 1 nodes per input are exact. Correlated noise mixes the standard
        # normals, so a monomial in two inputs can reach degree 2d in one of them: 2d + 1 nodes.
        nodes = quad_nodes or (model.degree + 1 if diagonal else 2 * model.degree + 1)
        eps, w = gauss_hermite_normal(nodes, sigma_in)
        w = jnp.asarray(w)
    elif method == "psqmc":
        eps = sobol_normal(n_qmc, sigma_in, seed=seed)
    else:
        eps = np.random.default_rng(seed).standard_normal((n_qmc, 4)) @ _sqrt_psd(sigma_in).T
    eps = jax.device_put(np.asarray(eps))          # device_put: jnp.asarray compiles a program per shape
    draws = []
    for a in range(3):
        key, sub = jax.random.split(key)
        draws.append(jax.random.multivariate_normal(sub, jax.device_put(np.asarray(fit.theta[a])),
                                                    jax.device_put(np.asarray(fit.cov[a])),
                                                    shape=(max(n_params, 2),), method="svd"))
    out = np.zeros((4, n, 3))
    model, inputs = centred(model, inputs)          # one program for every T0 (after resolve_method: same degree)
    # a term whose features depend on earlier rows (hysteresis) exists only on the whole series: its columns are
    # taken from the unperturbed series and cut per chunk (the input noise is not propagated through them)
    hist = history_columns(model, inputs) if history is None else history     # None without history terms
    hist = hist if model.is_linear else None
    chunks = range(0, n, chunk_size)
    if progress:
        from tqdm.auto import tqdm
        chunks = tqdm(chunks, desc="physics UQ", unit="chunk", leave=False)
    for lo in chunks:
        hi = min(n, lo + chunk_size)
        for a in range(3):
            th_hat, cov_th = jnp.asarray(fit.theta[a]), jnp.asarray(fit.cov[a])
            if model.is_linear:
                res = _lin_jit(_Linear(model), _slice_inputs(inputs, lo, hi), eps, w, draws[a], th_hat, cov_th,
                               method == "analytic",
                               None if hist is None else tuple(None if h is None else jax.device_put(h[lo:hi])
                                                               for h in hist))
                out[:, lo:hi, a] = np.stack([np.asarray(r) for r in res])
            else:
                size = min(chunk_size, n)
                start = min(lo, n - size)          # fixed-size chunks: one compilation
                res = _gen_jit(_General(model), inputs, start, size, eps, draws[a], th_hat, cov_th)
                out[:, start:start + size, a] = np.stack([np.asarray(r) for r in res])
    mean, alea, var_mc, var_jac = out
    return PhysicsUQ(mean=mean, aleatoric=np.sqrt(np.clip(alea, 0, None)),
                     epistemic=np.sqrt(np.clip((var_mc + var_jac) / 2, 0, None)),
                     epistemic_mc=np.sqrt(np.clip(var_mc, 0, None)), epistemic_jac=np.sqrt(np.clip(var_jac, 0, None)))
