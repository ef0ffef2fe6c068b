"""The network itself: dense layers, DropConnect masks, the forward pass, Fourier input features and the family head and loss."""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

from bayesmag._src.core.likelihoods import Likelihood
from bayesmag._src.core.network.spec import ACTIVATIONS, DTYPE, FOURIER_STREAM, NetworkSpec

__all__ = ['Dense', 'Params', 'init', 'DROP_TAIL', 'max_drops', 'keep_masks', 'drop_connect', 'apply', 'fourier_frequencies', 'embed', 'head_distribution', 'regularized_nll']


class Dense(NamedTuple):
    """One affine layer ``x @ w + b``; ``w`` is ``(in, out)``."""

    w: jax.Array
    b: jax.Array



Params = tuple[Dense, ...]



def init(key: jax.Array, n_in: int, n_out: int, *, hidden_layers: int, width: int) -> Params:
    """Glorot-uniform weights, zero biases (float32); ``hidden_layers`` layers of ``width`` units.

    Example:
        >>> p = init(jax.random.key(0), 4, 2, hidden_layers=2, width=8)
        >>> [layer.w.shape for layer in p]
        [(4, 8), (8, 8), (8, 2)]
    """
    sizes = [n_in] + [width] * hidden_layers + [n_out]
    keys = jax.random.split(key, len(sizes) - 1)
    layers = []
    for k, (a, b) in zip(keys, zip(sizes[:-1], sizes[1:])):
        lim = math.sqrt(6.0 / (a + b))
        layers.append(Dense(jax.random.uniform(k, (a, b), DTYPE, -lim, lim), jnp.zeros((b,), DTYPE)))
    return tuple(layers)



#: Probability that a mask needs more drops than :func:`max_drops` allows (then the last ones are lost).
DROP_TAIL = 2.0**-40



@functools.lru_cache(maxsize=None)
def max_drops(n: int, rate: float) -> int:
    """Smallest ``k`` with ``P(Binomial(n, rate) > k) <= DROP_TAIL`` (scipy), the static drop budget."""
    return int(scipy.stats.binom.isf(DROP_TAIL, n, rate)) + 1



def keep_masks(key: jax.Array, shapes: tuple[tuple[int, ...], ...], rate: float) -> tuple[jax.Array, ...]:
    r"""Independent Bernoulli(1 - ``rate``) boolean masks of the given shapes from one key.

    The weights of all shapes are numbered :math:`0..n-1`; the dropped positions of a
    Bernoulli(``rate``) process are the partial sums of i.i.d. geometric gaps
    (Devroye 1986, *Non-Uniform Random Variate Generation*, sec. 10.3), so a mask costs
    :data:`max_drops` draws and one scatter instead of ``n`` draws: at the paper's rate 0.01
    about 190 draws for 12.9k weights, which halves the training time on CPU. The masks are
    exact Bernoulli masks unless more than :func:`max_drops` weights would drop
    (probability :data:`DROP_TAIL`); for ``rate`` above 1/8 the mask is drawn per weight.
    """
    sizes = [math.prod(shape) for shape in shapes]
    n = sum(sizes)
    if rate <= 0.0:
        flat = jnp.ones((n,), bool)
    elif rate > 0.125:
        flat = jax.random.bernoulli(key, 1.0 - rate, (n,))
    else:
        return masks_from_drops(drop_positions(key, n, rate), shapes)
    return _split_flat(flat, shapes)


def drop_positions(key: jax.Array, n: int, rate: float) -> jax.Array:
    """``(max_drops(n, rate),)`` int32: the dropped positions of :func:`keep_masks`' geometric path
    (``0 < rate <= 1/8``; positions ``>= n`` drop nothing). Drawn apart from the masks so that training can
    draw every minibatch's positions of an epoch in one vmapped call (:func:`masks_from_drops` per step)."""
    # gaps - 1 ~ Geometric(rate) on {0, 1, ...} by inversion, in float64 where enabled so that
    # a floor never flips between differently fused programs (the chunked training's invariance)
    u = jax.random.uniform(key, (max_drops(n, rate),), jnp.float64, minval=jnp.finfo(jnp.float64).tiny)
    gaps = jnp.minimum(jnp.floor(jnp.log(u) / math.log1p(-rate)), n) + 1   # capped: no int32 overflow
    return jnp.cumsum(gaps.astype(jnp.int32)) - 1


def masks_from_drops(dropped: jax.Array, shapes: tuple[tuple[int, ...], ...]) -> tuple[jax.Array, ...]:
    """The boolean keep masks of ``shapes`` with the positions ``dropped`` (:func:`drop_positions`) off."""
    n = sum(math.prod(shape) for shape in shapes)
    return _split_flat(jnp.ones((n,), bool).at[dropped].set(False, mode="drop"), shapes)


