r"""Heteroscedastic residual network with Monte-Carlo DropConnect (Shetty & Marndi 2026, sec. 2.4).

One small MLP per field axis maps the standardised inputs :math:`x = (B_{meas}, T)` to the
raw head of a predictive family (:mod:`bayesmag.likelihoods`) for the physics residual
:math:`r = B_{ref} - \bar y_{phys}(x)`. Everything here is a pure function of pytrees:

* ``params`` is a tuple of :class:`Dense` layers (``w`` of shape ``(in, out)``, ``b`` of
  shape ``(out,)``), float32; :func:`init` makes them and :func:`apply` evaluates them;
* DropConnect (Wan et al. 2013) multiplies every weight *matrix* (not the biases, not the
  activations) by an independent Bernoulli(1 - p) mask scaled by ``1/(1-p)``, so the
  expected weights are the trained ones. One mask is drawn per minibatch step in training
  and one per forward pass at inference, shared by all rows of that pass (a pass is one
  draw of the weights from the approximate posterior; Mobiny et al. 2021).
  ``key=None`` gives the deterministic network with the expected weights;
* training (:func:`fit_residual_network`) is one jit-compiled program per axis, run in
  chunks of epochs (progress between them): the epoch loop is a :func:`jax.lax.while_loop`
  and the minibatch loop inside it a :func:`jax.lax.scan`; the axes run on threads over the
  cores there are (the same numbers for any count). Minibatches are reshuffled every epoch
  from a seeded key; a final short batch is padded with zero-weight rows.

Optional random Fourier input features (``fourier_features = m > 0``; not in the paper): the
standardised inputs ``z`` are extended to :math:`[z, \sin(2\pi zB), \cos(2\pi zB)]` with a fixed
``(n_in, m)`` matrix :math:`B \sim N(0, \sigma^2)` (``sigma = fourier_scale``) drawn from the
network seed (Tancik et al. 2020). A ReLU MLP on raw inputs learns smooth functions first
(spectral bias); the embedding lets it fit sharper structure in the residual. On a random row
split of an autocorrelated recording that sharper structure is mostly interpolation between
time neighbours, so it helps there far more than on held-out stretches of time
(``docs/hybrid.md``); it is off by default.

Loss (sec. 2.4), on the *standardised* residual :math:`\tilde r = (r - m_r)/s_r`:

.. math::  L(\phi) = \frac1N\sum_i \Big[-\log p(\tilde r_i \mid \mu_i, s_i)
           + \lambda\,(\log s_i^2)^2\Big],\qquad
           s_i^2 = \exp(\mathrm{clip}(h_{i,1}, lo, hi)) + \epsilon

with ``p`` the family density (Gaussian, Laplace or Student-t), ``lambda = log_scale_l2``,
``(lo, hi) = log_scale_clip`` and ``epsilon`` added to the squared scale. For the Gaussian
this is the paper's loss up to a factor 2 and a constant. Because the residual is scaled
to unit variance, ``log_scale_clip`` and the penalty act on the log of the scale relative to
the residual's training sd (the paper's raw-unit clip [-10, 3] uT^2 would put the x axis
residual variance, ~6e-4 uT^2, near the middle of the range too); inputs are standardised
by the fitting rows' mean and sd.

Early stopping (sec. 3.6): after every epoch the validation loss (the same regularised loss,
deterministic network) is compared with the best so far; an improvement of more than
``min_delta`` resets the patience counter, ``patience`` epochs without one stop training,
and the best weights are returned. A non-finite training or validation loss stops
training at once; the weights of the best finite epoch are kept and the epoch is
reported as ``TrainInfo.nan_epoch`` (-1 when none).

Monte-Carlo DropConnect inference (:func:`mc_predict`, sec. 2.4): for ``M`` passes with
independent masks, per row,

.. math::  \mu = \tfrac1M\sum_t \mu^{(t)},\quad
           \sigma^2_{alea,NN} = \tfrac1M\sum_t \mathrm{Var}^{(t)},\quad
           \sigma^2_{epi,NN} = \tfrac1{M-1}\sum_t (\mu^{(t)} - \mu)^2

where :math:`\mu^{(t)}` and :math:`\mathrm{Var}^{(t)}` are the family mean and variance of
pass ``t`` (Student-t: :math:`s^2\nu/(\nu-2)`; Laplace: :math:`2b^2`), mapped back to uT.

Deep ensemble x MC DropConnect (:class:`NetworkEnsemble`, e.g. the job's K cross-conformal fold
networks): the ``M`` passes are split over the ``K`` members (:func:`ensemble_passes`: ``M // K``
each, the first ``M mod K`` members one more, at least 2 each; member ``k`` draws its masks from
``seed + k``), so inference costs about one network's. The moments above are then taken over all ``M`` passes of
all members, exactly (:func:`pool_mc`): the epistemic variance is the sample variance of all
pass means, i.e. the within-member spread plus the spread between the members' means.

Size rule: a network whose parameter count per axis exceeds ``MAX_PARAMS_PER_ROW`` (10)
times the number of fitting rows (training rows minus the validation rows) is refused with
a ``ValueError`` naming ``width`` / ``hidden_layers`` (the job reports it as a config error): the
paper's 4 x 64 network (12.9k weights) needs at least 1.3k fitting rows. Fewer than
``MIN_VALIDATION_ROWS`` (20) validation rows make early stopping a coin toss and are refused
naming ``network.validation_fraction``.

References:
    Shetty & Marndi (2026). Metrology 6(3), 45, sections 2.4 and 3.6.
    Wan, L., Zeiler, M., Zhang, S., LeCun, Y. & Fergus, R. (2013). Regularization of neural
    networks using DropConnect. ICML.
    Tancik, M. et al. (2020). Fourier features let networks learn high frequency functions in
    low dimensional domains. NeurIPS.
    Mobiny, A. et al. (2021). DropConnect is effective in modeling uncertainty of Bayesian
    deep networks. Scientific Reports 11, 5458.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import threading
from concurrent.futures import Executor, ThreadPoolExecutor
from typing import Any, Callable, Mapping, NamedTuple, Union

import jax
import jax.numpy as jnp
import numpy as np
import optax
import scipy.stats

from bayesmag._src.core.likelihoods import LIKELIHOODS, Likelihood, ShapeParam, get_likelihood

__all__ = ["Dense", "NetworkSpec", "Standardizer", "TrainInfo", "ResidualNetwork", "MCPrediction",
           "ACTIVATIONS", "MAX_PARAMS_PER_ROW", "MIN_VALIDATION_ROWS", "init", "apply", "drop_connect", "keep_masks", "max_drops",
           "count_params", "fourier_frequencies", "embed", "head_distribution", "regularized_nll", "build_trainer",
           "validation_rows", "TrainProgress", "TRAIN_CHUNK_EPOCHS", "progress_bar", "merge_progress", "merged_reporter", "LEARN", "shape_settings",
           "check_network_size", "fit_residual_network", "mc_predict", "mc_samples", "recalibrate", "VALIDATION_KINDS",
           "NetworkEnsemble", "ensemble_passes", "pool_mc"]

DTYPE = jnp.float32

#: A network may have at most this many parameters per axis for every fitting row.
MAX_PARAMS_PER_ROW = 10
#: Early stopping needs at least this many validation rows.
MIN_VALIDATION_ROWS = 20
#: How validation rows are chosen from the training rows (``network.validation``).
VALIDATION_KINDS = ("random", "time_blocks")
#: ``fold_in`` stream of the Fourier frequency matrix (the axis networks use streams 0, 1, 2, ...).
FOURIER_STREAM = 0x46465431

ACTIVATIONS: dict[str, Callable[[jax.Array], jax.Array]] = {
    "relu": jax.nn.relu, "tanh": jnp.tanh, "gelu": jax.nn.gelu, "silu": jax.nn.silu, "elu": jax.nn.elu,
}


def shape_settings() -> dict[str, tuple[str, ShapeParam, str]]:
    """``{setting: (setting, ShapeParam, family)}`` for every family shape field fixed by a spec setting."""
    return {p.setting: (p.setting, p, cls.name) for cls in LIKELIHOODS.values()
            for p in cls.shape_params.values() if p.setting is not None}


class Dense(NamedTuple):
    """One affine layer ``x @ w + b``; ``w`` is ``(in, out)``."""

    w: jax.Array
    b: jax.Array


Params = tuple[Dense, ...]


# --------------------------------------------------------------------------- the network


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


def count_params(n_in: int, n_out: int, *, hidden_layers: int, width: int) -> int:
    """Number of weights and biases of :func:`init`'s network."""
    sizes = [n_in] + [width] * hidden_layers + [n_out]
    return sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))


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
        # gaps - 1 ~ Geometric(rate) on {0, 1, ...} by inversion, in float64 where enabled so that
        # a floor never flips between differently fused programs (the chunked training's invariance)
        u = jax.random.uniform(key, (max_drops(n, rate),), jnp.float64, minval=jnp.finfo(jnp.float64).tiny)
        gaps = jnp.minimum(jnp.floor(jnp.log(u) / math.log1p(-rate)), n) + 1   # capped: no int32 overflow
        dropped = jnp.cumsum(gaps.astype(jnp.int32)) - 1
        flat = jnp.ones((n,), bool).at[dropped].set(False, mode="drop")
    return tuple(part.reshape(shape) for part, shape in zip(jnp.split(flat, np.cumsum(sizes)[:-1]), shapes))


