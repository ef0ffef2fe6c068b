"""Monte-Carlo DropConnect inference: :func:`mc_predict` (one network or an ensemble, moments pooled exactly) and :func:`mc_samples`."""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bayesmag._src.core.network.spec import NetworkSpec
from bayesmag._src.core.network.model import apply, embed, head_distribution
from bayesmag._src.core.network.train import ResidualNetwork
from bayesmag._src.core.network.ensemble import NetworkEnsemble, ensemble_passes

__all__ = ['MCPrediction', 'pool_mc', 'mc_predict', 'mc_samples']


class MCPrediction(NamedTuple):
    """MC-DropConnect residual prediction in uT, each ``(n, A)``.

    ``mean``: mean over passes of the family mean; ``aleatoric``: sqrt of the mean over passes
    of the family variance; ``epistemic``: sd over passes of the family mean (ddof 1);
    ``shape``: the family's shape fields averaged over passes (Student-t ``df``), else empty.
    """

    mean: np.ndarray
    aleatoric: np.ndarray
    epistemic: np.ndarray
    shape: dict

    @property
    def total(self) -> np.ndarray:
        return np.sqrt(self.aleatoric**2 + self.epistemic**2)



def _mc_raw(spec: NetworkSpec, params, x, key, passes: int):
    """Per-pass family means, variances and shape fields, each ``(M, n, A)`` (standardised units)."""
    n_axes = jax.tree.leaves(params)[0].shape[0]
    keys = jax.random.split(key, (passes, n_axes))

    def one_pass_one_axis(p, k):
        dist = head_distribution(spec, apply(p, x, k, dropconnect=spec.dropconnect, activation=spec.activation))
        shape = {f.name: jnp.broadcast_to(getattr(dist, f.name), dist.batch_shape)
                 for f in dataclasses.fields(dist) if f.name not in ("loc", "scale")}
        return dist.mean, dist.variance, shape

    per_axis = jax.vmap(one_pass_one_axis, in_axes=(0, 0), out_axes=-1)            # over axes -> (n, A)
    return jax.vmap(per_axis, in_axes=(None, 0))(params, keys)                      # over passes -> (M, n, A)



_mc_passes = functools.partial(jax.jit, static_argnames=("spec", "passes"))(_mc_raw)



@functools.partial(jax.jit, static_argnames=("spec", "passes"))
def _mc_axes(spec: NetworkSpec, params, x, key, passes: int):
    means, variances, shapes = _mc_raw(spec, params, x, key, passes)
    mean = jnp.mean(means, axis=0)
    epi = jnp.sum(jnp.square(means - mean), axis=0) / (passes - 1)
    alea = jnp.mean(variances, axis=0)
    return mean, alea, epi, {k: jnp.mean(v, axis=0) for k, v in shapes.items()}



def pool_mc(parts: list[MCPrediction], counts) -> MCPrediction:
    """The :class:`MCPrediction` of all passes together, from each member's (``parts[k]`` over ``counts[k]``
    passes), exactly: mean of all pass means; aleatoric variance the mean over all passes of the family
    variance; epistemic variance the sample variance (ddof 1) of all pass means, i.e.
    ``(sum_k (m_k - 1) e_k^2 + sum_k m_k (mu_k - mu)^2) / (M - 1)``; shape fields averaged over all passes.
    A member's recalibration factor (:func:`recalibrate`) scales its own variances (as :func:`mc_predict`
    does); the spread between member means is not scaled."""
    m = np.asarray(counts, np.float64)[:, None, None]
    total = float(m.sum())
    mu = np.stack([p.mean for p in parts])
    mean = np.sum(m * mu, axis=0) / total
    alea = np.sum(m * np.stack([p.aleatoric for p in parts]) ** 2, axis=0) / total
    ss = np.sum((m - 1) * np.stack([p.epistemic for p in parts]) ** 2 + m * np.square(mu - mean), axis=0)
    shape = {k: np.sum(m * np.stack([p.shape[k] for p in parts]), axis=0) / total for k in parts[0].shape}
    return MCPrediction(mean, np.sqrt(alea), np.sqrt(ss / (total - 1)), shape)



def mc_predict(net: ResidualNetwork | NetworkEnsemble, x: np.ndarray, *, passes: int, seed: int = 0) -> MCPrediction:
    """``passes`` DropConnect forward passes of every axis network on inputs ``x`` ``(n, n_in)``.

    Pass ``t`` of axis ``a`` uses one weight mask for all rows. Returns means and sds in uT.
    A :class:`NetworkEnsemble` splits the passes over its members (:func:`ensemble_passes`; member ``k``
    from ``seed + k``) and pools all of them (:func:`pool_mc`).
    """
    if isinstance(net, NetworkEnsemble):
        counts = ensemble_passes(passes, len(net.members))
        return pool_mc([mc_predict(m, x, passes=c, seed=seed + k) for k, (m, c) in enumerate(zip(net.members, counts))],
                       counts)
    if passes < 2:
        raise ValueError(f"passes = {passes} must be at least 2 (the epistemic "
                          "variance is a sample variance over passes).")
    st = net.standardizer
    mean, alea, epi, shape = jax.device_get(_mc_axes(net.spec.compiled_key(), net.params, embed(st.x(x), net.frequencies),
                                                         jax.random.key(seed), passes))
    return _mc_in_units(net, mean, alea, epi, shape)


def _mc_in_units(net: ResidualNetwork, mean, alea, epi, shape) -> MCPrediction:
    """The :class:`MCPrediction` in uT from :func:`_mc_axes`' standardised moments (recalibration factor applied)."""
    st = net.standardizer
    rs = st.r_scale
    if net.variance_scale is not None:
        rs_var = rs * np.sqrt(np.asarray(net.variance_scale, np.float64))
    else:
        rs_var = rs
    mean = np.asarray(mean, np.float64) * rs + st.r_mean
    alea = np.sqrt(np.asarray(alea, np.float64)) * rs_var
    epi = np.sqrt(np.asarray(epi, np.float64)) * rs_var
    return MCPrediction(mean, alea, epi, {k: np.asarray(v, np.float64) for k, v in shape.items()})



def mc_samples(net: ResidualNetwork, x: np.ndarray, *, passes: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The raw passes of :func:`mc_predict` (same masks): family means and variances ``(M, n, A)`` in uT
    (without a recalibration factor). For checks and plots; :func:`mc_predict` reduces them on device."""
    st = net.standardizer
    means, variances, _ = jax.device_get(_mc_passes(net.spec.compiled_key(), net.params,
                                                    embed(st.x(x), net.frequencies), jax.random.key(seed), passes))
    return (np.asarray(means, np.float64) * st.r_scale + st.r_mean,
            np.asarray(variances, np.float64) * st.r_scale**2)

