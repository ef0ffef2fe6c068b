"""Settings of a residual network: :class:`NetworkSpec` (every setting, its default and its check), the activations and the size limits."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping, Union

import jax
import jax.numpy as jnp

from bayesmag._src.core.likelihoods import LIKELIHOODS, Likelihood, ShapeParam, get_likelihood

__all__ = ['DTYPE', 'MAX_PARAMS_PER_ROW', 'MIN_VALIDATION_ROWS', 'VALIDATION_KINDS', 'FOURIER_STREAM', 'ACTIVATIONS', 'shape_settings', 'count_params', 'LEARN', 'NetworkSpec']


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



def count_params(n_in: int, n_out: int, *, hidden_layers: int, width: int) -> int:
    """Number of weights and biases of :func:`init`'s network."""
    sizes = [n_in] + [width] * hidden_layers + [n_out]
    return sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))



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

