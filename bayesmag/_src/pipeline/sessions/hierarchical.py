r"""Between-session (per-run) random effects: a hierarchical Gaussian model with AR(1) noise within runs.

Model, per output axis, run :math:`r` and row :math:`t` of that run (rows in time order):

.. math::
    y_{rt} = J_{rt}^\top(\mu + E\,u_r) + \varepsilon_{rt}, \qquad u_r \sim N(0, \mathrm{diag}(\tau^2)),\\
    \varepsilon_{rt} = \rho\,\varepsilon_{r,t-1} + \eta_{rt}, \quad \eta \sim N(0, \sigma^2), \quad
    \varepsilon_{r1} \sim N(0, \sigma^2 / (1-\rho^2)),

with :math:`J` the physics model's Jacobian at the LM estimate (its design matrix for the paper's
affine model, so exact there), each column scaled to unit RMS over the training rows (so the
effect of a parameter is in uT at a typical input), and :math:`E` the columns of the parameters
that move between sessions (:data:`DEFAULT_EFFECTS`: offset, thermal offset slope and the three gain /
cross-axis terms of the axis, of which :func:`select_effects` keeps those that at least three runs
inform on their own). Priors: :math:`\tau_j \sim \mathrm{HalfNormal}(s_\tau)`, :math:`s_\tau` =
:data:`TAU_PRIOR_SCALE` = 0.5 uT (a session-to-session change of an RMS-input effect below 1 uT
with 95 % prior probability: weakly informative for fluxgate / AMR sensors whose session shifts
are tenths of a uT); :math:`\sigma \sim \mathrm{HalfNormal}(`:data:`SIGMA_PRIOR_SCALE`:math:`)`;
:math:`\rho \sim U(-1, 1)`; :math:`\mu` flat (Laplace path: integrated out exactly, i.e. REML) or
:math:`N(\hat\theta_{LM}, (10\,\mathrm{uT})^2)` in scaled units (NUTS).

Everything the likelihood needs is four :math:`(p+1)\times(p+1)` lag-moment matrices per run
(:func:`run_stats`): the AR(1) Prais-Winsten whitened Gram matrix of :math:`[J, y]` is
:math:`M_0 - \rho (M_1 + M_1^\top) + \rho^2 M_2 + (1-\rho^2) F`, so a fit costs the same for
3 000 or 300 000 rows. The random effects and :math:`\mu` are integrated out in closed form
(Woodbury), which leaves :math:`q + 2` hyperparameters per axis.

Two posteriors of the hyperparameters :math:`h = (\log\tau, \log\sigma, \operatorname{atanh}\rho)`:

* :func:`fit_laplace` -- the mode of the collapsed posterior (BFGS on JAX gradients) and the inverse
  Hessian there, sampled (default path, well under a second);
* :func:`fit_nuts` -- NumPyro NUTS on the *non-centred* model with explicit per-run effects
  :math:`u_r = \tau \odot z_r`, :math:`z_r \sim N(0, I)`, initialised at the LM fit.

Either gives a :class:`SessionPosterior`: the new-session predictive at a row with scaled Jacobian
:math:`f` is the scale mixture :math:`N(\bar y, v)`, :math:`v = \sum_j \tau_j^2 f_{E,j}^2 + f^\top C f +
\sigma^2/(1-\rho^2)` over the posterior of :math:`(\tau, \sigma, \rho)` (:math:`C`: posterior covariance
of :math:`\mu`). Few runs leave :math:`\tau` uncertain and the mixture heavy-tailed; it is matched, row
by row, to a Student-t by the first two moments of :math:`v` (a scaled inverse chi-square mixing law
has :math:`\mathrm{Var}\,v / (\mathrm E v)^2 = 2/(\nu - 4)`), and :meth:`SessionPosterior.transfer_sd`
returns the Gaussian sd with the same central ``level`` interval, less the within-session noise.

The Student-t dof can be learned (``df = "learned"``, :func:`_fit_learned_df`): a discrete posterior over
:data:`DF_GRID` from a discretised Gamma(2, 0.1) prior and each dof's importance-sampled marginal likelihood; the
predictive is then the mixture over the dofs (:func:`_mixture_variance`).
"""

from __future__ import annotations

import contextvars
import dataclasses
import functools
import math
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
import scipy.special
import scipy.stats

from bayesmag._src.core.physics import AXES, inputs_from_data

__all__ = ["DEFAULT_EFFECTS", "TAU_PRIOR_SCALE", "SIGMA_PRIOR_SCALE", "RunStats", "SessionPosterior", "run_stats",
           "fit_laplace", "fit_nuts", "fit_sessions", "select_effects", "weak_directions", "hierarchical_transfer", "condition_table", "run_loglik", "loro_elpd", "whitened_gram"]

#: Parameters with per-session random effects (the others are shared by all sessions).
DEFAULT_EFFECTS = ("O", "Ko", "S_x", "S_y", "S_z")
#: Half-normal prior scale of every random-effect sd, uT of effect at an RMS input.
TAU_PRIOR_SCALE = 0.5
#: Half-normal prior scale of the AR(1) innovation sd, uT.
SIGMA_PRIOR_SCALE = 1.0
#: Posterior draws of the hyperparameters kept for the predictive moments (as many as the importance proposals:
#: resampling fewer added seed-to-seed noise to the new-session sd).
N_DRAWS = 2048


class RunStats(NamedTuple):
    """Per-run, per-axis lag moments of ``z = [J / scale, y]`` (rows in time order): arrays (3, R, p+1, p+1)."""

    m0: np.ndarray      # sum_{t>=2} z_t z_t^T
    m1: np.ndarray      # sum_{t>=2} z_t z_{t-1}^T
    m2: np.ndarray      # sum_{t>=2} z_{t-1} z_{t-1}^T
    first: np.ndarray   # z_1 z_1^T
    n: np.ndarray       # (R,) rows per run
    scale: np.ndarray   # (3, p) column RMS of J
    effects: np.ndarray  # (q,) indices of the parameters with random effects
    runs: np.ndarray    # (R,) run ids
    nuisance: int = 0   # trailing columns of J (before y): within-run deviations with their own coefficient

    @property
    def n_params(self) -> int:
        """The model's parameters: the columns of ``J`` less the nuisance ones (whose margin a posterior drops)."""
        return self.scale.shape[1] - self.nuisance

    def select(self, keep: np.ndarray) -> "RunStats":
        """The stats of the runs ``keep`` (bool (R,) or indices)."""
        k = np.asarray(keep)
        return self._replace(m0=self.m0[:, k], m1=self.m1[:, k], m2=self.m2[:, k], first=self.first[:, k],
                             n=self.n[k], runs=self.runs[k])


#: ``(rows, recording, index)`` while :func:`hierarchical_transfer` runs with a ``series``: the training rows
#: ``rows`` (that object) are ``recording``'s rows ``index``, and a model whose rows depend on their neighbours (a
#: thermal lag) is evaluated on them within the recording (:func:`_jacobian`, :func:`_predict`).
_SERIES: contextvars.ContextVar = contextvars.ContextVar("bayesmag_session_series", default=None)


def _in_series(fit, data):
    """``(recording, index)`` when ``data`` is the training rows of a :data:`_SERIES` and the model needs it."""
    ctx = _SERIES.get()
    if ctx is not None and ctx[0] is data and fit.model.needs_series:
        return ctx[1], ctx[2]
    return None


def _jacobian(fit, data) -> np.ndarray:
    """(3, n, p) Jacobian of the physics prediction at the fit's parameters (the design matrix if linear)."""
    from bayesmag._src.core.fit import physics_jacobian
    series = _in_series(fit, data)
    if series is not None:
        return physics_jacobian(fit.model, fit.theta, inputs_from_data(series[0]))[:, series[1]]
    return physics_jacobian(fit.model, fit.theta, inputs_from_data(data))


def _predict(fit, data) -> np.ndarray:
    """(n, 3) physics prediction of ``data``'s rows (within the recording under :data:`_SERIES`)."""
    series = _in_series(fit, data)
    if series is not None:
        return np.asarray(fit.predict(inputs_from_data(series[0])))[series[1]]
    return np.asarray(fit.predict(inputs_from_data(data)))


def run_stats(data, fit, effects: Sequence[str] = DEFAULT_EFFECTS, scale: np.ndarray | None = None,
              within: dict | None = None, shared: np.ndarray | None = None,
              directions: dict | None = None) -> RunStats:
    """Lag-moment matrices of every run of ``data`` (with a reference) for :class:`~bayesmag.PhysicsFit` ``fit``.

    ``y`` is linearised at the fit: ``y - f(theta) + J theta`` (equal to ``y`` for a linear model).
    ``scale``: column scales to reuse (default: the RMS of each Jacobian column over ``data``).
    ``within``: ``{parameter: runs}``; each such run's within-run deviation of that parameter's Jacobian column
    from its run mean, less its least-squares part along the columns that run informs (per axis), becomes a
    column of its own (a nuisance coefficient, flat like ``mu``, appended after ``J``), so that variation does
    not inform the shared parameter (:func:`uninformed_within`). ``select`` does not drop such columns: a
    selection without their run leaves them zero (singular), so select before adding them.
    ``directions``: ``{run: W}``, ``W`` (p, k): each of the run's ``k`` directions ``J W`` (its within-run deviation
    from the run mean) becomes a nuisance column of its own, like ``within``'s (:func:`weak_directions`).
    ``shared``: (3, n, k) further columns (rows of ``data``) with one flat coefficient each, shared by every run
    and not a random effect, appended after those (e.g. a distortion the physics model lacks, learned elsewhere:
    :func:`fit_sessions`); like them, their margin is dropped from the posterior.
    """
    names = list(fit.model.param_names)
    missing = [e for e in effects if e not in names]
    if missing:
        raise ValueError(f"random effects {missing} are not parameters of the model {names}.")
    J = _jacobian(fit, data)                                               # (3, n, p)
    pred = _predict(fit, data)
    y = np.asarray(data.b_ref) - pred + np.einsum("anp,ap->na", J, np.asarray(fit.theta))
    extra = []
    rms = np.sqrt(np.mean(J**2, axis=1))                                   # (3, p)
    for e, rs in (within or {}).items():
        for r in rs:
            m = np.asarray(data.run) == r
            dev = J[:, m] - J[:, m].mean(axis=1, keepdims=True)              # (3, n_r, p)
            c = np.zeros(J.shape[:2])
            for a in range(3):
                # less its least-squares part along the columns the run does inform (a swept field's cross-talk
                # into this reading is that sweep's signal, which stays with the shared parameters)
                inf = dev[a].std(axis=0) > INFORM_FRACTION * rms[a]
                D = dev[a][:, inf]
                x = dev[a, :, names.index(e)]
                c[a, m] = x - D @ np.linalg.lstsq(D, x, rcond=None)[0] if D.shape[1] else x
            if np.abs(c).max() > 1e-9 * np.abs(J[:, :, names.index(e)]).max():     # nothing left: no column
                extra.append(c)
    for r, W in (directions or {}).items():
        m = np.asarray(data.run) == r
        cols = np.zeros(J.shape[:2] + (W.shape[1],))
        cols[:, m] = (J[:, m] - J[:, m].mean(axis=1, keepdims=True)) @ W
        extra += list(np.moveaxis(cols, 2, 0))
    p = J.shape[2]
    if shared is not None:
        shared = np.asarray(shared, np.float64)
        if shared.ndim != 3 or shared.shape[:2] != J.shape[:2]:
            raise ValueError(f"shared columns must have shape (3, {J.shape[1]}, k); got {shared.shape}.")
        extra += [shared[:, :, k] for k in range(shared.shape[2])]
    if extra:
        J = np.concatenate([J, np.stack(extra, axis=2)], axis=2)
    rms = np.sqrt(np.mean(J**2, axis=1))
    scale = np.where(rms > 0, rms, 1.0) if scale is None else np.concatenate([scale, rms[:, p:]], axis=1)
    z = np.concatenate([J / scale[:, None, :], y.T[:, :, None]], axis=2)   # (3, n, p+1)
    order = np.lexsort((data.time, data.run))
    z, run = z[:, order], np.asarray(data.run)[order]
    runs, first_idx = np.unique(run, return_index=True)
    onehot = (run[None, :] == runs[:, None]).astype(np.float64)            # (R, n)
    same = np.r_[False, run[1:] == run[:-1]]                               # row t has a predecessor in its run
    zp = np.concatenate([np.zeros_like(z[:, :1]), z[:, :-1]], axis=1)
    w = onehot * same[None, :]
    m0 = np.einsum("rn,ani,anj->arij", w, z, z)
    m1 = np.einsum("rn,ani,anj->arij", w, z, zp)
    m2 = np.einsum("rn,ani,anj->arij", w, zp, zp)
    zf = z[:, first_idx]
    first = np.einsum("ari,arj->arij", zf, zf)
    return RunStats(m0, m1, m2, first, onehot.sum(1), scale, np.array([names.index(e) for e in effects], int), runs,
                    len(extra))


def whitened_gram(m0, m1, m2, first, rho):
    """AR(1)-whitened Gram matrix of ``[J, y]`` of one run: ``M0 - rho (M1 + M1^T) + rho^2 M2 + (1-rho^2) F``."""
    return m0 - rho * (m1 + jnp.swapaxes(m1, -1, -2)) + rho**2 * m2 + (1 - rho**2) * first


def run_loglik(G, n, mu, L, sigma2, rho, df=None):
    r"""Log density of one run's rows, the random effect :math:`u = L z`, :math:`z \sim N(0, I)` integrated out.

    ``G``: whitened Gram (p+1, p+1) of ``[J, y]``; ``mu``: (p,) centre; ``L``: (p, k) factor of the
    random-effect covariance (k = 0: none). Woodbury with :math:`P = I + L^\top G_{XX} L / \sigma^2`.
    ``df`` None: Gaussian; a number: the multivariate Student-t with that shape matrix and ``df`` dof
    (:func:`_collapsed_t`); ``"laplace"``: the multivariate Laplace with that covariance (:func:`_laplace_log_g`).
    """
    p = mu.shape[0]
    gxx, gxy, gyy = G[:p, :p], G[:p, p], G[p, p]
    quad = (gyy - 2 * mu @ gxy + mu @ gxx @ mu) / sigma2
    logdet = n * jnp.log(sigma2) - jnp.log1p(-rho**2)
    if L.shape[1] > 0:
        b = L.T @ (gxy - gxx @ mu)
        P = jnp.eye(L.shape[1]) + L.T @ gxx @ L / sigma2
        c = jnp.linalg.cholesky(P)
        v = jax.scipy.linalg.solve_triangular(c, b, lower=True)
        logdet = logdet + 2 * jnp.sum(jnp.log(jnp.diag(c)))
        quad = quad - (v @ v) / sigma2**2
    if df is None:
        return -0.5 * n * jnp.log(2 * jnp.pi) - 0.5 * logdet - 0.5 * quad
    return _mix_log_g(quad, n, df) - 0.5 * logdet


def _unpack(h, q):
    return jnp.exp(h[:q]), jnp.exp(h[q]), jnp.tanh(h[q + 1])