def drop_connect(params: Params, key: jax.Array, rate: float) -> Params:
    """Params with every weight matrix masked by Bernoulli(1 - rate) and scaled by 1/(1 - rate).

    Biases are left alone. ``rate = 0`` returns ``params`` unchanged. Masks: :func:`keep_masks`.
    """
    if rate == 0.0:
        return params
    masks = keep_masks(key, tuple(layer.w.shape for layer in params), rate)
    out = []
    for mask, layer in zip(masks, params):
        w = layer.w
        out.append(Dense(jnp.where(mask, w * jnp.asarray(1.0 / (1.0 - rate), w.dtype), jnp.zeros((), w.dtype)),
                         layer.b))
    return tuple(out)


def apply(params: Params, x: jax.Array, key: jax.Array | None = None, *, dropconnect: float = 0.0,
          activation: str = "relu") -> jax.Array:
    """Raw head ``(..., n_out)`` for inputs ``x`` ``(..., n_in)``; one DropConnect mask from ``key``.

    ``key=None`` (or ``dropconnect=0``) evaluates the network with its expected weights.
    """
    if key is not None:
        params = drop_connect(params, key, dropconnect)
    act = ACTIVATIONS[activation]
    h = x
    for layer in params[:-1]:
        h = act(h @ layer.w + layer.b)
    last = params[-1]
    return h @ last.w + last.b


# --------------------------------------------------------------------------- spec and loss


#: ``student_t_df``-style settings take a number (fixed) or this word (learned by the head).
LEARN = "learn"


