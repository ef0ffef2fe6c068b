"""Variance recalibration of a trained network on held-out rows (:func:`recalibrate`)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from bayesmag._src.core.network.train import ResidualNetwork
from bayesmag._src.core.network.infer import mc_predict

__all__ = ['RECALIBRATION_GRID', 'recalibrate']


#: Grid of variance factors searched by :func:`recalibrate` (log-spaced, 1/20 to 20).
RECALIBRATION_GRID = np.exp(np.linspace(np.log(0.05), np.log(20.0), 601))



def recalibrate(net: ResidualNetwork, x_val: np.ndarray, r_val: np.ndarray, *, passes: int,
                seed: int = 0) -> ResidualNetwork:
    r"""``net`` with a per-axis variance factor :math:`c_a` fitted on held-out rows.

    The MC-DropConnect predictive of the residual, the family moment-matched to
    :math:`(\mu, c_a(\sigma^2_{alea} + \sigma^2_{epi}))`, has its mean NLL on ``(x_val, r_val)``
    minimised over :data:`RECALIBRATION_GRID` (for the Gaussian the optimum is
    :math:`c = \overline{(r-\mu)^2/\sigma^2}`; Levi et al. 2022). Both variance parts are
    scaled, so the aleatoric/epistemic split is kept. Use rows the network was not fitted on
    (its validation rows); with ``validation = "time_blocks"`` they stand for new stretches
    of time.

    References:
        Levi, D., Gispan, L., Giladi, N. & Fetaya, E. (2022). Evaluating and calibrating
        uncertainty prediction in regression tasks. Sensors 22(15), 5540.
    """
    from bayesmag._src.core.likelihoods import moment_match

    base = mc_predict(net._replace(variance_scale=None), x_val, passes=passes, seed=seed)
    var = base.aleatoric**2 + base.epistemic**2
    r_val = np.asarray(r_val, np.float64)
    shape = net.spec.shape_for(base.shape)
    c = RECALIBRATION_GRID[:, None, None]
    dist = moment_match(net.spec.likelihood, base.mean[None], c * var[None],
                        **{k: np.asarray(v)[None] if np.ndim(v) else v for k, v in shape.items()})
    nll = np.asarray(dist.nll(jnp.asarray(r_val[None]))).mean(axis=1)          # (grid, A)
    return net._replace(variance_scale=RECALIBRATION_GRID[np.argmin(nll, axis=0)])