def _split_flat(flat: jax.Array, shapes: tuple[tuple[int, ...], ...]) -> tuple[jax.Array, ...]:
    sizes = [math.prod(shape) for shape in shapes]
    return tuple(part.reshape(shape) for part, shape in zip(jnp.split(flat, np.cumsum(sizes)[:-1]), shapes))


def uses_drop_positions(rate: float) -> bool:
    """Whether :func:`keep_masks` draws ``rate``'s masks by :func:`drop_positions` (the geometric path)."""
    return 0.0 < rate <= 0.125



def drop_connect(params: Params, key: jax.Array, rate: float) -> Params:
    """Params with every weight matrix masked by Bernoulli(1 - rate) and scaled by 1/(1 - rate).

    Biases are left alone. ``rate = 0`` returns ``params`` unchanged. Masks: :func:`keep_masks`.
    """
    if rate == 0.0:
        return params
    return _masked(params, keep_masks(key, tuple(layer.w.shape for layer in params), rate), rate)


def _masked(params: Params, masks: tuple[jax.Array, ...], rate: float) -> Params:
    """``params`` with every weight matrix where ``masks`` keep it, scaled by 1/(1 - rate), else 0."""
    out = []
    for mask, layer in zip(masks, params):
        w = layer.w
        out.append(Dense(jnp.where(mask, w * jnp.asarray(1.0 / (1.0 - rate), w.dtype), jnp.zeros((), w.dtype)),
                         layer.b))
    return tuple(out)



def apply(params: Params, x: jax.Array, key: jax.Array | None = None, *, dropconnect: float = 0.0,
          activation: str = "relu", dropped: jax.Array | None = None) -> jax.Array:
    """Raw head ``(..., n_out)`` for inputs ``x`` ``(..., n_in)``; one DropConnect mask from ``key``.

    ``key=None`` (or ``dropconnect=0``) evaluates the network with its expected weights. ``dropped``
    instead of ``key``: the mask's dropped positions, drawn beforehand (``drop_positions(key, ...)``: the same
    mask as ``key`` gives).
    """
    if dropped is not None:
        params = _masked(params, masks_from_drops(dropped, tuple(layer.w.shape for layer in params)), dropconnect)
    elif key is not None:
        params = drop_connect(params, key, dropconnect)
    act = ACTIVATIONS[activation]
    h = x
    for layer in params[:-1]:
        h = act(h @ layer.w + layer.b)
    last = params[-1]
    return h @ last.w + last.b



def fourier_frequencies(spec: NetworkSpec, seed: int) -> np.ndarray:
    """The fixed ``(n_in, fourier_features)`` frequency matrix ``B ~ N(0, fourier_scale^2)`` of seed ``seed``.

    Drawn once from ``fold_in(key(seed), FOURIER_STREAM)`` and never trained (Tancik et al. 2020).
    """
    key = jax.random.fold_in(jax.random.key(seed), FOURIER_STREAM)
    b = jax.random.normal(key, (spec.n_in, spec.fourier_features), jnp.float32)
    return np.asarray(b, np.float64) * spec.fourier_scale



def embed(z: jax.Array, frequencies: np.ndarray | None) -> jax.Array:
    r"""Random Fourier input features :math:`[z, \sin(2\pi zB), \cos(2\pi zB)]` (``z`` standardised).

    ``frequencies`` ``(n_in, m)``; ``None`` or ``m = 0`` returns ``z`` unchanged (the paper's MLP).

    Example:
        >>> embed(jnp.zeros((2, 4)), np.ones((4, 3))).shape
        (2, 10)
    """
    if frequencies is None or frequencies.shape[-1] == 0:
        return z
    a = (2.0 * np.pi) * (z @ jnp.asarray(frequencies, z.dtype))
    return jnp.concatenate([z, jnp.sin(a), jnp.cos(a)], axis=-1)



def head_distribution(spec: NetworkSpec, raw: jax.Array) -> Likelihood:
    """The family member for raw head outputs ``(..., n_out)`` (standardised units, epsilon added)."""
    cls = spec.family
    dist = cls.from_head(raw, log_scale_clip=spec.log_scale_clip, **spec.fixed_shape)
    if spec.epsilon == 0.0:
        return dist
    scale = jnp.sqrt(jnp.square(dist.scale) + jnp.asarray(spec.epsilon, raw.dtype))
    return dataclasses.replace(dist, scale=scale)



def regularized_nll(spec: NetworkSpec, raw: jax.Array, r: jax.Array, weight: jax.Array | None = None) -> jax.Array:
    r"""Weighted mean of ``nll + lambda * (log s^2)^2`` over rows (the training loss of sec. 2.4)."""
    dist = head_distribution(spec, raw)
    ls2 = spec.family.head_log_scale2(raw, log_scale_clip=spec.log_scale_clip)
    per = dist.nll(r) + jnp.asarray(spec.log_scale_l2, raw.dtype) * jnp.square(ls2)
    if weight is None:
        return jnp.mean(per)
    return jnp.sum(weight * per) / jnp.maximum(jnp.sum(weight), 1.0)