@dataclasses.dataclass(frozen=True)
class NetworkSpec:
    """All settings of a residual network, its training and its MC inference: the one settings type.

    The job's ``[network]`` table is this type plus the job's own switches
    (:class:`bayesmag._src.app.config.NetworkConfig`), so names and defaults are written once, here.
    Frozen and hashable: the compiled training takes it as a static argument (with the fields
    that do not change the compiled program -- ``seed``, ``validation*``, ``recalibrate``,
    ``mc_passes`` -- normalised away, so new seeds do not recompile).

    ``likelihood`` names a family of :data:`bayesmag.likelihoods.LIKELIHOODS`. A family shape
    field with a ``setting`` (Student-t ``df``: ``student_t_df``) is fixed at that number or
    learned by the head with ``"learn"`` (``None`` is read as ``"learn"``). ``lr_plateau_factor
    < 1`` multiplies the learning rate by that factor after ``lr_plateau_patience`` epochs
    without a validation improvement (floor ``lr_min_factor * learning_rate``); the default 1
    keeps the paper's constant rate (on the real data a factor 0.5 every 20 epochs changed the
    test RMSE by less than the spread over seeds). ``validation_fraction`` / ``validation``
    choose the early-stopping rows (:func:`validation_rows`), ``recalibrate`` fits a variance
    factor on them (:func:`recalibrate`), ``mc_passes`` is the number of MC-DropConnect passes.

    Raises:
        ValueError: a setting outside its valid set, naming the setting, the value and the set.
    """

    likelihood: str = "gaussian"
    hidden_layers: int = 4
    width: int = 64
    activation: str = "relu"
    dropconnect: float = 0.01
    learning_rate: float = 5e-4
    batch_size: int = 16
    max_epochs: int = 1000
    patience: int = 50
    min_delta: float = 1e-6
    validation_fraction: float = 0.1
    log_scale_clip: tuple = (-10.0, 3.0)   # on the log of the squared scale of the standardised residual
    log_scale_l2: float = 1e-4
    epsilon: float = 1e-6
    student_t_df: Union[float, str] = 4.0   # a number > 2, or "learn"
    mc_passes: int = 100
    lr_plateau_factor: float = 1.0
    lr_plateau_patience: int = 20
    lr_min_factor: float = 1e-3
    fourier_features: int = 0             # m > 0: add m random Fourier features of the inputs (not in the paper)
    fourier_scale: float = 1.0            # sd of their frequencies, per standardised input unit
    validation: str = "random"            # "random" (paper) | "time_blocks" (one block per run)
    recalibrate: bool = False             # fit a variance factor per axis on the validation rows (NLL)
    seed: int = 0
    n_in: int = 4

    def __post_init__(self):
        if self.student_t_df is None:
            object.__setattr__(self, "student_t_df", LEARN)
        clip = self.log_scale_clip
        if not isinstance(clip, (list, tuple)) or len(clip) != 2:
            raise ValueError(f"log_scale_clip = {clip!r} must be [low, high] with low < high.")
        object.__setattr__(self, "log_scale_clip", tuple(float(v) for v in clip))
        if self.likelihood not in LIKELIHOODS:
            raise ValueError(f"likelihood {self.likelihood!r} is not known; it must be one of {sorted(LIKELIHOODS)}.")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation = {self.activation!r} is not valid; it must be one of {sorted(ACTIVATIONS)}.")
        if self.validation not in VALIDATION_KINDS:
            raise ValueError(f"validation = {self.validation!r} is not valid; it must be one of "
                             f"{list(VALIDATION_KINDS)}.")
        checks = [
            ("hidden_layers", self.hidden_layers >= 1, "at least 1"),
            ("width", self.width >= 1, "at least 1"),
            ("dropconnect", 0.0 <= self.dropconnect < 1.0, "in [0, 1)"),
            ("learning_rate", self.learning_rate > 0, "positive"),
            ("batch_size", self.batch_size >= 1, "at least 1"),
            ("max_epochs", self.max_epochs >= 1, "at least 1"),
            ("patience", self.patience >= 1, "at least 1"),
            ("min_delta", self.min_delta >= 0, "non-negative"),
            ("validation_fraction", 0.0 < self.validation_fraction < 1.0, "in (0, 1)"),
            ("log_scale_l2", self.log_scale_l2 >= 0, "non-negative"),
            ("epsilon", self.epsilon >= 0, "non-negative"),
            ("mc_passes", self.mc_passes >= 2, "at least 2 (the epistemic variance is a sample variance "
                                               "over passes)"),
            ("lr_plateau_factor", 0.0 < self.lr_plateau_factor <= 1.0, "in (0, 1]"),
            ("lr_plateau_patience", self.lr_plateau_patience >= 1, "at least 1"),
            ("lr_min_factor", 0.0 < self.lr_min_factor <= 1.0, "in (0, 1]"),
            ("fourier_features", self.fourier_features >= 0, "a count >= 0 (0: the plain MLP)"),
            ("fourier_scale", self.fourier_scale > 0, "positive"),
        ]
        for key, ok, what in checks:
            if not ok:
                raise ValueError(f"{key} = {getattr(self, key)!r} must be {what}.")
        lo, hi = self.log_scale_clip
        if not lo < hi:
            raise ValueError(f"log_scale_clip = {list(self.log_scale_clip)} must be [low, high] with low < high.")
        for field, param in shape_settings().items():
            value = getattr(self, param[0])
            if value != LEARN:
                param[1].check(param[0], value, param[2])

    @classmethod
    def from_config(cls, net: Any, likelihood: str) -> "NetworkSpec":
        """The spec of one likelihood from settings sharing its field names (``[network]``)."""
        kw = {f.name: getattr(net, f.name) for f in dataclasses.fields(cls)
              if f.name not in ("likelihood", "n_in") and hasattr(net, f.name)}
        return cls(likelihood=likelihood, **kw)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "NetworkSpec":
        """The spec saved as a plain dict (``to_dict``); reads the pre-0.2 name ``df`` (``None``: learned).

        Raises:
            KeyError: a setting this version does not know (names them).
        """
        d = dict(d)
        if "df" in d:
            df = d.pop("df")
            d.setdefault("student_t_df", LEARN if df is None else df)
        unknown = set(d) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise KeyError(f"unknown network settings {sorted(unknown)}")
        return cls(**d)

    def to_dict(self) -> dict:
        """Plain-JSON settings (``log_scale_clip`` as a list)."""
        d = dataclasses.asdict(self)
        d["log_scale_clip"] = list(d["log_scale_clip"])
        return d

    @property
    def family(self) -> type[Likelihood]:
        return get_likelihood(self.likelihood)

    @property
    def fixed_shape(self) -> dict[str, float]:
        """The family's shape fields held fixed by a setting (Student-t ``df`` unless ``"learn"``)."""
        out = {}
        for field, param in self.family.shape_params.items():
            if param.setting is None:
                if param.head is None:
                    out[field] = float(param.default)
                continue
            value = getattr(self, param.setting)
            if value != LEARN:
                out[field] = float(value)
        return out

    @property
    def df(self) -> float | None:
        """The fixed Student-t degrees of freedom, ``None`` when learned (``student_t_df``)."""
        return None if self.student_t_df == LEARN else float(self.student_t_df)

    def shape_for(self, learned: Mapping[str, Any]) -> dict[str, Any]:
        """Shape fields for moment matching: the fixed ones, else the per-row ``learned`` values."""
        fixed = self.fixed_shape
        return {f: fixed[f] if f in fixed else learned[f] for f in self.family.shape_names()}

    def compiled_key(self) -> "NetworkSpec":
        """This spec with the settings that do not enter the compiled training reset (a jit key)."""
        return dataclasses.replace(self, validation_fraction=0.1, validation="random", recalibrate=False,
                                   mc_passes=100, seed=0)

    @property
    def n_out(self) -> int:
        return self.family.n_head_params(**self.fixed_shape)

    @property
    def n_features(self) -> int:
        """Width of the MLP's input: the ``n_in`` standardised inputs plus ``2 * fourier_features``."""
        return self.n_in + 2 * self.fourier_features

    @property
    def n_params(self) -> int:
        """Trained weights and biases per axis (the fixed Fourier frequencies are not counted)."""
        return count_params(self.n_features, self.n_out, hidden_layers=self.hidden_layers, width=self.width)


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