def _collapsed(h, m0, m1, m2, first, n, effects, tau_scale, sigma_scale, reml=0.0):
    """Log posterior of ``h = (log tau (q), log sigma, atanh rho)`` with ``mu`` (flat) and the effects
    integrated out, Jacobians of the transforms included; also ``mu_hat`` and its covariance."""
    q = effects.shape[0]
    p = m0.shape[-1] - 1
    tau, sigma, rho = _unpack(h, q)
    s2 = sigma**2
    G = whitened_gram(m0, m1, m2, first, rho)                              # (R, p+1, p+1)
    E = jnp.zeros((p, q)).at[effects, jnp.arange(q)].set(tau)             # (p, q) = E diag(tau)

    def per_run(Gr, nr):
        # whitened V = s2 I + B B^T, B = W J E: V^{-1} = (I - B P^{-1} B^T / s2) / s2, P = I + B^T B / s2
        P = jnp.eye(q) + E.T @ Gr[:p, :p] @ E / s2
        c = jnp.linalg.cholesky(P)
        A = jax.scipy.linalg.solve_triangular(c, E.T @ Gr[:p, :], lower=True)      # (q, p+1)
        const = -0.5 * nr * jnp.log(2 * jnp.pi * s2) + 0.5 * jnp.log1p(-rho**2) - jnp.sum(jnp.log(jnp.diag(c)))
        return (Gr - A.T @ A / s2) / s2, const

    Vinv, consts = jax.vmap(per_run)(G, n)
    S = Vinv.sum(0)
    H, g, c = S[:p, :p], S[:p, p], S[p, p]
    ch = jnp.linalg.cholesky(H)
    w = jax.scipy.linalg.solve_triangular(ch, g, lower=True)
    mu = jax.scipy.linalg.cho_solve((ch, True), g)
    lp = consts.sum() - 0.5 * (c - w @ w) + reml * (0.5 * p * jnp.log(2 * jnp.pi) - jnp.sum(jnp.log(jnp.diag(ch))))
    # priors: half-normal tau, sigma (+ log Jacobians), uniform rho on (-1, 1) (+ atanh Jacobian)
    lp += jnp.sum(-0.5 * (tau / tau_scale) ** 2 + h[:q]) - 0.5 * (sigma / sigma_scale) ** 2 + h[q]
    lp += jnp.log1p(-rho**2)
    cov = jax.scipy.linalg.cho_solve((ch, True), jnp.eye(p))
    return lp, mu, cov


#: Gauss-Hermite nodes and weights for the Laplace family's scale-mixture integral (:func:`_laplace_log_g`).
_GH_T, _GH_W = np.polynomial.hermite.hermgauss(32)


def _laplace_log_g(Q, n):
    r"""Log density part of one run's rows that depends on :math:`Q` for the multivariate (symmetric) Laplace.

    The run's rows are :math:`N(0, w V)` with :math:`w \sim \mathrm{Exp}(1)` (mean 1, so :math:`V` is the
    covariance; every row's margin is a univariate Laplace): the density is
    :math:`(2\pi)^{-n/2}|V|^{-1/2} I`, :math:`I = \int_0^\infty w^{-n/2} e^{-Q/(2w) - w}\,dw
    = 2 (Q/2)^{(1-n/2)/2} K_{1-n/2}(\sqrt{2Q})`. The Bessel function of order :math:`1 - n/2` (hundreds of
    rows) has no cheap JAX form; the integral is taken in :math:`s = \log w`, where its integrand
    :math:`\exp((1-n/2)s - \tfrac Q2 e^{-s} - e^s)` is log-concave, by 32-node Gauss-Hermite around its mode
    (closed form) with the curvature there as scale (``test_laplace_run_density_equals_scipy``).
    Returns :math:`-\tfrac n2\log 2\pi + \log I`.
    """
    Q = jnp.maximum(Q, 1e-300)
    a = 1.0 - 0.5 * n
    root = jnp.sqrt(a**2 + 2 * Q)
    x = jnp.where(a > 0, 0.5 * (a + root), Q / (root - jnp.minimum(a, 0.0)))      # e^{s*}: x^2 - a x - Q/2 = 0
    s0 = jnp.log(x)
    c = 1.0 / jnp.sqrt(0.5 * Q / x + x)                                           # 1 / sqrt(-phi''(s*))
    s = s0[..., None] + jnp.sqrt(2.0) * c[..., None] * _GH_T
    phi = jnp.asarray(a)[..., None] * s - 0.5 * Q[..., None] * jnp.exp(-s) - jnp.exp(s)
    logI = jax.scipy.special.logsumexp(phi + _GH_T**2 + jnp.log(_GH_W), axis=-1) + jnp.log(jnp.sqrt(2.0) * c)
    return -0.5 * n * jnp.log(2 * jnp.pi) + logI


def _mix_log_g(Q, n, df):
    """The ``Q``-dependent log density of a run under a Gaussian scale mixture: Student-t (``df`` a number) or
    Laplace (``df = "laplace"``); the ``-log|V|/2`` is added by the caller."""
    if isinstance(df, str):
        return _laplace_log_g(Q, n)
    if isinstance(df, (int, float)):
        return (jax.scipy.special.gammaln((df + n) / 2) - jax.scipy.special.gammaln(df / 2)
                - 0.5 * n * jnp.log(df * jnp.pi) - 0.5 * (df + n) * jnp.log1p(Q / df))
    # a traced dof (the learned-df grid, :func:`_fit_learned_df`): inf is the Gaussian limit, exactly
    gauss = jnp.isinf(df)
    d = jnp.where(gauss, 1.0, df)
    t = (jax.scipy.special.gammaln((d + n) / 2) - jax.scipy.special.gammaln(d / 2)
         - 0.5 * n * jnp.log(d * jnp.pi) - 0.5 * (d + n) * jnp.log1p(Q / d))
    return jnp.where(gauss, -0.5 * n * jnp.log(2 * jnp.pi) - 0.5 * Q, t)


def _collapsed_t(h, m0, m1, m2, first, n, effects, tau_scale, sigma_scale, reml=0.0, df=4.0, iters=60):
    r"""The scale-mixture counterpart of :func:`_collapsed`: every run's rows jointly multivariate Student-t
    (``df`` dof) or Laplace (``df = "laplace"``, :func:`_laplace_log_g`) with the Gaussian's covariance
    :math:`V_r = J E T^2 E^\top J^\top + \Sigma_{AR(1)}` as shape matrix, i.e. the run's random effects and
    noise share one scale :math:`w_r` (t: precision :math:`\mathrm{Gamma}(\nu/2, \nu/2)`; Laplace: variance
    :math:`\mathrm{Exp}(1)`) -- a session whose deviation and noise are both large; Student-t log density per
    run, :math:`Q_r = (y_r - J_r\mu)^\top V_r^{-1} (y_r - J_r\mu)`:

    .. math:: \log\Gamma(\tfrac{\nu+n_r}{2}) - \log\Gamma(\tfrac\nu2) - \tfrac{n_r}{2}\log(\nu\pi)
              - \tfrac12\log|V_r| - \tfrac{\nu+n_r}{2}\log(1 + Q_r/\nu).

    ``mu`` has no closed form here: its mode by iteratively reweighted GLS (the EM update of the scale
    mixture, weights :math:`E[w_r^{-1} \mid y_r] = -2\,\partial g/\partial Q_r`, for the t
    :math:`(\nu+n_r)/(\nu+Q_r)`; from the Gaussian solution until the relative change is below 1e-11, at
    most ``iters`` steps, and one Newton step, outside the gradient), then one
    Newton step that carries the derivative of the mode (implicit differentiation: at the mode the step is
    zero and its derivative is :math:`-H^{-1}\partial_h \nabla_\mu`), its covariance the inverse observed
    information there; ``reml`` = 1 adds the Laplace approximation of integrating a flat ``mu`` (exact in
    the Gaussian case).
    """
    q = effects.shape[0]
    p = m0.shape[-1] - 1
    tau, sigma, rho = _unpack(h, q)
    s2 = sigma**2
    G = whitened_gram(m0, m1, m2, first, rho)
    E = jnp.zeros((p, q)).at[effects, jnp.arange(q)].set(tau)

    def per_run(Gr, nr):
        P = jnp.eye(q) + E.T @ Gr[:p, :p] @ E / s2
        c = jnp.linalg.cholesky(P)
        A = jax.scipy.linalg.solve_triangular(c, E.T @ Gr[:p, :], lower=True)
        logdet = nr * jnp.log(s2) - jnp.log1p(-rho**2) + 2 * jnp.sum(jnp.log(jnp.diag(c)))
        return (Gr - A.T @ A / s2) / s2, logdet

    Vinv, logdet = jax.vmap(per_run)(G, n)
    vxx, vxy, vyy = Vinv[:, :p, :p], Vinv[:, :p, p], Vinv[:, p, p]
    quad = lambda mu, vxx=vxx, vxy=vxy, vyy=vyy: (jnp.einsum("i,rij,j->r", mu, vxx, mu) - 2 * vxy @ mu   # noqa: E731
                                                  + vyy)
    dg = jax.vmap(jax.grad(lambda Q, nr: _mix_log_g(Q, nr, df)))

    sx, sy, sv = (jax.lax.stop_gradient(v) for v in (vxx, vxy, vyy))

    def step(mu):
        w = -2 * dg(jnp.maximum(quad(mu, sx, sy, sv), 0.0), n)
        return jnp.linalg.solve(jnp.einsum("r,rij->ij", w, sx), jnp.einsum("r,ri->i", w, sy))

    def body(c):
        k, mu, _ = c
        new = step(mu)
        return k + 1, new, jnp.max(jnp.abs(new - mu)) / (jnp.max(jnp.abs(new)) + 1e-300)

    mu0 = jnp.linalg.solve(sx.sum(0), sy.sum(0))
    _, mu_s, _ = jax.lax.while_loop(lambda c: (c[0] < iters) & (c[2] > 1e-11), body, (0, mu0, jnp.inf))
    mu_s = jax.lax.stop_gradient(mu_s)

    def loglik(m):
        return jnp.sum(_mix_log_g(jnp.maximum(quad(m), 0.0), n, df) - 0.5 * logdet)

    def newton(m):
        return m - jnp.linalg.solve(jax.hessian(loglik)(m), jax.grad(loglik)(m))

    mu_s = jax.lax.stop_gradient(newton(mu_s))           # polish: the EM steps converge linearly
    grad_mu = jax.grad(loglik)(mu_s)
    info = -jax.hessian(loglik)(mu_s)
    info = 0.5 * (info + info.T)
    mu = mu_s + jnp.linalg.solve(info, grad_mu)          # zero step at the mode; carries d mu / d h
    info = -jax.hessian(loglik)(mu)                      # at mu: the REML term's derivative goes through mu too
    ch = jnp.linalg.cholesky(0.5 * (info + info.T))
    lp = loglik(mu) + reml * (0.5 * p * jnp.log(2 * jnp.pi) - jnp.sum(jnp.log(jnp.diag(ch))))
    lp += jnp.sum(-0.5 * (tau / tau_scale) ** 2 + h[:q]) - 0.5 * (sigma / sigma_scale) ** 2 + h[q]
    lp += jnp.log1p(-rho**2)
    return lp, mu, jax.scipy.linalg.cho_solve((ch, True), jnp.eye(p))


def _lp(h, m0, m1, m2, first, n, effects, tau_scale, sigma_scale, reml=0.0, df=None):
    """:func:`_collapsed` (Gaussian, ``df`` None) or :func:`_collapsed_t` (Student-t with ``df`` dof, or
    Laplace with ``df = "laplace"``)."""
    if df is None:
        return _collapsed(h, m0, m1, m2, first, n, effects, tau_scale, sigma_scale, reml)
    return _collapsed_t(h, m0, m1, m2, first, n, effects, tau_scale, sigma_scale, reml, df)


@functools.partial(jax.jit, static_argnames=("df",))
def _neg_lp_and_grad(h, m0, m1, m2, first, n, effects, tau_scale, sigma_scale, reml=0.0, df=None):
    f = lambda hh: -_lp(hh, m0, m1, m2, first, n, effects, tau_scale, sigma_scale, reml, df)[0]  # noqa: E731
    return jax.value_and_grad(f)(h)


@functools.partial(jax.jit, static_argnames=("df",))
def _hessian(h, m0, m1, m2, first, n, effects, tau_scale, sigma_scale, reml=0.0, df=None):
    f = lambda hh: -_lp(hh, m0, m1, m2, first, n, effects, tau_scale, sigma_scale, reml, df)[0]  # noqa: E731
    return jax.hessian(f)(h)


@functools.partial(jax.jit, static_argnames=("df",))
def _lp_mu_cov(hs, m0, m1, m2, first, n, effects, ts, ss, reml=0.0, df=None):
    """The collapsed log posterior, ``mu_hat`` and its covariance at every row of ``hs`` (vmapped)."""
    return jax.vmap(lambda h: _lp(h, m0, m1, m2, first, n, effects, ts, ss, reml, df))(hs)


#: Proposals drawn for the importance correction of the Laplace posterior (:func:`fit_laplace`), one scrambled Sobol
#: sequence (:func:`_t_points`). With 1200 pseudo-random proposals and 400 draws the new-session sd moved by up to
#: 23 % with the seed (Belsten, run 1 left out); now by at most 6 % (``benchmarks/bench_transfer_seed.py``).
N_PROPOSALS = 2048
#: Degrees of freedom of the multivariate-t proposal (heavier tails than the posterior's, so the weights are bounded).
PROPOSAL_DF = 4.0
#: Below this effective share of the proposals a second, re-centred importance round is drawn.
MIN_ESS_FRACTION = 0.25


def _t_logq(hs, centre, cov):
    """Log density (up to the constant shared by all components) of the multivariate t proposal, per row of ``hs``."""
    d = centre.size
    w_, V = np.linalg.eigh(cov)
    maha = np.sum(((hs - centre) @ V) ** 2 / np.maximum(w_, 1e-300), axis=1)
    return -0.5 * (PROPOSAL_DF + d) * np.log1p(maha / PROPOSAL_DF) - 0.5 * np.sum(np.log(np.maximum(w_, 1e-300)))


def _t_points(rng, d: int, k: int, cov) -> tuple[np.ndarray, np.ndarray]:
    """``k`` points of the multivariate t proposal, ``(z, g)`` with ``z ~ N(0, cov)`` and ``g ~ chi2(df)/df``,
    from one scrambled Sobol sequence in ``d + 1`` dimensions (its seed from ``rng``) through the normal and
    chi-square quantiles: randomised quasi-Monte-Carlo, whose importance estimates of the between-session
    variance's moments vary less between seeds than pseudo-random draws' (the new-session sd moved by up to 23 %
    with ``uq.seed`` on Belsten, run 1 left out; sixth outside pass)."""
    import warnings

    import scipy.stats.qmc as qmc
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)            # a k that is no power of 2 keeps its balance
        u = qmc.Sobol(d + 1, scramble=True, seed=rng).random(k)
    u = np.clip(u, 1e-12, 1 - 1e-12)
    w_, V = np.linalg.eigh(np.asarray(cov, np.float64))
    z = (scipy.stats.norm.ppf(u[:, :d]) * np.sqrt(np.maximum(w_, 0.0))) @ V.T
    g = scipy.stats.chi2.ppf(u[:, d], PROPOSAL_DF) / PROPOSAL_DF
    return z, g


def _importance_round(rng, centre, cov, lp_fn, proposals, more=()):
    """One importance sample: t proposals around ``centre`` with scale ``cov`` (with ``more`` = ``((centre, cov),
    ...)``: an equal-weight mixture of such t's, one per posterior mode); ``(hs, extra, w, ess)``."""
    d = centre.size
    comps = [(centre, cov), *more]
    sizes = [proposals] if not more else rng.multinomial(proposals, np.full(len(comps), 1.0 / len(comps)))
    hs = []
    for (c, v), k in zip(comps, sizes):
        z, g = _t_points(rng, d, int(k), v)
        hs.append(c + z / np.sqrt(g)[:, None])
    hs = np.concatenate(hs)
    logq = np.logaddexp.reduce([_t_logq(hs, c, v) for c, v in comps], axis=0) - np.log(len(comps))
    lp, *extra = (np.asarray(v, np.float64) for v in lp_fn(hs))
    ok = np.isfinite(lp) & np.all([np.isfinite(e).reshape(proposals, -1).all(1) for e in extra], axis=0)
    logw = np.where(ok, lp - logq, -np.inf)
    if not ok.any():
        return hs, extra, np.full(proposals, 1.0 / proposals), 0.0
    w = np.exp(logw - logw.max())
    w /= w.sum()
    return hs, extra, w, float(1.0 / np.sum(w**2))


def _importance_draws(rng, h0, cov_h, lp_fn, draws: int, proposals: int = N_PROPOSALS, more=()):
    r"""``draws`` draws of ``h`` from the exact collapsed posterior by importance resampling.

    Proposal: a multivariate t with :data:`PROPOSAL_DF` dof around the mode with the (floored) Laplace
    covariance; weights :math:`\exp(\mathrm{lp}(h) - \log q(h))`, resampled (systematic). If the effective
    sample size is below :data:`MIN_ESS_FRACTION` of the proposals (a posterior much wider than its
    Laplace approximation, e.g. a between-session sd that five runs bound only by its prior), a second
    round re-centres the proposal on the first round's weighted mean and covariance (never narrower than
    the Laplace one) and the two rounds' samples are pooled (each weighted by its effective size). The
    Gaussian approximation in :math:`\log\tau` has lighter tails than the posterior of a between-session
    variance estimated from a few sessions (for a variance from ``R`` groups the exact posterior is close to
    a scaled inverse chi-square with ``R - 1`` dof, whose right tail is a power law): with 7 sessions the
    Laplace draws alone gave a new session's predictive 8-16 dof on x and z, with the correction 7-12
    (``bench_hybrid_shift``). ``lp_fn(hs) -> (lp, *extra)`` is evaluated on all proposals. Returns
    ``(hs, extra, ess)``: the resampled ``h`` (draws, d), the matching rows of every ``extra`` array, and
    the effective sample size (of the pooled rounds). ``more``: ``((mode, cov), ...)`` of further posterior
    modes; the first round's proposal is then the equal-weight mixture of the t's around every mode.
    """
    hs, extra, w, ess = _importance_round(rng, h0, cov_h, lp_fn, proposals, more)
    if ess < MIN_ESS_FRACTION * proposals:
        m = w @ hs
        c = (hs - m).T @ ((hs - m) * w[:, None])
        cov2 = c + cov_h * 0.25
        hs2, extra2, w2, ess2 = _importance_round(rng, m, cov2, lp_fn, proposals)
        # pool the two self-normalised samples, each weighted by its effective size
        hs = np.concatenate([hs, hs2])
        extra = [np.concatenate([a, b]) for a, b in zip(extra, extra2)]
        w = np.concatenate([w * ess, w2 * ess2]) / (ess + ess2)
        ess = float(1.0 / np.sum(w**2))
    n = hs.shape[0]
    idx = np.minimum(np.searchsorted(np.cumsum(w), (rng.uniform() + np.arange(draws)) / draws), n - 1)
    return hs[idx], [e[idx] for e in extra], ess


def _fd_hessian(fg, h0: np.ndarray, step: float = 1e-4) -> np.ndarray:
    """Hessian of the function whose value and gradient ``fg`` returns, by central differences of the gradient
    (2 d compiled gradient calls; no second compilation of the collapsed posterior's third derivatives)."""
    d = h0.size
    Hh = np.zeros((d, d))
    for j in range(d):
        e = np.zeros(d)
        e[j] = step
        Hh[:, j] = (fg(h0 + e)[1] - fg(h0 - e)[1]) / (2 * step)
    return 0.5 * (Hh + Hh.T)


#: Likelihoods of the hierarchical model (registered families with a Gaussian scale-mixture form, per run).
LIKELIHOODS = ("gaussian", "student_t", "laplace")
#: sd of log tau under the half-normal prior (of log|z|, z ~ N(0, 1)): pi / sqrt(8).
LOG_TAU_PRIOR_SD = math.pi / math.sqrt(8)
#: Floor of the Laplace precision of ``h`` in every direction: the posterior is never wider than the prior of
#: log tau. A mode near tau = 0 has an almost flat left tail in log tau (the half-normal's density ~ tau there);
#: its Gaussian approximation would be symmetric and nearly unbounded, and its right tail gave tau^2 = inf.
MIN_CURVATURE = 1.0 / LOG_TAU_PRIOR_SD**2
#: 1: integrate the flat ``mu`` out of the hyperparameter posterior (restricted likelihood); 0: profile it.
REML = 1.0


#: ``transfer_df`` value that learns the Student-t dof (:func:`_fit_learned_df`).
LEARNED = "learned"
#: Grid of the learned dof (``inf``: the Gaussian limit, evaluated exactly by :func:`_mix_log_g`).
DF_GRID = (2.5, 3.0, 4.0, 6.0, 10.0, 20.0, 50.0, math.inf)
#: Gamma(shape, rate) prior of the dof (Juarez and Steel 2010: mean 20, mode 10, P(df < 6) = 0.12), truncated
#: to df > 2 (a finite variance) and discretised on the cells of :data:`DF_GRID` (:func:`df_prior_weights`).
DF_PRIOR = (2.0, 0.1)
#: Upper edge of the last finite grid point's cell; the Gaussian limit holds the prior mass above it.
DF_GAUSS_EDGE = 100.0
#: Components of the predictive mixture below this posterior weight are dropped (the rest renormalised):
#: the tail probability of an interval moves by less than this (its 95 % half-width by < 0.1 %).
MIN_DF_WEIGHT = 1e-4


def df_prior_weights(grid=DF_GRID, prior=DF_PRIOR) -> np.ndarray:
    """Prior mass of every grid dof: the Gamma(shape, rate) prior, truncated to df > 2, integrated over the
    grid point's cell (edges at the geometric means of neighbours, 2 below the first, :data:`DF_GAUSS_EDGE`
    between the last finite point and ``inf``).

    Example: ``df_prior_weights()`` -> 8 weights summing to 1, the Gaussian limit's ``P(df > 100) / P(df > 2)``.
    """
    g = np.asarray(grid, np.float64)
    fin = g[np.isfinite(g)]
    edges = np.r_[2.0, np.sqrt(fin[1:] * fin[:-1]), DF_GAUSS_EDGE if np.isinf(g[-1]) else np.inf]
    edges = np.r_[edges, np.inf] if np.isinf(g[-1]) else edges
    cdf = scipy.stats.gamma(prior[0], scale=1.0 / prior[1]).cdf(edges)
    w = np.diff(cdf)
    return w / w.sum()


def _check_likelihood(likelihood: str, df) -> float | str | None:
    """``None`` (Gaussian), the Student-t dof, ``"learned"`` or ``"laplace"``; ValueError naming the bad value."""
    from bayesmag._src.core.likelihoods import get_likelihood

    if likelihood not in LIKELIHOODS:
        raise ValueError(f"the hierarchical transfer likelihood {likelihood!r} is not supported; it must be one of "
                         f"{list(LIKELIHOODS)} (a Gaussian scale mixture per run).")
    if likelihood == "gaussian":
        return None
    if likelihood == "laplace":
        return "laplace"
    if df == LEARNED:
        return LEARNED
    get_likelihood(likelihood).shape_params["df"].check("uq.transfer_df", df, likelihood)
    return float(df)