# --------------------------------------------------------------------------- training


class TrainInfo(NamedTuple):
    """What training did, per axis when vmapped (leading axis 3).

    ``epochs_run``: epochs completed; ``best_epoch``: epoch (0-based) of the returned weights,
    -1 if no epoch had a finite validation loss (the initial weights are returned);
    ``nan_epoch``: epoch whose loss was non-finite (training stopped there), -1 if none;
    ``train_loss`` / ``val_loss``: per-epoch losses, ``nan`` after the last epoch run.
    """

    epochs_run: jax.Array
    best_epoch: jax.Array
    best_val_loss: jax.Array
    nan_epoch: jax.Array
    train_loss: jax.Array
    val_loss: jax.Array


class TrainState(NamedTuple):
    params: Params
    opt_state: Any
    key: jax.Array
    epoch: jax.Array
    best_params: Params
    best_loss: jax.Array
    best_epoch: jax.Array
    wait: jax.Array
    plateau: jax.Array
    nan_epoch: jax.Array
    train_loss: jax.Array
    val_loss: jax.Array


def shuffle_rounds(n: int) -> int:
    """Sort rounds of ``jax.random.permutation(key, n)``: ``ceil(3 ln n / ln(2^32 - 1))`` (JAX's ``_shuffle``)."""
    return int(np.ceil(3 * np.log(max(1, int(n))) / np.log(np.iinfo(np.uint32).max)))


def masked_permutation(key: jax.Array, n, size: int, rounds) -> jax.Array:
    """``(size,)``: ``jax.random.permutation(key, n)`` for a traced ``n <= size``, then ``n .. size-1``.

    The same algorithm as JAX's (``rounds = shuffle_rounds(n)`` stable sorts by fresh 32-bit keys), with the
    padding elements sorted last in every round, so the real elements meet the same random bits at the same
    positions: under the partitionable threefry (``jax_threefry_partitionable``, JAX's default) the bits of a
    longer shape start with those of a shorter one (``tests/test_network_batch.py`` checks it).
    """
    x = jnp.arange(size)
    for r in range(shuffle_rounds(size)):
        key, sub = jax.random.split(key)
        bits = jax.random.bits(sub, (size,), jnp.uint32)
        _, _, xs = jax.lax.sort(((x >= n).astype(jnp.int32), bits, x), num_keys=2)
        x = jnp.where(r < rounds, xs, x)
    return x


class _Trainer(NamedTuple):
    init_state: Callable      # (params, key) -> TrainState
    epoch: Callable           # (state, x_fit, r_fit, x_val, r_val) -> state after one epoch
    running: Callable         # state -> bool: not stopped (max_epochs, patience, non-finite loss)
    info: Callable            # state -> TrainInfo
    masked_epoch: Callable    # (state, x_fit, r_fit, n_fit, x_val, r_val, n_val, rounds) -> state (padded rows)


def _trainer(spec: NetworkSpec) -> _Trainer:
    """The pieces of the training loop of one axis (pure, traceable; see :func:`build_trainer`)."""
    opt = optax.inject_hyperparams(optax.adam)(learning_rate=spec.learning_rate)
    bs = spec.batch_size
    lr_min = spec.learning_rate * spec.lr_min_factor

    def loss_fn(params, key, xb, rb, wb):
        raw = apply(params, xb, key, dropconnect=spec.dropconnect, activation=spec.activation)
        return regularized_nll(spec, raw, rb, wb)

    grad_fn = jax.value_and_grad(loss_fn)

    def init_state(params, key):
        nan_hist = jnp.full((spec.max_epochs,), jnp.nan, DTYPE)
        return TrainState(params=params, opt_state=opt.init(params), key=key, epoch=jnp.asarray(0),
                          best_params=params, best_loss=jnp.asarray(jnp.inf, DTYPE), best_epoch=jnp.asarray(-1),
                          wait=jnp.asarray(0), plateau=jnp.asarray(0), nan_epoch=jnp.asarray(-1),
                          train_loss=nan_hist, val_loss=nan_hist)

    def epoch(s: TrainState, x_fit, r_fit, x_val, r_val) -> TrainState:
        n = x_fit.shape[0]
        n_batches = -(-n // bs)
        pad = n_batches * bs - n
        weight = jnp.concatenate([jnp.ones((n,), DTYPE), jnp.zeros((pad,), DTYPE)]).reshape(n_batches, bs)

        def step(carry, batch):
            params, opt_state = carry
            idx, w, k = batch
            loss, g = grad_fn(params, k, x_fit[idx], r_fit[idx], w)
            updates, opt_state = opt.update(g, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), loss * jnp.sum(w)

        key, k_perm, k_steps = jax.random.split(s.key, 3)
        perm = jax.random.permutation(k_perm, n)
        idx = jnp.concatenate([perm, perm[:pad]]).reshape(n_batches, bs)
        step_keys = jax.random.split(k_steps, n_batches)
        (params, opt_state), losses = jax.lax.scan(step, (s.params, s.opt_state), (idx, weight, step_keys),
                                                   unroll=SCAN_UNROLL)
        train_loss = jnp.sum(losses) / n
        val = regularized_nll(spec, apply(params, x_val, activation=spec.activation), r_val)
        return finish(s, params, opt_state, key, train_loss, val)

    def masked_epoch(s: TrainState, x_fit, r_fit, n_fit, x_val, r_val, n_val, rounds) -> TrainState:
        """:func:`epoch` on the first ``n_fit`` of the padded fitting rows and ``n_val`` validation rows: the same
        permutation of the real rows (:func:`masked_permutation`), the same minibatches and keys, steps past the
        real rows' last minibatch left out (so it traces under ``vmap`` over recordings of different lengths)."""
        size = x_fit.shape[0]
        n_batches_max = -(-size // bs)
        p = jnp.arange(n_batches_max * bs)
        n_safe = jnp.maximum(n_fit, 1)
        key, k_perm, k_steps = jax.random.split(s.key, 3)
        perm = masked_permutation(k_perm, n_fit, size, rounds)
        src = jnp.minimum(jnp.where(p < n_fit, p, (p - n_fit) % n_safe), size - 1)   # a short last batch wraps
        idx = perm[src].reshape(n_batches_max, bs)
        weight = (p < n_fit).astype(DTYPE).reshape(n_batches_max, bs)
        active = jnp.arange(n_batches_max) < -(-n_fit // bs)
        step_keys = jax.random.split(k_steps, n_batches_max)   # a prefix is the unpadded epoch's keys

        def step(carry, batch):
            params, opt_state = carry
            idx, w, k, on = batch
            loss, g = grad_fn(params, k, x_fit[idx], r_fit[idx], w)
            updates, new_state = opt.update(g, opt_state, params)
            new = (optax.apply_updates(params, updates), new_state)
            return jax.tree.map(lambda a, b: jnp.where(on, a, b), new, carry), jnp.where(on, loss * jnp.sum(w), 0.0)

        (params, opt_state), losses = jax.lax.scan(step, (s.params, s.opt_state), (idx, weight, step_keys, active),
                                                   unroll=SCAN_UNROLL)
        train_loss = jnp.sum(losses) / n_safe
        wv = (jnp.arange(x_val.shape[0]) < n_val).astype(DTYPE)
        val = regularized_nll(spec, apply(params, x_val, activation=spec.activation), r_val, wv)
        return finish(s, params, opt_state, key, train_loss, val)

    def finish(s: TrainState, params, opt_state, key, train_loss, val) -> TrainState:
        """Early stopping, best weights, learning-rate plateau and loss history after one epoch."""
        finite = jnp.isfinite(train_loss) & jnp.isfinite(val)
        improved = finite & (val < s.best_loss - spec.min_delta)
        best_params = jax.tree.map(lambda new, old: jnp.where(improved, new, old), params, s.best_params)
        plateau = jnp.where(improved, 0, s.plateau + 1)
        reduce = plateau >= spec.lr_plateau_patience
        lr = opt_state.hyperparams["learning_rate"]
        lr = jnp.where(reduce, jnp.maximum(lr * spec.lr_plateau_factor, lr_min), lr).astype(lr.dtype)
        opt_state = opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": lr})
        return TrainState(
            params=params, opt_state=opt_state, key=key, epoch=s.epoch + 1, plateau=jnp.where(reduce, 0, plateau),
            best_params=best_params,
            best_loss=jnp.where(improved, val, s.best_loss),
            best_epoch=jnp.where(improved, s.epoch, s.best_epoch),
            wait=jnp.where(improved, 0, s.wait + 1),
            nan_epoch=jnp.where(finite, s.nan_epoch, s.epoch),
            train_loss=s.train_loss.at[s.epoch].set(train_loss),
            val_loss=s.val_loss.at[s.epoch].set(val),
        )

    def running(s: TrainState):
        return (s.epoch < spec.max_epochs) & (s.wait < spec.patience) & (s.nan_epoch < 0)

    def info(s: TrainState) -> TrainInfo:
        return TrainInfo(epochs_run=s.epoch, best_epoch=s.best_epoch, best_val_loss=s.best_loss,
                         nan_epoch=s.nan_epoch, train_loss=s.train_loss, val_loss=s.val_loss)

    return _Trainer(init_state, epoch, running, info, masked_epoch)


def build_trainer(spec: NetworkSpec) -> Callable[..., tuple[Params, TrainInfo]]:
    """``train(params, key, x_fit, r_fit, x_val, r_val) -> (best_params, TrainInfo)`` for one axis.

    Pure and traceable (wrap in ``jax.jit`` / ``jax.vmap``): Adam on
    :func:`regularized_nll` with one DropConnect mask per minibatch, reshuffled minibatches
    every epoch, early stopping with best-weight restore, stop at the first non-finite loss.
    Inputs are float32 and already standardised.
    """
    t = _trainer(spec)

    def train(params, key, x_fit, r_fit, x_val, r_val):
        s = jax.lax.while_loop(t.running, lambda s: t.epoch(s, x_fit, r_fit, x_val, r_val), t.init_state(params, key))
        return s.best_params, t.info(s)

    return train


#: Epochs per compiled call of the training loop: between calls :func:`fit_residual_network`
#: reports progress (epochs run, best validation loss per axis). The chunks run the same
#: epochs in the same order, so the trained weights depend on it only through float32 rounding.
TRAIN_CHUNK_EPOCHS = 25
#: Minibatch steps per iteration of the compiled step loop (``jax.lax.scan(unroll=...)``).
SCAN_UNROLL = 1


class TrainProgress(NamedTuple):
    """Where training stands after a chunk of epochs, per axis: ``epochs``, ``best_val_loss``,
    ``val_loss`` (of the last epoch run), ``done`` (stopped), and ``max_epochs``."""

    epochs: np.ndarray
    best_val_loss: np.ndarray
    val_loss: np.ndarray
    done: np.ndarray
    max_epochs: int


@functools.partial(jax.jit, static_argnames=("spec",))
def _init_axes(spec: NetworkSpec, keys):
    t = _trainer(spec)

    def one(key):
        k_init, k_train = jax.random.split(key)
        params = init(k_init, spec.n_features, spec.n_out, hidden_layers=spec.hidden_layers, width=spec.width)
        return t.init_state(params, k_train)

    return jax.vmap(one)(keys)


@functools.partial(jax.jit, static_argnames=("spec",))
def _train_chunk(spec: NetworkSpec, state: TrainState, stop, x_fit, r_fit, x_val, r_val):
    """Run every axis's training loop until it stops or reaches epoch ``stop`` (vmapped)."""
    t = _trainer(spec)

    def one(s, r_f, r_v):
        return jax.lax.while_loop(lambda s: t.running(s) & (s.epoch < stop),
                                  lambda s: t.epoch(s, x_fit, r_f, x_val, r_v), s)

    s = jax.vmap(one, in_axes=(0, 1, 1))(state, r_fit, r_val)
    return s, jax.vmap(t.running)(s)


@functools.partial(jax.jit, static_argnums=1)
def _axis_keys(seed, n: int):
    """The training key of each axis: ``fold_in(key(seed), a)`` for ``a < n``."""
    base = jax.random.key(seed)
    return jax.vmap(lambda a: jax.random.fold_in(base, a))(jnp.arange(n))


def _train_axes(spec: NetworkSpec, keys, x_fit, r_fit, x_val, r_val, *,
                progress: Callable[[TrainProgress], None] | None = None, chunk: int = TRAIN_CHUNK_EPOCHS):
    """Init + train one network per column of ``r_fit`` (vmapped), ``chunk`` epochs per compiled call.

    :func:`fit_residual_network` calls it with one column per thread (:func:`_train_parallel`).
    """
    spec = spec.compiled_key()
    s = _init_axes(spec, keys)
    stop = 0
    while stop < spec.max_epochs:
        stop = min(stop + chunk, spec.max_epochs)
        s, running = _train_chunk(spec, s, stop, x_fit, r_fit, x_val, r_val)
        running = np.asarray(running)
        if progress is not None:
            ep = np.asarray(s.epoch)
            last = np.asarray(s.val_loss)[np.arange(ep.size), np.maximum(ep - 1, 0)]
            progress(TrainProgress(ep, np.asarray(s.best_loss), last, ~running, spec.max_epochs))
        if not running.any():
            break
    t = _trainer(spec)
    return s.best_params, jax.vmap(t.info)(s)


def training_threads() -> int:
    """Threads :func:`fit_residual_network` trains the axes on: the cores this process may use, at
    most 3 (``BAYESMAG_TRAIN_THREADS`` overrides). The results do not depend on it."""
    env = os.environ.get("BAYESMAG_TRAIN_THREADS", "").strip()
    if env:
        return max(1, int(env))
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cores, 3))


def _train_parallel(spec: NetworkSpec, keys, x_fit, r_fit, x_val, r_val, *,
                    progress: Callable[[TrainProgress], None] | None = None, threads: int | None = None,
                    pool: Executor | None = None):
    """Every axis trained alone (:func:`_train_axes` on one column), the axes on ``threads`` threads.

    One compiled training of a 4 x 64 network on 16-row batches keeps one core busy; the axes run
    side by side on the cores there are (on the paper's data two threads finish the three axes in
    about the time of the longest). Each axis is the same compiled program with its own key and
    column, so the results are the same for any number of threads or cores, and an axis stops
    computing when it stops (a vmapped loop would compute it, masked, until the last one stops).
    Progress from the axes is merged under a lock. ``pool``: run the axes on this executor instead
    (shared by several trainings at once, e.g. the cross-conformal fold networks, so that they
    share the cores without oversubscribing them).
    """
    n_axes = r_fit.shape[1]
    threads = training_threads() if threads is None else threads
    report = merged_reporter(n_axes, 1, progress) if progress is not None else None   # waiting axes: epoch 0
    r_fit, r_val = np.asarray(r_fit), np.asarray(r_val)

    def run(a):
        return _train_axes(spec, keys[a:a + 1], x_fit, r_fit[:, a:a + 1], x_val, r_val[:, a:a + 1],
                           progress=None if report is None else lambda p: report(a, p))

    if pool is not None:
        parts = [f.result() for f in [pool.submit(run, a) for a in range(n_axes)]]
    elif threads < 2 or n_axes < 2:
        parts = [run(a) for a in range(n_axes)]
    else:
        with ThreadPoolExecutor(min(threads, n_axes), thread_name_prefix="bayesmag-train") as own:
            parts = list(own.map(run, range(n_axes)))
    join = lambda *leaves: np.concatenate([np.asarray(leaf) for leaf in leaves])   # noqa: E731
    params = jax.tree.map(lambda *leaves: jnp.asarray(join(*leaves)), *[p for p, _ in parts])
    info = jax.tree.map(join, *[i for _, i in parts])
    return params, info


def progress_bar(max_epochs: int, n_axes: int = 1, *,
                 desc: str = "network training") -> tuple[Callable[[TrainProgress], None], Any]:
    """A ``tqdm`` bar over ``n_axes`` trainings of at most ``max_epochs`` epochs each, fed by
    :class:`TrainProgress`: the epochs run, a stopped training counted as all its epochs (early
    stopping makes the rest unknown until it happens); the best validation loss per axis (up to 3
    axes) or how many have stopped."""
    from tqdm.auto import tqdm
    bar = tqdm(total=n_axes * max_epochs, desc=desc, unit="epoch", leave=False)

    def update(p: TrainProgress) -> None:
        bar.update(max(0, int(np.where(p.done, p.max_epochs, p.epochs).sum()) - bar.n))
        if p.done.size <= 3:
            bar.set_postfix_str("best val loss " + " ".join("-" if not np.isfinite(v) else f"{v:.4g}"
                                                             for v in p.best_val_loss))
        else:
            bar.set_postfix_str(f"{int(p.done.sum())} of {p.done.size} stopped")

    return update, bar


def merged_reporter(n_parts: int, n_axes: int, sink: Callable[[TrainProgress], None]) -> Callable[[int, TrainProgress], None]:
    """``report(k, p)`` for ``n_parts`` trainings of ``n_axes`` axes running on threads: keeps each one's
    latest :class:`TrainProgress` and passes ``sink`` all of them merged (:func:`merge_progress`), under a lock."""
    latest: list = [None] * n_parts
    lock = threading.Lock()

    def report(k: int, p: TrainProgress) -> None:
        with lock:
            latest[k] = p
            sink(merge_progress(latest, n_axes, p.max_epochs))

    return report


def merge_progress(parts: list, n_axes: int, max_epochs: int) -> TrainProgress:
    """One :class:`TrainProgress` of several trainings (``parts``: each one's latest, or None when it has
    not reported yet: counted as ``n_axes`` axes at epoch 0, not stopped)."""
    idle = TrainProgress(np.zeros(n_axes, int), np.full(n_axes, np.nan), np.full(n_axes, np.nan),
                         np.zeros(n_axes, bool), max_epochs)
    parts = [idle if q is None else q for q in parts]
    return TrainProgress(*(np.concatenate([getattr(q, f) for q in parts])
                           for f in ("epochs", "best_val_loss", "val_loss", "done")), max_epochs)


# --------------------------------------------------------------------------- fitted network


class Standardizer(NamedTuple):
    """Affine maps to the network's units: ``(x - x_mean)/x_scale`` and ``(r - r_mean)/r_scale``."""

    x_mean: np.ndarray
    x_scale: np.ndarray
    r_mean: np.ndarray
    r_scale: np.ndarray

    @classmethod
    def fit(cls, x: np.ndarray, r: np.ndarray) -> "Standardizer":
        def sd(a):
            s = np.std(a, axis=0)
            return np.where(s > 0, s, 1.0)
        return cls(np.mean(x, axis=0), sd(x), np.mean(r, axis=0), sd(r))

    def x(self, x: np.ndarray) -> jax.Array:
        return jnp.asarray((np.asarray(x, np.float64) - self.x_mean) / self.x_scale, DTYPE)

    def r(self, r: np.ndarray) -> jax.Array:
        return jnp.asarray((np.asarray(r, np.float64) - self.r_mean) / self.r_scale, DTYPE)


class ResidualNetwork(NamedTuple):
    """Trained per-axis residual networks: ``params`` stacked over axes (leading axis ``n_axes``)."""

    spec: NetworkSpec
    params: Params
    standardizer: Standardizer
    info: TrainInfo
    n_fit: int
    n_val: int
    frequencies: np.ndarray | None = None    # (n_in, fourier_features) fixed Fourier frequencies, or None
    variance_scale: np.ndarray | None = None  # (A,) factor on the MC variances from :func:`recalibrate`, or None
    val_rows: np.ndarray | None = None       # rows of the training inputs held out for early stopping

    def info_dict(self, axes: tuple[str, ...] = ("x", "y", "z")) -> dict:
        """Per-axis ``epochs_run``, ``best_epoch``, ``best_val_loss``, ``nan_epoch`` as plain Python."""
        out = {}
        for a, ax in enumerate(axes):
            out[ax] = {"epochs_run": int(self.info.epochs_run[a]), "best_epoch": int(self.info.best_epoch[a]),
                       "best_val_loss": float(self.info.best_val_loss[a]), "nan_epoch": int(self.info.nan_epoch[a])}
        return out


def validation_rows(n: int, fraction: float, *, seed: int, kind: str = "random",
                    groups: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Seeded ``(fit_rows, val_rows)`` of ``range(n)``; ``ValueError`` if val < ``MIN_VALIDATION_ROWS``.

    ``kind = "random"``: rows drawn at random (the paper). ``kind = "time_blocks"``: one
    contiguous block of ``fraction`` of the rows inside every group of ``groups`` (the run of
    each row, rows in time order), so early stopping and recalibration see rows whose time
    neighbours were not fitted.
    """
    if kind not in VALIDATION_KINDS:
        raise ValueError(f"validation = {kind!r} is not valid; it must be one of "
                          f"{list(VALIDATION_KINDS)}.")
    n_val = int(round(fraction * n))
    if not 0.0 < fraction < 1.0 or n_val < MIN_VALIDATION_ROWS or n - n_val < 1:
        raise ValueError(
            f"validation_fraction = {fraction} leaves {n_val} of {n} training rows for "
            f"validation; early stopping needs at least {MIN_VALIDATION_ROWS} (and some rows left to fit). "
            f"Raise it to at least {math.ceil(MIN_VALIDATION_ROWS / max(n, 1) * 1000) / 1000:g} or use more data.")
    if kind == "time_blocks":
        from bayesmag._src.core.data import split_time_blocks

        groups = np.zeros(n, int) if groups is None else np.asarray(groups)
        if groups.shape != (n,):
            raise ValueError(f"groups must have shape ({n},), got {groups.shape}")
        sp = split_time_blocks(groups, test_fraction=fraction, seed=seed)
        return sp.train, sp.test
    perm = np.random.default_rng(seed).permutation(n)
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])


def check_network_size(spec: NetworkSpec, n_fit: int) -> None:
    """``ValueError`` if the network has more than ``MAX_PARAMS_PER_ROW`` parameters per fitting row."""
    if spec.n_params > MAX_PARAMS_PER_ROW * n_fit:
        raise ValueError(
            f"The residual network ({spec.hidden_layers} hidden layers x {spec.width} units, {spec.n_params} "
            f"parameters per axis) is too large for {n_fit} fitting rows: at most {MAX_PARAMS_PER_ROW} parameters "
            f"per row ({MAX_PARAMS_PER_ROW * n_fit}). Lower 'width' or 'hidden_layers', "
            "or use more data.")
    if spec.batch_size > n_fit:
        raise ValueError(f"batch_size = {spec.batch_size} exceeds the {n_fit} fitting rows.")


def fit_residual_network(x: np.ndarray, r: np.ndarray, spec: NetworkSpec, *,
                         validation_fraction: float | None = None, seed: int | None = None,
                         validation: str | None = None, groups: np.ndarray | None = None,
                         progress: bool | Callable[[TrainProgress], None] = False,
                         pool: Executor | None = None) -> ResidualNetwork:
    """Train one network per column of the residuals ``r`` ``(n, A)`` on inputs ``x`` ``(n, n_in)``.

    A seeded ``validation_fraction`` of the rows is held out for early stopping (chosen as
    :func:`validation_rows` ``kind = validation`` with the rows' run ``groups``); inputs and
    residuals are standardised by the fitting rows' mean and sd. Axis ``a`` uses the key
    ``fold_in(key(seed), a)``, and each column trains alone (:func:`_train_parallel`: one compiled program
    for every axis, the axes on threads; the results do not depend on the thread count), in compiled chunks
    of :data:`TRAIN_CHUNK_EPOCHS` epochs;
    ``progress`` (``True`` for a progress bar, or a callable taking :class:`TrainProgress`)
    hears after every chunk. ``validation_fraction``, ``seed`` and ``validation`` default to
    the spec's. ``pool``: an executor the axes train on, shared with other trainings (see
    :func:`_train_parallel`); the result does not depend on it.
    """
    validation_fraction = spec.validation_fraction if validation_fraction is None else validation_fraction
    seed = spec.seed if seed is None else seed
    validation = spec.validation if validation is None else validation
    x = np.asarray(x, np.float64)
    r = np.asarray(r, np.float64)
    if x.ndim != 2 or x.shape[1] != spec.n_in:
        raise ValueError(f"x must have shape (n, {spec.n_in}), got {x.shape}")
    if r.ndim != 2 or r.shape[0] != x.shape[0]:
        raise ValueError(f"r must have shape ({x.shape[0]}, A), got {r.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(r))):
        raise ValueError("x and r must be finite")
    fit_rows, val_rows = validation_rows(x.shape[0], validation_fraction, seed=seed, kind=validation, groups=groups)
    check_network_size(spec, fit_rows.size)
    st = Standardizer.fit(x[fit_rows], r[fit_rows])
    keys = _axis_keys(seed, r.shape[1])
    freqs = fourier_frequencies(spec, seed) if spec.fourier_features else None
    bar = None
    if progress is True:
        progress, bar = progress_bar(spec.max_epochs, r.shape[1],
                                     desc=f"network training ({spec.likelihood}, {r.shape[1]} axes)")
    try:
        params, info = _train_parallel(spec, keys, embed(st.x(x[fit_rows]), freqs), st.r(r[fit_rows]),
                                       embed(st.x(x[val_rows]), freqs), st.r(r[val_rows]), progress=progress or None,
                                       pool=pool)
    finally:
        if bar is not None:
            bar.close()
    return ResidualNetwork(spec, params, st, jax.device_get(info), int(fit_rows.size), int(val_rows.size), freqs,
                           None, val_rows)


# --------------------------------------------------------------------------- MC DropConnect inference


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


class NetworkEnsemble(NamedTuple):
    """Deep ensemble of ``K`` trained :class:`ResidualNetwork` of one spec (e.g. the job's cross-conformal
    fold networks), predicted together by :func:`mc_predict` with the passes split over the members."""

    members: tuple

    @property
    def spec(self) -> NetworkSpec:
        return self.members[0].spec


def ensemble_passes(passes: int, members: int) -> tuple[int, ...]:
    """MC passes per member: ``passes // members`` each, the first ``passes % members`` members one more
    (100 over 5: 20 each; 101 over 5: 21, 20, 20, 20, 20), and never fewer than 2 (a member's sample
    variance needs 2): below ``2 * members`` passes every member runs 2, ``2 * members`` in all."""
    if members < 1 or passes < 2:
        raise ValueError(f"an ensemble needs at least 1 member and 2 passes, got {members} and {passes}.")
    return tuple(max(2, passes // members + (k < passes % members)) for k in range(members))


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


# --------------------------------------------------------------------------- recalibration

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