@dataclasses.dataclass(frozen=True)
class SessionPosterior:
    """What a new session's predictive needs, per axis: moments of the variance parts and the mean's covariance.

    ``w_mean`` (3, q+1) / ``w_cov`` (3, q+1, q+1): posterior mean / covariance of
    ``(tau_1^2..tau_q^2, sigma^2/(1-rho^2))``; ``mu_cov`` (3, p, p): posterior covariance of ``mu``
    (scaled units); ``scale`` (3, p): Jacobian column scales; ``effects``: names with random effects;
    ``level``: the central level the equivalent sd is matched at; ``n_runs``: training runs;
    ``method``: "laplace" or "nuts"; ``mu`` (3, p): posterior mean of ``mu`` in model units; ``df``: the
    likelihood's dof (inf: Gaussian; finite: Student-t, every run's effects and noise share one
    Gamma(df/2, df/2) precision scale, so a new session's error is itself t with ``df`` dof given the
    hyperparameters; ``w_mean`` and ``w_cov`` then hold the variances, i.e. the shapes times df/(df-2));
    ``centre`` (3, q): the scaled Jacobian value each effect is measured from (None: 0); ``prior_only``: the
    effects too few runs inform, carried with their prior moments about the training mean of their
    column (:func:`with_prior_effects`).
    """

    w_mean: np.ndarray
    w_cov: np.ndarray
    mu_cov: np.ndarray
    scale: np.ndarray
    effects: tuple
    level: float
    n_runs: int
    method: str
    mu: np.ndarray
    effect_index: tuple = ()
    df: float = math.inf
    centre: np.ndarray | None = None
    prior_only: tuple = ()
    laplace: bool = False
    ess: tuple = ()     # per axis: effective sample size of the importance correction (Laplace path; () if none)
    # learned dof (``transfer_df = "learned"``): the dof grid, its posterior weight per axis (3, K) and the variance
    # moments given each dof (3, K, q+1) / (3, K, q+1, q+1); w_mean / w_cov are then the mixture's (summaries)
    df_grid: tuple = ()
    df_weight: np.ndarray | None = None
    mix_w_mean: np.ndarray | None = None
    mix_w_cov: np.ndarray | None = None
    df_log_evidence: np.ndarray | None = None   # (3, K) log marginal likelihood of each dof (diagnostic, not saved)
    # per axis: the constant transfer sd used instead of the model's where it failed its check against
    # leave-one-run-out (``transfer_check = "loro"``, :func:`hierarchical_transfer`); nan: the model's own; (): none
    fallback_sd: tuple = ()

    def components(self) -> list["SessionPosterior"]:
        """The fixed-dof posteriors a learned-dof one mixes (``[]`` if the dof is fixed); ``mu`` and its
        covariance are the mixture's (pooled over the dof by the law of total covariance)."""
        return [dataclasses.replace(self, w_mean=self.mix_w_mean[:, k], w_cov=self.mix_w_cov[:, k], df=float(d),
                                    df_grid=(), df_weight=None, mix_w_mean=None, mix_w_cov=None, df_log_evidence=None)
                for k, d in enumerate(self.df_grid)]

    @property
    def tau(self) -> np.ndarray:
        """(3, q) posterior root-mean-square random-effect sd, uT at an RMS input."""
        return np.sqrt(np.maximum(self.w_mean[:, :-1], 0))

    def variance_moments(self, J: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per row and axis: mean and variance of the new-session variance ``v``, and the noise part's mean.

        ``J``: (3, n, p) Jacobian in model units. Returns three (n, 3) arrays.
        """
        return _moments(np.asarray(J) / self.scale[:, None, :], self.w_mean, self.w_cov, self.mu_cov,
                        np.asarray(self.effect_index, int), self.centre)

    def predictive_t(self, J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row-wise Student-t of the new-session error: ``(df, scale)`` (n, 3) each (moment matched)."""
        if self.df_grid:
            raise ValueError("a learned-dof session posterior is a mixture of Student-t's, one per dof "
                             "(components(), new_session_variance); it has no single row-wise t.")
        m, v, _ = self.variance_moments(J)
        ratio = v / np.maximum(m, 1e-300) ** 2
        if self.laplace:
            # v = a s, s ~ Exp(1) (mean 1, Var s = 1), independent of the posterior part a
            ratio = (1 + ratio) * 2 - 1
        elif math.isfinite(self.df):
            # v = a s, a the posterior part, s = (1/w) (df-2)/df (mean 1, Var s = 2/(df-4)), independent:
            # Var v / (E v)^2 = (1 + ratio)(1 + 2/(df-4)) - 1; df <= 4 (infinite Var s): the likelihood's df
            if self.df <= 4:
                df = np.full_like(m, self.df)
                return df, np.sqrt(m * (df - 2) / df)
            ratio = (1 + ratio) * (1 + 2 / (self.df - 4)) - 1
        df = 4.0 + 2.0 / np.maximum(ratio, 1e-12)
        df = np.minimum(df, 1e6)
        return df, np.sqrt(m * (df - 2) / df)

    def new_session_variance(self, J: np.ndarray, level: float | None = None) -> np.ndarray:
        """(n, 3) Gaussian variance with the same central ``level`` interval as the new-session predictive."""
        level = self.level if level is None else level
        if self.df_grid:
            return _mixture_variance(self, J, level)
        df, s = self.predictive_t(J)
        u = 0.5 + level / 2
        var = (scipy.stats.t.ppf(u, df) * s / scipy.stats.norm.ppf(u)) ** 2
        if self.laplace:
            # the t with the Laplace mixture's variance and kurtosis (6 dof) has a 95 % interval 5.7 % shorter
            # than the Laplace's own: never below the Laplace interval at the mean variance
            m, _, _ = self.variance_moments(J)
            var = np.maximum(var, (np.log(1 / (1 - level)) * np.sqrt(m / 2) / scipy.stats.norm.ppf(u)) ** 2)
        return var

    def transfer_sd(self, J: np.ndarray, level: float | None = None) -> np.ndarray:
        """(n, 3) transfer sd: the equivalent new-session variance less the mean within-session noise."""
        _, _, noise = self.variance_moments(J)
        sd = np.sqrt(np.maximum(self.new_session_variance(J, level) - noise, 0.0))
        if self.fallback_sd:
            fb = np.asarray(self.fallback_sd, np.float64)
            sd = np.where(np.isnan(fb)[None, :], sd, fb[None, :])
        return sd

    @property
    def checked_axes(self) -> tuple:
        """The axes (names) whose transfer is leave-one-run-out's constant sd, the model having failed its check."""
        return tuple(ax for ax, v in zip(AXES, self.fallback_sd) if not math.isnan(v)) if self.fallback_sd else ()

    def transfer_sd_for(self, fit, data) -> np.ndarray:
        """(n, 3) transfer sd of every row of ``data`` for the physics ``fit`` (its Jacobian at ``fit.theta``)."""
        if data.n == 0:
            return np.zeros((0, 3))
        return self.transfer_sd(_jacobian(fit, data))

    def as_arrays(self) -> dict:
        return {"w_mean": self.w_mean, "w_cov": self.w_cov, "mu_cov": self.mu_cov, "scale": self.scale,
                "mu": self.mu, **({} if self.centre is None else {"centre": self.centre}),
                **({"df_weight": self.df_weight, "mix_w_mean": self.mix_w_mean, "mix_w_cov": self.mix_w_cov}
                   if self.df_grid else {})}

    def meta(self) -> dict:
        return {"effects": list(self.effects), "effect_index": list(map(int, self.effect_index)),
                "level": float(self.level), "n_runs": int(self.n_runs), "method": self.method,
                "likelihood": self.likelihood, "df": self._df_meta(),
                "prior_only": list(self.prior_only),
                **({"df_grid": [float(d) if math.isfinite(d) else None for d in self.df_grid]} if self.df_grid else {}),
                **({"fallback_sd": [None if math.isnan(v) else float(v) for v in self.fallback_sd]}
                   if self.fallback_sd else {})}

    def _df_meta(self):
        return LEARNED if self.df_grid else float(self.df) if math.isfinite(self.df) else None

    @property
    def likelihood(self) -> str:
        """``"gaussian"``, ``"student_t"`` or ``"laplace"``."""
        return "laplace" if self.laplace else "student_t" if math.isfinite(self.df) or self.df_grid else "gaussian"

    def as_dict(self) -> dict:
        """JSON summary: per axis the random-effect sds and the noise sd (posterior root means)."""
        return {"method": self.method, "n_runs": int(self.n_runs), "effects": list(self.effects),
                "likelihood": self.likelihood, "df": self._df_meta(),
                "prior_only": list(self.prior_only),
                **({"df_posterior": {ax: {("inf" if math.isinf(d) else f"{d:g}"): round(float(self.df_weight[a, k]), 6)
                                          for k, d in enumerate(self.df_grid)} for a, ax in enumerate(AXES)}}
                   if self.df_grid else {}),
                **({"importance_ess": [round(float(e), 1) for e in self.ess]} if self.ess else {}),
                **({"fallback_sd": {ax: None if math.isnan(v) else float(v) for ax, v in zip(AXES, self.fallback_sd)}}
                   if self.fallback_sd else {}),
                "tau": {ax: dict(zip(self.effects, map(float, self.tau[a]))) for a, ax in enumerate(AXES)},
                "noise_sd": {ax: float(np.sqrt(self.w_mean[a, -1])) for a, ax in enumerate(AXES)}}


def _moments(f, w_mean, w_cov, mu_cov, eidx, centre=None):
    """Mean / variance of ``v = sum_j tau_j^2 (f_j - c_j)^2 + noise + f^T C f`` per row: (n, 3) each, plus noise mean."""
    fe = f[:, :, eidx] - (0.0 if centre is None else np.asarray(centre)[:, None, :])
    fe2 = fe**2                                                             # (3, n, q)
    wvec = np.concatenate([fe2, np.ones(fe2.shape[:2] + (1,))], axis=2)     # (3, n, q+1)
    m = np.einsum("anq,aq->na", wvec, w_mean) + np.einsum("anp,apk,ank->na", f, mu_cov, f)
    v = np.einsum("anq,aqk,ank->na", wvec, w_cov, wvec)
    return m, np.maximum(v, 0.0), np.broadcast_to(w_mean[:, -1], m.shape).copy()


def _summarise(tau2, noise, mu_draws_cov, mu_mean, stats: RunStats, names, level, method,
               df: float | str = math.inf) -> SessionPosterior:
    w = np.concatenate([tau2, noise[..., None]], axis=-1)                   # (3, K, q+1)
    if not (np.isfinite(w).all() and np.isfinite(mu_draws_cov).all() and np.isfinite(mu_mean).all()):
        raise RuntimeError("the hierarchical transfer model's posterior is not finite (a between-session sd "
                           "without a bound); use [uq] transfer = \"loro\" for these data.")
    laplace = isinstance(df, str)
    df = math.inf if laplace else df               # Laplace: the shape matrix is the covariance (E w = 1)
    if math.isfinite(df):
        w = w * df / (df - 2)                      # shape -> variance of the scale mixture
    w_mean = w.mean(1)
    w_cov = np.einsum("aki,akj->aij", w - w_mean[:, None], w - w_mean[:, None]) / max(w.shape[1] - 1, 1)
    p = stats.n_params                             # the nuisance columns' margin dropped
    return SessionPosterior(w_mean, w_cov, mu_draws_cov[:, :p, :p], stats.scale[:, :p],
                            tuple(names[i] for i in stats.effects),
                            float(level), int(stats.n.size), method, mu_mean[:, :p] / stats.scale[:, :p],
                            effect_index=tuple(int(i) for i in stats.effects), df=float(df), laplace=laplace)


def _mixture_variance(post: "SessionPosterior", J: np.ndarray, level: float) -> np.ndarray:
    """(n, 3) Gaussian variance with the same central ``level`` interval as the learned-dof predictive: the
    mixture over the dof grid (posterior weights; those below :data:`MIN_DF_WEIGHT` dropped, the rest
    renormalised) of every dof's row-wise Student-t (as :meth:`SessionPosterior.predictive_t` of
    :meth:`SessionPosterior.components`, all dofs in one einsum). Its quantile by Newton steps on the mixture's
    cdf from the weighted mean of the two most probable dofs' quantiles, with Halley's correction (the density's
    derivative costs no further cdf; the correction factor kept within [1/2, 2], never below ``z_u min_k s_k``, a
    lower bound), to a relative step of 1e-5, after which the error is of the order of its cube (Newton alone:
    its square); only the rows not yet converged are iterated. Two or three cdf evaluations per row where Newton
    to 1e-10 took four (each about 0.5 s at 100 000 rows x 3 axes x 7 dofs on this machine); the same variances
    to 1e-13 (``benchmarks/time_learned_df.py --apply``)."""
    u = 0.5 + level / 2
    W = np.where(post.df_weight >= MIN_DF_WEIGHT, post.df_weight, 0.0)
    W = W / W.sum(axis=1, keepdims=True)                                    # (3, K)
    used = np.flatnonzero((W > 0).any(axis=0))
    if used.size == 1:
        return post.components()[used[0]].new_session_variance(J, level)
    f = np.asarray(J) / post.scale[:, None, :]
    eidx = np.asarray(post.effect_index, int)
    fe = f[:, :, eidx] - (0.0 if post.centre is None else np.asarray(post.centre)[:, None, :])
    wvec = np.concatenate([fe**2, np.ones(fe.shape[:2] + (1,))], axis=2)   # (3, n, q+1)
    fcf = np.einsum("anp,apk,ank->na", f, post.mu_cov, f)
    m = np.einsum("anq,akq->kna", wvec, post.mix_w_mean[:, used]) + fcf    # (K', n, 3)
    v = np.maximum(np.einsum("anq,akqr,anr->kna", wvec, post.mix_w_cov[:, used], wvec), 0.0)
    dfk = np.asarray(post.df_grid, np.float64)[used][:, None, None]
    ratio = v / np.maximum(m, 1e-300) ** 2
    mid = np.isfinite(dfk) & (dfk > 4)
    ratio = np.where(mid, (1 + ratio) * (1 + 2 / np.where(mid, dfk - 4, 1.0)) - 1, ratio)
    nu = np.where(np.isfinite(dfk) & (dfk <= 4), dfk, np.minimum(4.0 + 2.0 / np.maximum(ratio, 1e-12), 1e6))
    sc = np.sqrt(m * (nu - 2) / nu)
    w = np.broadcast_to(W[:, used].T[:, None, :], nu.shape)
    nu, sc, w = (a.reshape(used.size, -1) for a in (nu, sc, w))             # (K', n*3)
    # start: the weighted mean of the quantiles of the (up to) two most probable dofs of the axis
    order = np.argsort(-W[:, used], axis=1)[:, :2]                         # (3, 2)
    cols = np.arange(nu.shape[1])
    x, tot = np.zeros(nu.shape[1]), np.zeros(nu.shape[1])
    for j in range(order.shape[1]):
        pick = np.broadcast_to(order[None, :, j], m.shape[1:]).ravel()
        wj = w[pick, cols]
        x += wj * sc[pick, cols] * scipy.special.stdtrit(nu[pick, cols], u)
        tot += wj
    x = x / tot
    lower = scipy.stats.norm.ppf(u) * np.where(w > 0, sc, np.inf).min(0)
    lognorm = (scipy.special.gammaln((nu + 1) / 2) - scipy.special.gammaln(nu / 2) - 0.5 * np.log(nu * np.pi)
               - np.log(sc))
    act = np.arange(x.size)
    for _ in range(60):
        n_, s_, w_, z = nu[:, act], sc[:, act], w[:, act], x[act] / sc[:, act]
        F = np.sum(w_ * scipy.special.stdtr(n_, z), axis=0) - u
        pdf = w_ * np.exp(lognorm[:, act] - 0.5 * (n_ + 1) * np.log1p(z**2 / n_))
        dens = np.sum(pdf, axis=0)
        slope = np.sum(pdf * (-(n_ + 1) * z / (s_ * (n_ + z**2))), axis=0)      # the density's derivative
        step = F / np.maximum(dens, 1e-300)
        # Halley's correction (cubic convergence), kept within [1/2, 2] of the Newton step
        step = step / np.clip(1 - 0.5 * step * slope / np.maximum(dens, 1e-300), 0.5, 2.0)
        new = np.maximum(x[act] - step, lower[act])
        done = np.abs(new - x[act]) <= 1e-5 * np.abs(new)     # the error left: of the order of 1e-15 of it
        x[act] = new
        act = act[~done]
        if act.size == 0:
            break
    return (x.reshape(m.shape[1:]) / scipy.stats.norm.ppf(u)) ** 2


def _pool_components(post: "SessionPosterior", comps: Sequence["SessionPosterior"]) -> "SessionPosterior":
    """The learned-dof posterior of ``comps`` (one per dof of ``post.df_grid``, sharing ``mu`` and its covariance)
    with ``post``'s weights: ``w_mean`` / ``w_cov`` the mixture's moments (law of total covariance)."""
    W = post.df_weight
    wm = np.stack([c.w_mean for c in comps], 1)                             # (3, K, q+1)
    wc = np.stack([c.w_cov for c in comps], 1)
    mean = np.einsum("ak,aki->ai", W, wm)
    dev = wm - mean[:, None]
    cov = np.einsum("ak,akij->aij", W, wc + dev[..., :, None] * dev[..., None, :])
    return dataclasses.replace(comps[0], w_mean=mean, w_cov=cov, df=math.inf, df_grid=tuple(post.df_grid),
                               df_weight=W, mix_w_mean=wm, mix_w_cov=wc, df_log_evidence=post.df_log_evidence,
                               ess=post.ess)


@jax.jit
def _neg_lp_grad_grid(H, dfs, m0, m1, m2, first, n, effects, ts, ss, reml):
    """``-sum_k lp(H_k; dfs_k)`` of the Student-t collapsed posterior (:func:`_collapsed_t`), its gradient (K, d)
    and the per-dof ``lp`` (K,): every dof of the grid in one vmapped call (the blocks are independent)."""
    def f(Hm):
        lp = jax.vmap(lambda h, d: _collapsed_t(h, m0, m1, m2, first, n, effects, ts, ss, reml, d)[0])(Hm, dfs)
        return -jnp.sum(lp), lp
    (v, lp), g = jax.value_and_grad(f, has_aux=True)(H)
    return v, g, lp


@jax.jit
def _lp_mu_cov_grid(hs, dfs, m0, m1, m2, first, n, effects, ts, ss, reml):
    """:func:`_collapsed_t` at every row of ``hs`` with the dof ``dfs`` of that row (vmapped)."""
    return jax.vmap(lambda h, d: _collapsed_t(h, m0, m1, m2, first, n, effects, ts, ss, reml, d))(hs, dfs)


def _t_log_norm(d: int) -> float:
    """log normalising constant of the :data:`PROPOSAL_DF` multivariate t that :func:`_t_logq` leaves out."""
    nu = PROPOSAL_DF
    return float(scipy.special.gammaln((nu + d) / 2) - scipy.special.gammaln(nu / 2) - 0.5 * d * np.log(nu * np.pi))


#: Total importance proposals of the learned-dof fit (pseudo-random), split over the dofs the screen keeps.
N_PROPOSALS_LEARNED = 1200
#: Fewest importance proposals of a dof the screen keeps (its evidence matters, its draws hardly).
MIN_PROPOSALS_DF = 100
#: Screen of the learned-dof fit: a dof whose Laplace log posterior is more than this many nats below the best
#: one's gets weight 0 (it would get < 2e-9 of the mass unless the Laplace evidence is off by nats).
DF_SCREEN = 20.0


def _fit_learned_df(stats: RunStats, names, *, level, tau_scale, sigma_scale, draws, seed, reml,
                    proposals: int = N_PROPOSALS_LEARNED) -> "SessionPosterior":
    r"""The Student-t model with its dof learned (``transfer_df = "learned"``), per axis.

    The dof is given a discrete posterior on :data:`DF_GRID` (2.5 ... 50 and the Gaussian limit): prior
    :func:`df_prior_weights` (Gamma(2, 0.1), Juarez and Steel 2010, discretised) times each dof's marginal
    likelihood :math:`p(y \mid \nu) = \int p(y \mid h, \nu)\, p(h)\, dh` (``mu`` flat and integrated as in
    :func:`_collapsed_t`: the same improper constant for every dof, so the ratios are proper). All dofs are
    fitted together: BFGS on the sum of the (independent) negative log posteriors, one vmapped JAX call per
    step, and the Hessians by central differences of that gradient, every dof's block at once. Their Laplace
    evidences screen the grid (:data:`DF_SCREEN`); for the dofs kept, the integral is estimated by the
    importance sample that also corrects their draws (as :func:`_importance_draws`: the mean of
    :math:`p(y, h \mid \nu) / q(h)` over a t proposal around the dof's mode with its normalised density; exact
    where the Laplace approximation is not: a between-session sd near 0 skews the posterior of
    :math:`\log\tau`), :data:`N_PROPOSALS_LEARNED` proposals in one vmapped call, :data:`MIN_PROPOSALS_DF` per
    dof kept and the rest by the Laplace posterior weight. A grid,
    not a continuous dof in ``h``: its Gaussian limit is exact, and the dof's posterior is far from Gaussian in
    any scale (flat towards the Gaussian, sharp below 4 on heavy-tailed data).
    """
    grid = np.asarray(DF_GRID, np.float64)
    K = grid.size
    log_prior = np.log(df_prior_weights(grid))
    rng = np.random.default_rng(seed)
    q = stats.effects.size
    d = q + 2
    eff = jnp.asarray(stats.effects)
    dfs = jnp.asarray(grid)
    logc = _t_log_norm(d)
    weight, logZ, mix_mean, mix_cov, mus, covs, esss = [], [], [], [], [], [], []
    for a in range(3):
        args = (jnp.asarray(stats.m0[a]), jnp.asarray(stats.m1[a]), jnp.asarray(stats.m2[a]),
                jnp.asarray(stats.first[a]), jnp.asarray(stats.n), eff, tau_scale, sigma_scale, float(reml))

        def fg(x):
            v, g, _ = _neg_lp_grad_grid(jnp.asarray(x.reshape(K, d)), dfs, *args)
            v, g = float(v), np.asarray(g, np.float64).ravel()
            return (v, g) if np.isfinite(v) else (1e300, np.zeros_like(g))

        def fg_gauss(h):
            v, g = _neg_lp_and_grad(jnp.asarray(h), *args, df=None)
            v, g = float(v), np.asarray(g, np.float64)
            return (v, g) if np.isfinite(v) else (1e300, np.zeros_like(g))

        # every dof from the Gaussian model's mode (found as the default path finds it, from the moment start):
        # the dofs' modes then lie in the basin the default uses; from the moment start some dofs' BFGS reached
        # the absurd large-tau mode of docs/sessions.md "Several modes", whose evidence is higher
        h_gauss = _best_of(fg_gauss, _with_rho(_init_h(stats, a, tau_scale), q, rho_start(stats, a))).x
        res = scipy.optimize.minimize(fg, np.tile(h_gauss, K), jac=True, method="BFGS",
                                      options={"gtol": 1e-6, "maxiter": 3000})
        modes = res.x.reshape(K, d)
        lp_modes = -np.asarray(_neg_lp_grad_grid(jnp.asarray(modes), dfs, *args)[2], np.float64)
        Hs = np.zeros((K, d, d))
        for j in range(d):
            e = np.zeros((K, d))
            e[:, j] = 1e-4
            Hs[:, :, j] = (fg((modes + e).ravel())[1] - fg((modes - e).ravel())[1]).reshape(K, d) / 2e-4
        covh, lap = [], np.zeros(K)
        for k in range(K):
            w_, V = np.linalg.eigh(0.5 * (Hs[k] + Hs[k].T))
            w_ = np.maximum(w_, MIN_CURVATURE)
            covh.append((V / w_) @ V.T)
            lap[k] = -lp_modes[k] + 0.5 * d * np.log(2 * np.pi) - 0.5 * np.sum(np.log(w_))
        lap = np.where(np.isfinite(lap), lap, -np.inf)
        keep = np.flatnonzero(log_prior + lap >= np.max(log_prior + lap) - DF_SCREEN)
        # proposals: MIN_PROPOSALS_DF per dof kept, the rest by Laplace posterior weight (a fixed total: one shape)
        wl = np.exp(log_prior[keep] + lap[keep] - np.max(log_prior[keep] + lap[keep]))
        extra = proposals - MIN_PROPOSALS_DF * keep.size
        counts = MIN_PROPOSALS_DF + np.floor(extra * wl / wl.sum()).astype(int)
        counts[np.argmax(wl)] += proposals - counts.sum()
        split = np.split(np.arange(proposals), np.cumsum(counts)[:-1])
        rows = jnp.asarray(np.concatenate([np.full(p_.size, grid[k]) for k, p_ in zip(keep, split)]))

        def evaluate(centres, cs):
            hs = []
            for k, p_ in zip(keep, split):
                z = rng.multivariate_normal(np.zeros(d), cs[k], size=p_.size, method="eigh")
                hs.append(centres[k] + z / np.sqrt(rng.chisquare(PROPOSAL_DF, size=p_.size) / PROPOSAL_DF)[:, None])
            hs = np.concatenate(hs)
            lp, mu_k, cov_k = (np.asarray(v, np.float64) for v in _lp_mu_cov_grid(jnp.asarray(hs), rows, *args))
            out = {}
            for k, p_ in zip(keep, split):
                ok = np.isfinite(lp[p_]) & np.isfinite(mu_k[p_]).all(1) & np.isfinite(cov_k[p_]).all((1, 2))
                logw = np.where(ok, lp[p_] - _t_logq(hs[p_], centres[k], cs[k]) - logc, -np.inf)
                out[k] = [(hs[p_], mu_k[p_], cov_k[p_], logw)]
            return out

        rounds = evaluate(modes, covh)
        # dofs the screen gives >= 1 % of the mass whose proposal missed (a negligible dof's weight stays negligible)
        redo = [k for k, c in zip(keep, counts) if wl[list(keep).index(k)] / wl.sum() >= 0.01
                and _ess(rounds[k][0][3]) < MIN_ESS_FRACTION * c]
        if redo:    # a second, re-centred round for the dofs whose proposal missed (as _importance_draws)
            cen, cs = list(modes), list(covh)
            for k in redo:
                hk, _, _, lw = rounds[k][0]
                w = _normalised(lw)
                if w.sum() > 0:
                    m = w @ hk
                    cen[k], cs[k] = m, (hk - m).T @ ((hk - m) * w[:, None]) + covh[k] * 0.25
            second = evaluate(cen, cs)
            for k in redo:
                rounds[k] += second[k]
        lz = np.full(K, -np.inf)
        tau2, noise = np.zeros((K, draws, q)), np.zeros((K, draws))
        mu_m, mu_c = np.zeros((K, stats.scale.shape[1])), np.zeros((K, stats.scale.shape[1], stats.scale.shape[1]))
        ess_k = np.zeros(K)
        for k in keep:
            # each round's mean weight estimates p(y | df); pooled with their effective sizes as weights
            es = np.array([_ess(r[3]) for r in rounds[k]])
            zs = np.array([np.logaddexp.reduce(r[3]) - np.log(r[3].size) for r in rounds[k]])
            if es.sum() > 0:
                lz[k] = np.logaddexp.reduce(zs + np.log(np.maximum(es, 1e-300))) - np.log(es.sum())
            hk, mk, ck = (np.concatenate([r[i] for r in rounds[k]]) for i in range(3))
            w = np.concatenate([_normalised(r[3]) * e for r, e in zip(rounds[k], es)])
            w = w / w.sum() if w.sum() > 0 else np.full(w.size, 1.0 / w.size)
            ess_k[k] = 1.0 / np.sum(w**2)
            idx = np.minimum(np.searchsorted(np.cumsum(w), (rng.uniform() + np.arange(draws)) / draws), w.size - 1)
            f = grid[k] / (grid[k] - 2) if np.isfinite(grid[k]) else 1.0      # shape -> variance
            tau2[k] = np.exp(2 * hk[idx, :q]) * f
            noise[k] = np.exp(2 * hk[idx, q]) / (1 - np.tanh(hk[idx, q + 1]) ** 2) * f
            mu_m[k] = mk[idx].mean(0)
            mu_c[k] = ck[idx].mean(0) + np.atleast_2d(np.cov(mk[idx].T))
        lpost = log_prior + lz
        wk = np.exp(lpost - lpost.max())
        wk /= wk.sum()
        wv = np.concatenate([tau2, noise[..., None]], axis=2)                 # (K, draws, q+1)
        mix_mean.append(wv.mean(1))
        mix_cov.append(np.einsum("kdi,kdj->kij", wv - wv.mean(1, keepdims=True), wv - wv.mean(1, keepdims=True))
                       / max(draws - 1, 1))
        mu = wk @ mu_m
        dm = mu_m - mu
        covs.append(np.einsum("k,kij->ij", wk, mu_c + dm[:, :, None] * dm[:, None, :]))
        mus.append(mu)
        weight.append(wk)
        logZ.append(lz)
        esss.append(float(ess_k[int(np.argmax(wk))]))
    mix_mean, mix_cov = np.stack(mix_mean), np.stack(mix_cov)
    if not (np.isfinite(mix_mean).all() and np.isfinite(mix_cov).all() and np.isfinite(np.stack(covs)).all()):
        raise RuntimeError("the hierarchical transfer model's posterior is not finite (a between-session sd "
                           "without a bound); use [uq] transfer = \"loro\" for these data.")
    p = stats.n_params                             # the nuisance columns' margin dropped
    base = SessionPosterior(mix_mean[:, 0], mix_cov[:, 0], np.stack(covs)[:, :p, :p], stats.scale[:, :p],
                            tuple(names[i] for i in stats.effects), float(level), int(stats.n.size), "laplace",
                            np.stack(mus)[:, :p] / stats.scale[:, :p], effect_index=tuple(int(i) for i in stats.effects),
                            df_grid=tuple(float(g) for g in grid), df_weight=np.stack(weight),
                            df_log_evidence=np.stack(logZ), ess=tuple(esss))
    comps = [dataclasses.replace(base, w_mean=mix_mean[:, k], w_cov=mix_cov[:, k], df=float(grid[k]), df_grid=(),
                                 df_weight=None) for k in range(K)]
    return _pool_components(base, comps)


def _normalised(logw: np.ndarray) -> np.ndarray:
    if not np.isfinite(logw).any():
        return np.zeros_like(logw)
    w = np.exp(logw - logw[np.isfinite(logw)].max())
    return w / w.sum()


def _ess(logw: np.ndarray) -> float:
    w = _normalised(logw)
    return float(1.0 / np.sum(w**2)) if w.sum() > 0 else 0.0


def _init_h(stats: RunStats, a: int, tau_scale: float) -> np.ndarray:
    q = stats.effects.size
    g = stats.m0[a].sum(0) + stats.first[a].sum(0)
    p = g.shape[0] - 1
    beta = np.linalg.lstsq(g[:p, :p], g[:p, p], rcond=None)[0]
    rss = max(g[p, p] - beta @ g[:p, p], 1e-12)
    s2 = rss / max(stats.n.sum() - p, 1)
    return np.r_[np.full(q, np.log(0.2 * tau_scale)), 0.5 * np.log(s2 * 0.3), np.arctanh(0.8)]


#: Tolerance (max abs difference in ``h``) below which two BFGS results are the same mode.
SAME_MODE = 1e-2
#: Default of ``fit_laplace(mode_search=...)``: False, the posterior around the mode found from the moment start
#: only. With True the second start finds, on some simulated campaigns of 30 sessions, a mode 50 nats higher at
#: between-session sds ten times the true ones (docs/sessions.md, "Several modes"): the collapsed posterior of
#: the diagonal model is then multimodal and its global mode wrong, so the global search is an option, not the default.
MODE_SEARCH = False


def rho_start(stats: RunStats, a: int) -> float:
    """Lag-1 autocorrelation of the within-run residuals of axis ``a`` (Yule-Walker), a data start for ``rho``.

    Every run's ``y`` is regressed on all of its own columns (minimum-norm least squares), so the runs' levels,
    gains and other session deviations leave the residual; the estimate is ``sum r_t r_(t-1) / sum r_t^2`` over
    all runs (rows 2..n), clipped to [-0.9, 0.95]. ``nan`` when there is no residual.
    """
    num = den = 0.0
    for m0, m1, f in zip(stats.m0[a], stats.m1[a], stats.first[a]):
        g = m0 + f
        p = g.shape[0] - 1
        v = np.r_[-np.linalg.lstsq(g[:p, :p], g[:p, p], rcond=1e-10)[0], 1.0]
        num += v @ m1 @ v
        den += v @ m0 @ v
    return float(np.clip(num / den, -0.9, 0.95)) if den > 0 else math.nan


def _bfgs(fg, h):
    return scipy.optimize.minimize(fg, h, jac=True, method="BFGS", options={"gtol": 1e-6, "maxiter": 500})


def _best_of(fg, starts):
    """BFGS from each start; the first start's result unless a later one reaches a different mode (by
    :data:`SAME_MODE`) with a higher log posterior (the same mode reached twice keeps the first start's point)."""
    best = None
    for h in starts:
        res = _bfgs(fg, h)
        if best is None or (res.fun < best.fun - 1e-6 and np.max(np.abs(res.x - best.x)) >= SAME_MODE):
            best = res
    return best


def _with_rho(h_init, q, rho) -> list:
    """``[h_init]``, plus ``h_init`` with ``rho`` set where ``rho`` is a number more than 0.05 from its start."""
    if not math.isfinite(rho) or abs(np.tanh(h_init[q + 1]) - rho) <= 0.05:
        return [h_init]
    return [h_init, np.r_[h_init[:q + 1], np.arctanh(rho)]]


def _modes(fg, h_init, q, tau_scale, search: bool = True, rho: float = math.nan):
    """Modes of the collapsed posterior and their (floored) Laplace covariances: ``[(h, cov), ...]``.

    The first mode: BFGS from ``h_init`` (between-session sds at a fifth of the prior scale, ``rho`` 0.8) and,
    where ``rho`` (:func:`rho_start`) is more than 0.05 from that, from the same point with ``rho`` at the
    data's autocorrelation, keeping the higher mode (a campaign of 12 white-noise runs had one axis's BFGS from
    0.8 stop at ``rho`` 0.997 with between-session sds 3-10x the truth, 96 nats below the mode at ``rho`` 0.04:
    docs/sessions.md, "The within-run correlation's start"). With ``search`` also from every ``log tau`` at the
    prior scale: with few runs the posterior of a between-session sd can be bimodal (a mode near 0
    and one where a large sd lets the runs' levels decouple; Belsten with run 3 left out, y: the larger
    mode holds 96 % of the mass by grid integration, and BFGS from the first start found only the small one).
    The second is kept only if it is a different point; the highest mode comes first. ``search`` False: the
    first mode only (the default of :func:`fit_laplace`, see :data:`MODE_SEARCH`).
    """
    out = []
    first = _best_of(fg, _with_rho(h_init, q, rho))
    second = [np.r_[np.full(q, np.log(tau_scale)), h_init[q:]]] if q and search else []
    for res in [first] + [_bfgs(fg, h) for h in second]:
        if out and np.max(np.abs(res.x - out[0][0])) < SAME_MODE:
            continue
        w, V = np.linalg.eigh(_fd_hessian(fg, res.x))
        out.append((res.x, (V / np.maximum(w, MIN_CURVATURE)) @ V.T, res.fun))
    return [(h, c) for h, c, _ in sorted(out, key=lambda o: o[2])]


def fit_laplace(stats: RunStats, names, *, level: float = 0.95, tau_scale: float = TAU_PRIOR_SCALE,
                sigma_scale: float = SIGMA_PRIOR_SCALE, draws: int = N_DRAWS, seed: int = 0,
                return_modes: bool = False, likelihood: str = "gaussian", df: float | str = 4.0,
                reml: float = REML, importance: bool = True, mode_search: bool = MODE_SEARCH) -> SessionPosterior:
    """Laplace approximation of the collapsed hyperparameter posterior (module docstring), per axis.

    The mode by BFGS (JAX gradients), the covariance the inverse Hessian there; ``draws`` draws of
    ``h`` from it give the variance moments and, averaged, the covariance of ``mu``. ``likelihood``:
    ``"gaussian"`` or ``"student_t"`` (with ``df`` > 2 dof, :func:`_collapsed_t`, or ``df = "learned"``: a
    posterior over :data:`DF_GRID`, :func:`_fit_learned_df`); ``reml``: 1 integrates
    the flat ``mu`` out (restricted likelihood), 0 profiles it (maximum); ``importance``: the draws are
    corrected to the exact collapsed posterior by importance resampling (:func:`_importance_draws`; False:
    the Gaussian approximation's own draws); ``mode_search``: BFGS from a second start too and the importance
    proposal a mixture over the modes found (:func:`_modes`).
    """
    dfs = _check_likelihood(likelihood, df)
    if dfs == LEARNED:
        if return_modes or mode_search or not importance:
            raise ValueError("transfer_df = 'learned' takes the default Laplace path only (importance draws, one "
                             "mode per dof, no return_modes).")
        return _fit_learned_df(stats, names, level=level, tau_scale=tau_scale, sigma_scale=sigma_scale, draws=draws,
                               seed=seed, reml=reml)
    rng = np.random.default_rng(seed)
    q = stats.effects.size
    eff = jnp.asarray(stats.effects)
    tau2, noise, covs, mus, modes, esss = [], [], [], [], [], []
    for a in range(3):
        args = (jnp.asarray(stats.m0[a]), jnp.asarray(stats.m1[a]), jnp.asarray(stats.m2[a]),
                jnp.asarray(stats.first[a]), jnp.asarray(stats.n), eff, tau_scale, sigma_scale, float(reml))

        def fg(h):
            v, g = _neg_lp_and_grad(jnp.asarray(h), *args, df=dfs)
            v, g = float(v), np.asarray(g, np.float64)
            return (v, g) if np.isfinite(v) else (1e300, np.zeros_like(g))

        found = _modes(fg, _init_h(stats, a, tau_scale), q, tau_scale, mode_search, rho=rho_start(stats, a))
        h0, cov_h = found[0]
        all_fn = lambda x: _lp_mu_cov(jnp.asarray(x), *args, df=dfs)     # noqa: E731
        if importance:
            hs, (mu_k, cov_k), ess = _importance_draws(rng, h0, cov_h, all_fn, draws, more=found[1:])
            esss.append(ess)
        else:
            hs = rng.multivariate_normal(h0, cov_h, size=draws, method="eigh")
            mu_k, cov_k = (np.asarray(v) for v in all_fn(hs)[1:])
        tau2.append(np.exp(2 * hs[:, :q]))
        rho = np.tanh(hs[:, q + 1])
        noise.append(np.exp(2 * hs[:, q]) / (1 - rho**2))
        ok = np.isfinite(mu_k).all(1) & np.isfinite(cov_k).all((1, 2))
        covs.append(cov_k[ok].mean(0) + np.cov(mu_k[ok].T))       # law of total covariance over h
        mus.append(mu_k[ok].mean(0))
        modes.append(h0)
    post = _summarise(np.stack(tau2), np.stack(noise), np.stack(covs), np.stack(mus), stats, names, level, "laplace",
                      df=math.inf if dfs is None else dfs)
    post = dataclasses.replace(post, ess=tuple(esss))
    return (post, np.stack(modes)) if return_modes else post


def _nuts_model(m0, m1, m2, first, n, effects, mu0, tau_scale, sigma_scale, df=None):
    """The non-centred hierarchical model of one axis in NumPyro (explicit per-run effects; with ``df``, every
    run's effects and noise scaled by its own ``w_r ~ Gamma(df/2, df/2)`` precision: the Student-t model)."""
    import numpyro
    import numpyro.distributions as dist

    R, q = m0.shape[0], effects.shape[0]
    p = m0.shape[-1] - 1
    mu = numpyro.sample("mu", dist.Normal(mu0, 10.0).to_event(1))
    tau = numpyro.sample("tau", dist.HalfNormal(tau_scale * jnp.ones(q)).to_event(1))
    sigma = numpyro.sample("sigma", dist.HalfNormal(sigma_scale))
    rho = numpyro.sample("rho", dist.Uniform(-1.0, 1.0))
    z = numpyro.sample("z", dist.Normal(jnp.zeros((R, q)), 1.0).to_event(2))
    if df is None:
        w = jnp.ones(R)
    elif isinstance(df, str):        # Laplace: variance scale v_r ~ Exp(1), precision w_r = 1 / v_r
        w = 1.0 / numpyro.sample("v", dist.Exponential(jnp.ones(R)).to_event(1))
    else:
        w = numpyro.sample("w", dist.Gamma(df / 2 * jnp.ones(R), df / 2).to_event(1))
    theta = mu[None, :] + jnp.zeros((R, p)).at[:, effects].set(tau * z / jnp.sqrt(w)[:, None])    # (R, p)
    G = whitened_gram(m0, m1, m2, first, rho)
    ll = jax.vmap(lambda Gr, nr, th, wr: run_loglik(Gr, nr, th, jnp.zeros((p, 0)), sigma**2 / wr, rho))(G, n, theta, w)
    numpyro.factor("runs", ll.sum())


def fit_nuts(stats: RunStats, names, fit, *, level: float = 0.95, tau_scale: float = TAU_PRIOR_SCALE,
             sigma_scale: float = SIGMA_PRIOR_SCALE, warmup: int = 500, samples: int = 500, seed: int = 0,
             return_draws: bool = False, likelihood: str = "gaussian", df: float = 4.0):
    """NUTS (NumPyro) on the non-centred model, one chain per axis, initialised at the LM fit."""
    from numpyro.infer import MCMC, NUTS, init_to_value

    dfs = _check_likelihood(likelihood, df)
    if dfs == LEARNED:
        raise ValueError("transfer_df = 'learned' is fitted on the Laplace path only (uq.transfer = \"hierarchical\"); "
                         "give hierarchical_nuts a number > 2.")
    q = stats.effects.size
    tau2, noise, covs, mus, raw = [], [], [], [], []
    for a in range(3):
        args = tuple(jnp.asarray(x) for x in (stats.m0[a], stats.m1[a], stats.m2[a], stats.first[a], stats.n))
        mu0 = jnp.asarray(np.r_[np.asarray(fit.theta[a]) * stats.scale[a, :len(fit.theta[a])],
                                np.zeros(stats.nuisance)])        # the decoupled columns' coefficients start at 0
        h = _init_h(stats, a, tau_scale)
        init = {"mu": mu0, "tau": jnp.exp(jnp.asarray(h[:q])), "sigma": float(np.exp(h[q])),
                "rho": float(np.tanh(h[q + 1])), "z": jnp.zeros((stats.n.size, q)),
                **({} if dfs is None else {"v" if isinstance(dfs, str) else "w": jnp.ones(stats.n.size)})}
        kernel = NUTS(_nuts_model, init_strategy=init_to_value(values=init), target_accept_prob=0.9)
        mcmc = MCMC(kernel, num_warmup=warmup, num_samples=samples, progress_bar=False)
        mcmc.run(jax.random.PRNGKey(seed + a), *args, jnp.asarray(stats.effects), mu0, tau_scale, sigma_scale, dfs)
        s = {k: np.asarray(v) for k, v in mcmc.get_samples().items()}
        tau2.append(s["tau"] ** 2)
        noise.append(s["sigma"] ** 2 / (1 - s["rho"] ** 2))
        covs.append(np.cov(s["mu"].T))
        mus.append(s["mu"].mean(0))
        raw.append(s)
    post = _summarise(np.stack(tau2), np.stack(noise), np.stack(covs), np.stack(mus), stats, names, level, "nuts",
                      df=math.inf if dfs is None else dfs)
    return (post, raw) if return_draws else post


#: A random effect is kept only if at least this many runs inform it on their own (:func:`select_effects`).
MIN_INFORMING_RUNS = 3
#: A run informs a parameter if its Jacobian column varies within the run by more than this share of the
#: column's RMS over all rows (else the run sees it only as a constant, confounded with the offset).
INFORM_FRACTION = 0.1


def select_effects(train, fit, effects: Sequence[str] = DEFAULT_EFFECTS,
                   min_runs: int = MIN_INFORMING_RUNS) -> tuple[tuple[str, ...], dict]:
    """The candidate ``effects`` that at least ``min_runs`` runs inform on their own, and the dropped ones
    with their counts: a session's change of a gain is only seen in runs that sweep that field axis (the
    offset ``O``, a constant column, is informed by every run). Counted on the x axis's Jacobian (the
    same design for every axis of the paper's model).
    """
    keep, dropped = [], {}
    for e, inf in _informing(train, fit, effects).items():
        count = int(inf.sum())
        (keep.append(e) if count >= min_runs else dropped.__setitem__(e, count))
    return tuple(keep), dropped


def _informing(train, fit, effects: Sequence[str]) -> dict:
    """``{effect: bool (R,)}``: which runs (``np.unique(train.run)`` order) inform each of the model's ``effects``
    on their own (:data:`INFORM_FRACTION`; a constant column, the offset, is informed by every run)."""
    names = list(fit.model.param_names)
    J = _jacobian(fit, train)[0]
    rms = np.sqrt(np.mean(J**2, axis=0))
    out = {}
    for e in effects:
        if e not in names:
            continue
        j = names.index(e)
        col = J[:, j]
        const = np.ptp(col) <= 1e-12 * max(rms[j], 1e-300)
        out[e] = np.array([bool(const or col[train.run == r].std() > INFORM_FRACTION * rms[j])
                           for r in np.unique(train.run)])
    return out


#: Default of ``fit_sessions(within_uninformed=...)``: True, an uninformed candidate's column varies inside a run
#: that does not inform it with a coefficient of its own (:func:`uninformed_within`); False: the shared ``mu``.
WITHIN_UNINFORMED = True


def uninformed_within(train, fit, dropped: Sequence[str], axis: int | None = None) -> dict:
    r"""``{effect: runs}``: for every candidate the selection rule dropped, the runs that do not inform it
    (``axis``: for that output axis, whose own gain ``S_<axis>`` is left out, below).

    The rule (:func:`select_effects`) says such a run sees the parameter only as a constant: its column varies
    inside the run by less than :data:`INFORM_FRACTION` of its RMS (e.g. Belsten's x field wobbling by 0.6-1.7
    uT inside the runs that sweep y or z or hold it at 37 uT). Fitted with the shared :math:`\mu_j`, that
    wobble still estimates the parameter -- its slope is the DUT's own reading noise and drift (errors in
    variables), and cross-talk from the field the run does sweep -- and where the runs' levels disagree with
    it, the model reads a large between-session sd (Belsten, run 3 left out, y: a second mode at 1.57 uT,
    docs/sessions.md). :func:`run_stats` (``within``) gives each such run's within-run deviation of the column
    its own flat coefficient, so :math:`\mu_j` is learned only from the runs that sweep it and from the runs'
    levels -- the selection rule's verdict, made part of the likelihood (the part of the wobble along the
    columns the run does inform, e.g. a reading that follows the run's sweep, stays shared: :func:`run_stats`).
    Where every run informs every candidate (the simulated campaigns) the result is empty and nothing changes.
    Not a cure for an input no run sweeps: on Belsten with run 3 left out the z axis's offset sd became bimodal
    instead (the z-from-x term then rests on run 6's level alone, docs/sessions.md, Limits).

    The output axis's own gain is not decoupled: a wobble of its field is read at unit gain, a direct signal
    of the axis's own reading (on Belsten, run 1 left out, x, decoupling it moved the offset sd from 0.018 to
    1.19 uT: each run's own gain read from its wobble, against the shared one at run 6's 37 uT level), where a
    cross-axis term or a thermal slope sees a tenth or less of it, the size of the drifts.
    """
    runs = np.unique(train.run)
    own = None if axis is None else f"S_{AXES[axis]}"
    return {e: [r for r, inf in zip(runs, v) if not inf] for e, v in _informing(train, fit, dropped).items()
            if not v.all() and e != own}


#: Default of ``fit_sessions(weak=...)``: a run's direction of the random-effect columns whose within-run sd is under
#: this many times its white-noise sd (and under INFORM_FRACTION of the columns' RMS) gets a coefficient of its own
#: (:func:`weak_directions`); None: off.
WEAK_NOISE_MULTIPLE = 5.0


def weak_directions(train, fit, effects: Sequence[str], axis: int = 0,
                    multiple: float = WEAK_NOISE_MULTIPLE, J: np.ndarray | None = None) -> dict:
    r"""``{run: W}``, ``W`` (p, k): the directions of the random ``effects``' Jacobian columns along which a run's
    within-run variation is small and mostly reading noise.

    Per run (rows in time order), the within-run deviations of the non-constant effect columns of ``axis`` (each
    scaled to unit RMS over ``train``) are split by SVD into orthogonal directions. A direction is weak where its
    sd is under :data:`INFORM_FRACTION` (the selection rule's share of the RMS, :func:`select_effects`) and under
    ``multiple`` times its own white-noise sd, read from its first differences
    (:math:`1.4826\,\mathrm{MAD}/\sqrt2`: steps and sweeps move few differences, reading noise moves all).

    Why: a run that holds the field still (or sweeps it along one line) sees the DUT's reading noise, and nothing
    of the reference, along the unswept directions. Fitted with the run's own random effects, the noise reads as
    a gain of about zero there (errors in variables: the slope is attenuated by
    :math:`s^2 / (s^2 + \sigma_{noise}^2)`), a gain of one in the runs that sweep it, and the fit buys the lower
    residual with a large between-session sd of the gains: on clean simulated campaigns of eight 100-row runs
    (``tests/test_transfer.py::_session``, reading noise 0.05 uT) the transfer sd of one axis was 3.0-4.7 uT against
    leave-one-run-out's 0.19-0.40 on 5 of 8 seeds, and where a second start finds the mode at small sds, the large
    one is higher by 33-72 nats (docs/sessions.md). A weak direction gets a coefficient of its own in that run
    (:func:`run_stats` ``directions``), so its wobble informs neither the shared parameters nor the run's random
    effects; the run's level still informs them. The two conditions keep real signal: a wobble that is a real field both sensors read
    (Belsten's 0.6-1.7 uT, slow) is not white, and a design whose rows are independent draws (a shuffled or
    subsampled record) varies by far more than a tenth of the RMS. ``J``: the (3, n, p) Jacobian on ``train`` if
    the caller has it.
    """
    names = list(fit.model.param_names)
    J = (_jacobian(fit, train) if J is None else J)[axis]
    idx = np.array([names.index(e) for e in effects if e in names], int)
    rms = np.sqrt(np.mean(J[:, idx] ** 2, axis=0))
    varies = np.ptp(J[:, idx], axis=0) > 1e-12 * np.maximum(rms, 1e-300)          # the offset's column does not
    idx, rms = idx[varies], rms[varies]
    out = {}
    run, time = np.asarray(train.run), np.asarray(train.time)
    for r in np.unique(run):
        m = np.flatnonzero(run == r)
        m = m[np.argsort(time[m], kind="stable")]
        if m.size < 3 or idx.size == 0:
            continue
        X = J[np.ix_(m, idx)] / rms
        X = X - X.mean(axis=0)
        _, sv, vt = np.linalg.svd(X, full_matrices=False)
        d = np.diff(X @ vt.T, axis=0)
        noise = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(2)
        sd = sv / np.sqrt(m.size)
        weak = (sd < multiple * noise) & (sd < INFORM_FRACTION) & (sv > 1e-9 * max(sv[0], 1e-300))
        if weak.any():
            W = np.zeros((J.shape[1], int(weak.sum())))
            W[idx] = vt[weak].T / rms[:, None]
            out[r] = W
    return out


def fit_sessions(train, fit, *, method: str = "laplace", effects: Sequence[str] = DEFAULT_EFFECTS,
                 level: float = 0.95, seed: int = 0, likelihood: str = "gaussian", df: float | str = 4.0,
                 uninformed: str | None = None, within_uninformed: bool = WITHIN_UNINFORMED,
                 shared: np.ndarray | None = None, weak: float | None = WEAK_NOISE_MULTIPLE, **kw) -> SessionPosterior:
    """The hierarchical session model of ``train`` (at least 2 runs) around the pooled LM ``fit``; the random
    effects are the ``effects`` that enough runs inform (:func:`select_effects`); ``within_uninformed``: the
    dropped ones vary inside the runs that do not inform them with a coefficient of their own
    (:func:`uninformed_within`); ``shared``: (3, n, k) columns with a coefficient shared by all runs
    (:func:`run_stats`), fitted and then integrated out; ``weak``: a run's directions of the effect columns whose
    within-run variation is small and mostly noise get a coefficient of their own (:func:`weak_directions`, ``weak``
    its noise multiple; None: off)."""
    runs = np.unique(train.run)
    if runs.size < 2:
        raise ValueError(f"the hierarchical transfer model needs at least 2 training runs (sessions); the "
                         f"training data hold {runs.size}. Use [uq] transfer = \"loro\" or \"off\".")
    eff, dropped = select_effects(train, fit, effects, min_runs=min(MIN_INFORMING_RUNS, runs.size))
    if not eff:
        eff = ("O",) if "O" in fit.model.param_names else ()
    if method not in ("laplace", "nuts"):
        raise ValueError(f"method {method!r} is not known; it must be 'laplace' or 'nuts'.")
    drop = [e for e in dropped if e not in eff]
    withins = [uninformed_within(train, fit, drop, a) if within_uninformed else {} for a in range(3)]
    jac = _jacobian(fit, train) if weak is not None else None
    weaks = [weak_directions(train, fit, eff, a, weak, J=jac) if weak is not None else {} for a in range(3)]
    designs = [(w, {r: np.round(W, 12).tobytes() for r, W in v.items()}) for w, v in zip(withins, weaks)]
    post = None
    for a0 in [a for a in range(3) if designs[a] not in designs[:a]]:       # one fit per distinct design
        w = withins[a0]
        stats = run_stats(train, fit, eff, within=w, shared=shared, directions=weaks[a0])
        if method == "laplace":
            part = fit_laplace(stats, fit.model.param_names, level=level, seed=seed, likelihood=likelihood, df=df, **kw)
        else:
            part = fit_nuts(stats, fit.model.param_names, fit, level=level, seed=seed, likelihood=likelihood, df=df,
                            **kw)
        post = part if post is None else _take_axes(post, part, [a for a in range(3) if designs[a] == designs[a0]])
    uninformed = (UNINFORMED if PRIOR_FOR_UNINFORMED else "fixed") if uninformed is None else uninformed
    if uninformed not in UNINFORMED_CHOICES:
        raise ValueError(f"uninformed = {uninformed!r} must be one of {list(UNINFORMED_CHOICES)}.")
    if uninformed == "fixed":
        return post
    prior = [e for e in effects if e in dropped and e not in eff]
    if uninformed == "pooled":
        q = len(post.effects)
        mom = (post.w_mean[:, :q].mean(axis=1), np.diagonal(post.w_cov[:, :q, :q], axis1=1, axis2=2).mean(axis=1))
        return with_prior_effects(post, fit, train, prior, moments=mom)
    return with_prior_effects(post, fit, train, prior, kw.get("tau_scale", TAU_PRIOR_SCALE))


def _take_axes(post: SessionPosterior, part: SessionPosterior, axes: Sequence[int]) -> SessionPosterior:
    """``post`` with the output ``axes`` taken from ``part`` (the same effects; a fit of another design)."""
    ax = list(axes)
    arrays = {}
    for k in ("w_mean", "w_cov", "mu_cov", "scale", "mu", "df_weight", "mix_w_mean", "mix_w_cov", "df_log_evidence"):
        if getattr(post, k) is None or getattr(part, k) is None:     # the learned dof's arrays: only with it
            continue
        v = np.array(getattr(post, k))
        v[ax] = getattr(part, k)[ax]
        arrays[k] = v
    ess = tuple(part.ess[a] if a in ax else e for a, e in enumerate(post.ess)) if post.ess and part.ess else post.ess
    return dataclasses.replace(post, ess=ess, **arrays)


#: Carry the candidate effects too few runs inform (:func:`with_prior_effects`) instead of taking them as fixed.
PRIOR_FOR_UNINFORMED = True
#: How: ``"pooled"`` (exchangeable with the learned effects of the axis: their mean second moments),
#: ``"prior"`` (the half-normal prior's) or ``"fixed"`` (not carried: no change between sessions).
UNINFORMED_CHOICES = ("pooled", "prior", "fixed")
UNINFORMED = "pooled"


def with_prior_effects(post: SessionPosterior, fit, train, names: Sequence[str],
                       tau_scale: float = TAU_PRIOR_SCALE, moments=None) -> SessionPosterior:
    r"""Add the random effects ``names`` that the training runs cannot inform, with their prior.

    A parameter that fewer than :data:`MIN_INFORMING_RUNS` runs sweep (e.g. the x gain on Belsten, with
    the run that sweeps the x field left out) is seen by the others as a constant, confounded with the
    offset: its session-to-session change *at the training runs' inputs* is already in the learned
    offset spread, and nothing in the data says how it changes elsewhere. Taking it as fixed between
    sessions (zero variance) is the strongest possible assumption; the Bayesian answer is the prior,
    :math:`\tau_j \sim \mathrm{HalfNormal}(s_\tau)`, so :math:`E\tau_j^2 = s_\tau^2` and
    :math:`\mathrm{Var}\,\tau_j^2 = 2 s_\tau^4`, acting on the scaled Jacobian column measured from its
    training mean :math:`\bar f_j` (the part at the training inputs is the offset's): the row's variance
    gains :math:`s_\tau^2 (f_j - \bar f_j)^2`, zero where the training runs sat and growing as the row
    moves along the unswept input.

    ``moments``: ``(mean, var)`` of :math:`\tau_j^2`, (3,) each, to use instead of the prior's: the job's
    default (``uninformed = "pooled"``) takes the effects of one axis as exchangeable (their sds drawn
    from one distribution, as the sessions are), so an effect no run informs gets the mean posterior
    moments of the axis's learned ones (on Belsten: the offset's), each row's variance gaining
    :math:`E[\tau_O^2] (f_j - \bar f_j)^2`.
    """
    names = [e for e in names if e not in post.effects]
    if not names:
        return post
    if post.df_grid:       # learned dof: every dof's posterior carries them (with its own dof), then re-pooled
        return _pool_components(post, [with_prior_effects(c, fit, train, names, tau_scale, moments)
                                       for c in post.components()])
    param = list(fit.model.param_names)
    idx = [param.index(e) for e in names]
    f = _jacobian(fit, train)[:, :, idx] / post.scale[:, None, idx]          # (3, n, k)
    k, q = len(idx), len(post.effects)
    if moments is None:
        t2 = np.full(3, tau_scale**2 * (post.df / (post.df - 2) if math.isfinite(post.df) else 1.0))
        v2 = 2 * t2**2
    else:
        t2, v2 = (np.broadcast_to(np.asarray(m, np.float64), (3,)) for m in moments)
    w_mean = np.concatenate([post.w_mean[:, :q], np.repeat(t2[:, None], k, axis=1), post.w_mean[:, q:]], axis=1)
    w_cov = np.zeros((3, q + k + 1, q + k + 1))
    keep = np.r_[np.arange(q), q + k]
    w_cov[:, keep[:, None], keep[None, :]] = post.w_cov
    w_cov[:, q + np.arange(k), q + np.arange(k)] = v2[:, None]
    centre = np.concatenate([np.zeros((3, q)) if post.centre is None else post.centre, f.mean(axis=1)], axis=1)
    return dataclasses.replace(post, w_mean=w_mean, w_cov=w_cov, effects=tuple(post.effects) + tuple(names),
                               effect_index=tuple(post.effect_index) + tuple(idx), centre=centre,
                               prior_only=tuple(post.prior_only) + tuple(names))


def loro_elpd(stats: RunStats, names, *, pooling: str = "partial", seed: int = 0,
              tau_scale: float = TAU_PRIOR_SCALE) -> np.ndarray:
    """Leave-one-run-out log predictive density of every run's rows (jointly, AR(1) and effects integrated), (R, 3).

    ``pooling``: ``"partial"`` (the hierarchical model), ``"complete"`` (no random effects: one set of
    parameters for every session) or ``"none"`` (every session its own effects, unconstrained; a new
    session is predicted by the empirical mixture of the training sessions' fitted effects).
    Each fold refits on the other runs (Laplace; ``mu`` and the effects integrated, the hyperparameters
    by the mean density over the Laplace draws).
    """
    R = stats.n.size
    out = np.zeros((R, 3))
    q = stats.effects.size
    for k in range(R):
        keep = np.arange(R) != k
        tr, te = stats.select(keep), stats.select(np.array([k]))
        sub = tr if pooling != "complete" else tr._replace(effects=stats.effects[:0])
        if pooling == "none":
            out[k] = _elpd_none(tr, te)
            continue
        post, modes = fit_laplace(sub, names, seed=seed, return_modes=True, draws=200, tau_scale=tau_scale)
        out[k] = _elpd_fold(sub, te, modes, seed)
    return out


def _elpd_fold(tr: RunStats, te: RunStats, modes, seed) -> np.ndarray:
    """log mean over Laplace draws of p(y_left | h): mu ~ N(mu_hat(h), C(h)) and the effects integrated."""
    rng = np.random.default_rng(seed)
    q = tr.effects.size
    res = np.zeros(3)
    for a in range(3):
        args = (jnp.asarray(tr.m0[a]), jnp.asarray(tr.m1[a]), jnp.asarray(tr.m2[a]), jnp.asarray(tr.first[a]),
                jnp.asarray(tr.n), jnp.asarray(tr.effects), TAU_PRIOR_SCALE, SIGMA_PRIOR_SCALE)
        Hh = np.asarray(_hessian(jnp.asarray(modes[a]), *args, reml=REML))
        w, V = np.linalg.eigh(0.5 * (Hh + Hh.T))
        hs = rng.multivariate_normal(modes[a], (V / np.maximum(w, MIN_CURVATURE)) @ V.T, size=200, method="eigh")
        lp = np.asarray(_fold_lp(jnp.asarray(hs), *args, jnp.asarray(te.m0[a, 0]), jnp.asarray(te.m1[a, 0]),
                                 jnp.asarray(te.m2[a, 0]), jnp.asarray(te.first[a, 0]), float(te.n[0])))
        lp = lp[np.isfinite(lp)]
        res[a] = np.logaddexp.reduce(lp) - np.log(lp.size)
    return res


@jax.jit
def _fold_lp(hs, m0, m1, m2, first, n, effects, ts, ss, t0, t1, t2, tf, tn):
    q = effects.shape[0]
    p = m0.shape[-1] - 1

    def one(h):
        _, mu, cov = _collapsed(h, m0, m1, m2, first, n, effects, ts, ss)
        tau, sigma, rho = _unpack(h, q)
        re = jnp.zeros((p, p)).at[effects, effects].set(tau**2)
        L = jnp.linalg.cholesky(cov + re + 1e-12 * jnp.eye(p))
        G = whitened_gram(t0, t1, t2, tf, rho)
        return run_loglik(G, tn, mu, L, sigma**2, rho)

    return jax.vmap(one)(hs)


def _elpd_none(tr: RunStats, te: RunStats) -> np.ndarray:
    """No pooling: per-session effects fitted freely (shared parameters and AR(1) noise by GLS at the
    complete-pooling noise estimate); the new session's density is the mean over the training sessions'
    fitted effects, all plugged in (their estimation uncertainty is left out: no pooling has no model of it)."""
    res = np.zeros(3)
    q = tr.effects.size
    R = tr.n.size
    for a in range(3):
        sub = tr._replace(effects=tr.effects[:0])
        _, modes = fit_laplace(sub, (), draws=50, return_modes=True)
        h = modes[a]
        sigma, rho = float(np.exp(h[0])), float(np.tanh(h[1]))
        G = np.asarray(whitened_gram(tr.m0[a], tr.m1[a], tr.m2[a], tr.first[a], rho))      # (R, p+1, p+1)
        p = G.shape[-1] - 1
        # joint GLS: shared theta (p) and free effects (R x q), with the effects' mean fixed at 0 by
        # the constraint sum_r u_r = 0 (their mean is part of the shared theta)
        eidx = tr.effects
        dim = p + R * q
        A = np.zeros((dim, dim))
        b = np.zeros(dim)
        for r in range(R):
            gxx, gxy = G[r, :p, :p], G[r, :p, p]
            sl = slice(p + r * q, p + (r + 1) * q)
            Sx = np.zeros((p, dim))
            Sx[:, :p] = np.eye(p)
            Sx[eidx, sl] = np.eye(q)
            A += Sx.T @ gxx @ Sx
            b += Sx.T @ gxy
        C = np.zeros((q, dim))
        for r in range(R):
            C[:, p + r * q:p + (r + 1) * q] = np.eye(q)
        KKT = np.block([[A, C.T], [C, np.zeros((q, q))]])
        sol = np.linalg.lstsq(KKT, np.r_[b, np.zeros(q)], rcond=None)[0][:dim]
        theta, u = sol[:p], sol[p:].reshape(R, q)
        Gt = np.asarray(whitened_gram(te.m0[a, 0], te.m1[a, 0], te.m2[a, 0], te.first[a, 0], rho))
        lps = []
        for r in range(R):
            th = theta.copy()
            th[eidx] += u[r]
            lps.append(float(run_loglik(jnp.asarray(Gt), float(te.n[0]), jnp.asarray(th), jnp.zeros((p, 0)),
                                        sigma**2, rho)))
        res[a] = np.logaddexp.reduce(lps) - np.log(R)
    return res


#: Fewer training runs than this leave the between-session sds mostly to their prior: the job warns.
FEW_RUNS = 6
#: The check against leave-one-run-out (:func:`misfit_axes`): the session model's new-session sd (rms transfer sd over
#: the training rows and the residual sd combined) may be at most this many times loro's. A round factor, not fitted:
#: the Belsten run-axes it names are 2.4-111x (151x with temperature_quadratic); on the eight simulated generators
#: (15 draws each) it names none, their widths 0.71-1.58x loro's (docs/sessions.md, "The check against ...").
MISFIT_RATIO = 2.0
#: ``[uq] transfer_check``: what the job does on an axis :func:`misfit_axes` names (settings.TRANSFER_CHECKS).
TRANSFER_CHECKS = ("loro", "warn")


def misfit_axes(sd, loro_sd, s2) -> np.ndarray:
    """(3,) bool: the axes whose new-session sd under the session model, ``sqrt(sd^2 + s2)`` (``sd``: its
    root-mean-square transfer sd over the training rows, ``s2``: the fit's residual variance), exceeds
    :data:`MISFIT_RATIO` times the same under leave-one-run-out, ``sqrt(loro_sd^2 + s2)``: intervals more than
    twice as wide as the held-out runs support. The job warns on them and (``transfer_check = "loro"``) uses
    leave-one-run-out's sd there. (Until this round the rule compared the transfer sds alone, ``sd > 2 loro_sd``
    and ``sd^2 > s2``: on simulated campaigns whose loro sd is small against the residual it named axes whose
    intervals were only 1.1-1.4x loro's, 6 of 16 draws; docs/sessions.md.)"""
    sd, loro, s2 = (np.asarray(v, float) for v in (sd, loro_sd, s2))
    return np.sqrt(sd**2 + s2) > MISFIT_RATIO * np.sqrt(loro**2 + s2)


def hierarchical_transfer(train, fit, *, method: str = "laplace", level: float = 0.95, seed: int = 0,
                          effects: Sequence[str] = DEFAULT_EFFECTS, likelihood: str = "gaussian", df: float | str = 4.0,
                          uninformed: str | None = None, series=None, check: str = "loro"):
    """The job's ``[uq] transfer = "hierarchical"``: ``(TransferEstimate, SessionPosterior or None)``.

    The estimate's ``sd`` is the root-mean-square row-dependent transfer sd over the training rows (a
    summary for reports; predictions use the rows' own). With fewer than 2 runs it falls back to
    :func:`~bayesmag._src.core.predictor.estimate_transfer` (its warning) and no session model. With 3 or more it
    also reports leave-one-run-out's sd (``loro_sd``) and warns on an axis whose sd exceeds :data:`MISFIT_RATIO`
    times that and the axis's residual sd (unmodelled physics read as session change: run ``bayesmag discover``).
    ``check`` (``[uq] transfer_check``): ``"loro"`` (default) gives such an axis leave-one-run-out's constant sd
    instead of the model's (the model failed a check against held-out runs: its spread is more than twice what
    they show; docs/sessions.md, "The check against leave-one-run-out"), ``"warn"`` keeps the model's and only warns.
    ``series``: ``(recording, train_index)``: a model whose rows depend on their neighbours (a thermal lag) is
    linearised on the training rows within the recording, as it was fitted (:data:`_SERIES`).
    """
    token = _SERIES.set(None if series is None else (train, series[0], np.asarray(series[1])))
    try:
        return _hierarchical_transfer(train, fit, method=method, level=level, seed=seed, effects=effects,
                                      likelihood=likelihood, df=df, uninformed=uninformed, series=series,
                                      check=check)
    finally:
        _SERIES.reset(token)


def _hierarchical_transfer(train, fit, *, method, level, seed, effects, likelihood, df, uninformed, series, check):
    from bayesmag._src.core.predictor import TransferEstimate, estimate_transfer

    if check not in TRANSFER_CHECKS:
        raise ValueError(f"check = {check!r} must be one of {list(TRANSFER_CHECKS)}.")
    bound = [t.name for t in fit.model.terms if getattr(t, "localised", None) == "run"]     # run_offset
    if bound:
        raise ValueError(f"the hierarchical transfer models every run's offset as a random effect; the model's "
                         f"{', '.join(bound)} fits offsets of particular runs as fixed parameters, which the random "
                         f"effects would duplicate. Drop {bound[0]} from the physics extra terms, or use "
                         f"transfer = \"loro\".")
    runs = np.unique(train.run)
    if runs.size < 2:                       # no spread between sessions to learn: loro's fallback, said so
        tr = estimate_transfer(train, fit, series=series)
        note = (f"transfer = \"hierarchical\" was asked for, but the training data hold {runs.size} run "
                f"(session): the session model needs at least 2 and was not fitted. ")
        return dataclasses.replace(tr, warning=note + (tr.warning or "")), None
    post = fit_sessions(train, fit, method=method, effects=effects, level=level, seed=seed, likelihood=likelihood,
                        df=df, uninformed=uninformed)
    sd = np.sqrt(np.mean(post.transfer_sd_for(fit, train) ** 2, axis=0))
    warnings = []
    if runs.size < FEW_RUNS:
        warnings.append(f"The training data hold {runs.size} runs (sessions): the between-session sds of the "
                        f"hierarchical transfer model are then poorly determined (their prior, half-normal with scale "
                        f"{TAU_PRIOR_SCALE} uT, weighs as much as the few runs), and new-session intervals are wide. "
                        f"Record at least {FEW_RUNS} sessions.")
    dropped = select_effects(train, fit, effects)[1]
    weak = weak_directions(train, fit, [e for e in post.effects if e not in post.prior_only])     # as fit_sessions
    summary = {**post.as_dict(), "dropped_effects_informing_runs": dropped,
               "weak_directions_per_run": {str(r): int(W.shape[1]) for r, W in weak.items()}}
    if runs.size >= 3:
        loro = estimate_transfer(train, fit, level=level, series=series).sd
        summary["loro_sd"] = {ax: float(v) for ax, v in zip(AXES, loro)}
        big = list(np.flatnonzero(misfit_axes(sd, loro, fit.s2)))
        summary["check"] = {"rule": f"sqrt(model rms transfer sd^2 + residual variance) > {MISFIT_RATIO:g}x "
                                    "sqrt(loro sd^2 + residual variance)", "action": check,
                            "failed_axes": [AXES[a] for a in big],
                            "model_rms_sd": {ax: float(v) for ax, v in zip(AXES, sd)}}
        if big:
            tot = lambda v, a: float(np.sqrt(v**2 + fit.s2[a]))   # noqa: E731  new-session sd with the residual
            said = ", ".join(f"{sd[a]:.3g} uT on {AXES[a]} (with the residual sd {tot(sd[a], a):.3g} uT, "
                             f"{tot(sd[a], a) / tot(loro[a], a):.1f}x leave-one-run-out's {tot(loro[a], a):.3g})"
                             for a in big)
            causes = ("Three known causes (docs/sessions.md, Limits), each read as session change: physics that every "
                      "session shares but the model lacks (run `bayesmag discover` on the training data and put the "
                      "terms it names in [physics] extra_terms); runs that leave field directions unswept beyond what "
                      "the model sets aside as reading noise (a second posterior mode); and one run whose level the "
                      "model does not fit together with the others' (such as the only heated run, when no other run "
                      "sweeps that axis).")
            if check == "loro":
                fb = np.full(3, np.nan)
                fb[big] = loro[big]
                post = dataclasses.replace(post, fallback_sd=tuple(float(v) for v in fb))
                sd = np.where(np.isnan(fb), sd, fb)
                warnings.append(
                    f"The hierarchical transfer sd is {said}: the session model failed its check against the held-out "
                    f"runs on {', '.join(AXES[a] for a in big)}, and there the new-session intervals use "
                    f"leave-one-run-out's constant sd instead (no row dependence on that axis; [uq] transfer_check = "
                    f"\"warn\" keeps the model's). " + causes)
            else:
                warnings.append(f"The hierarchical transfer sd is {said}. " + causes
                                + " Compare with [uq] transfer = \"loro\" before using these intervals.")
    warning = " ".join(warnings) or None
    return (TransferEstimate(sd, f"hierarchical_{post.method}",
                             {"model": summary, "conditions": condition_table(post, fit, train)}, warning), post)


def condition_table(post: SessionPosterior, fit, train) -> list[dict]:
    """The row-dependent transfer sd at the corners of the training domain, for the certificate.

    Conditions: measured field at the training rows' per-axis minimum, at zero (clipped into the training
    range) and at the per-axis maximum, each at the lowest and the highest training temperature (6 rows).
    Returns ``[{"field": [bx, by, bz], "temperature": T, "transfer_sd": {axis: sd}}, ...]`` (uT, C).

    Example: ``condition_table(post, fit, train)[0]["transfer_sd"]["x"]``.
    """
    from bayesmag._src.core.data import CalibrationData

    lo, hi = train.b_meas.min(axis=0), train.b_meas.max(axis=0)
    fields = [lo, np.clip(np.zeros(3), lo, hi), hi]
    temps = [float(train.temperature.min()), float(train.temperature.max())]
    b = np.array([f for _ in temps for f in fields], np.float64)
    t = np.repeat(temps, len(fields))
    rows = CalibrationData(b, t, None, np.arange(t.size, dtype=np.float64), np.zeros(t.size, int))
    sd = post.transfer_sd_for(fit, rows)
    return [{"field": [float(v) for v in b[i]], "temperature": float(t[i]),
             "transfer_sd": {ax: float(sd[i, a]) for a, ax in enumerate(AXES)}} for i in range(t.size)]


def posterior_from_artifact(meta, arrays: dict, param_names: Sequence[str]) -> SessionPosterior:
    """The :class:`SessionPosterior` a calibration saved (``meta``: its JSON table, ``arrays``: ``sessions/*``
    without the prefix), every field checked; ValueError names the field, the bad value and that the file is damaged."""
    if not isinstance(meta, dict):
        raise ValueError(f"field 'sessions' must be a table; got {meta!r}.")
    p = len(param_names)
    effects = meta.get("effects")
    if not isinstance(effects, list) or not effects or any(e not in param_names for e in effects):
        raise ValueError(f"field 'sessions.effects' = {effects!r} must name parameters of the model {list(param_names)}.")
    q = len(effects)
    prior_only = meta.get("prior_only", [])
    if not isinstance(prior_only, list) or any(e not in effects for e in prior_only):
        raise ValueError(f"field 'sessions.prior_only' = {prior_only!r} must list some of sessions.effects.")
    level, n_runs = meta.get("level"), meta.get("n_runs")
    if isinstance(level, bool) or not isinstance(level, (int, float)) or not 0 < level < 1:
        raise ValueError(f"field 'sessions.level' = {level!r} must be a number in (0, 1).")
    if isinstance(n_runs, bool) or not isinstance(n_runs, int) or n_runs < 2:
        raise ValueError(f"field 'sessions.n_runs' = {n_runs!r} must be an integer >= 2.")
    if meta.get("method") not in ("laplace", "nuts"):
        raise ValueError(f"field 'sessions.method' = {meta.get('method')!r} must be 'laplace' or 'nuts'.")
    shapes = {"w_mean": (3, q + 1), "w_cov": (3, q + 1, q + 1), "mu_cov": (3, p, p), "scale": (3, p), "mu": (3, p)}
    out = {}
    for k, shape in shapes.items():
        if k not in arrays:
            raise ValueError(f"array 'sessions/{k}' is missing.")
        v = np.asarray(arrays[k])
        if v.shape != shape or v.dtype.kind != "f" or not np.isfinite(v).all():
            raise ValueError(f"array 'sessions/{k}' must be finite floats of shape {shape}; got {v.dtype} {v.shape}.")
        out[k] = v.astype(np.float64)
    centre = None
    if "centre" in arrays:
        centre = np.asarray(arrays["centre"])
        if centre.shape != (3, q) or centre.dtype.kind != "f" or not np.isfinite(centre).all():
            raise ValueError(f"array 'sessions/centre' must be finite floats of shape {(3, q)}; got {centre.dtype} "
                             f"{centre.shape}.")
        centre = centre.astype(np.float64)
    if (out["w_mean"] < 0).any() or (out["scale"] <= 0).any():
        raise ValueError("array 'sessions/w_mean' or 'sessions/scale' is negative (variances and scales are >= 0).")
    for k in ("w_cov", "mu_cov"):
        m = out[k]
        if not np.allclose(m, np.swapaxes(m, 1, 2), rtol=1e-8, atol=1e-300) or \
                (np.linalg.eigvalsh(m).min(axis=1) < -1e-8 * np.abs(m).max(axis=(1, 2))).any():
            raise ValueError(f"array 'sessions/{k}' is not a stack of symmetric positive semi-definite matrices.")
    lik, df = meta.get("likelihood", "gaussian"), meta.get("df")
    if lik not in LIKELIHOODS:
        raise ValueError(f"field 'sessions.likelihood' = {lik!r} must be one of {list(LIKELIHOODS)}.")
    if lik in ("gaussian", "laplace") and df is not None:
        raise ValueError(f"field 'sessions.df' = {df!r} must be null for the {lik} likelihood.")
    learned = lik == "student_t" and df == LEARNED
    if lik == "student_t" and not learned and (isinstance(df, bool) or not isinstance(df, (int, float))
                                               or not 2 < df < math.inf):
        raise ValueError(f"field 'sessions.df' = {df!r} must be a number > 2 or {LEARNED!r} for the Student-t "
                         "likelihood.")
    mix = {}
    if learned:
        grid = meta.get("df_grid")
        if not isinstance(grid, list) or not grid or any(
                not (g is None or not isinstance(g, bool) and isinstance(g, (int, float)) and 2 < g < math.inf)
                for g in grid) or len(set(grid)) != len(grid):
            raise ValueError(f"field 'sessions.df_grid' = {grid!r} must list distinct dofs > 2 (null: the Gaussian "
                             "limit) for a learned dof.")
        K = len(grid)
        for k, shape in (("df_weight", (3, K)), ("mix_w_mean", (3, K, q + 1)), ("mix_w_cov", (3, K, q + 1, q + 1))):
            v = np.asarray(arrays.get(k, np.zeros(0)))
            if k not in arrays or v.shape != shape or v.dtype.kind != "f" or not np.isfinite(v).all():
                raise ValueError(f"array 'sessions/{k}' must be finite floats of shape {shape}; got "
                                 f"{v.dtype} {v.shape}.")
            mix[k] = v.astype(np.float64)
        if (mix["df_weight"] < 0).any() or not np.allclose(mix["df_weight"].sum(1), 1.0, atol=1e-9):
            raise ValueError("array 'sessions/df_weight' must hold weights >= 0 summing to 1 per axis.")
        m = mix["mix_w_cov"]
        if (mix["mix_w_mean"] < 0).any() or not np.allclose(m, np.swapaxes(m, -1, -2), rtol=1e-8, atol=1e-300) or \
                (np.linalg.eigvalsh(m).min(axis=-1) < -1e-8 * np.abs(m).max(axis=(-2, -1))).any():
            raise ValueError("array 'sessions/mix_w_mean' or 'sessions/mix_w_cov' is not variance moments "
                             "(means >= 0, symmetric positive semi-definite covariances).")
        mix["df_grid"] = tuple(math.inf if g is None else float(g) for g in grid)
    fb = meta.get("fallback_sd")
    if fb is not None:
        if not isinstance(fb, list) or len(fb) != 3 or any(
                not (v is None or not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and v >= 0)
                for v in fb):
            raise ValueError(f"field 'sessions.fallback_sd' = {fb!r} must list 3 values, each a transfer sd >= 0 (uT) "
                             "or null (the model's own).")
        mix["fallback_sd"] = tuple(math.nan if v is None else float(v) for v in fb)
    idx = tuple(list(param_names).index(e) for e in effects)
    return SessionPosterior(out["w_mean"], out["w_cov"], out["mu_cov"], out["scale"], tuple(effects), float(level),
                            int(n_runs), meta["method"], out["mu"], effect_index=idx,
                            df=float(df) if lik == "student_t" and not learned else math.inf, centre=centre,
                            prior_only=tuple(prior_only), laplace=lik == "laplace", **mix)
