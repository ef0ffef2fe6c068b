"""Priors of the NUTS model: validated ``priors`` settings (:func:`parse_priors`)."""

from __future__ import annotations

import dataclasses
import math
from typing import Mapping, Sequence

from bayesmag._src.core.likelihoods import LIKELIHOODS, get_likelihood
from bayesmag._src.core.physics import AXES
from bayesmag._src.pipeline.nuts.constants import DEFAULT_PRIOR_SCALE

__all__ = ["NutsPriors", "parse_priors"]


@dataclasses.dataclass(frozen=True)
class NutsPriors:
    """Validated prior settings (see the module docstring and :func:`parse_priors`).

    Attributes:
      scale: prior sd of every physics parameter in LM standard errors (default 100).
      overrides: ``{(axis or None, parameter): (mean or None, sd)}``; mean None = LM estimate,
        axis None = every axis. Absolute units of the parameter.
      sigma: HalfNormal scale of the per-axis noise scale in uT, per axis; None = sd of the
        reference field on that axis.
      fixed: ``((shape field, value), ...)``: shape fields of the likelihood family held
        fixed (Student-t ``df``); the others are learned with their family's prior.
      likelihood: the family these priors are for.
    """

    scale: float = DEFAULT_PRIOR_SCALE
    overrides: tuple = ()
    sigma: tuple = (None, None, None)
    fixed: tuple = ()
    likelihood: str = "gaussian"

    @property
    def df(self) -> float | None:
        """The fixed Student-t degrees of freedom (``None``: learned or not Student-t)."""
        return dict(self.fixed).get("df")

    def shape(self) -> dict[str, tuple[float, bool]]:
        """``{field: (value, learned)}`` for every shape field of the family: the fixed value, or the
        initial value (the family default) of a learned one. Learned: the family gives a prior."""
        family = get_likelihood(self.likelihood)
        fixed = dict(self.fixed)
        return {f: (fixed[f], False) if f in fixed else (float(p.default), p.prior is not None)
                for f, p in family.shape_params.items()}

    def describe(self) -> dict:
        family = get_likelihood(self.likelihood)
        shape = {}
        for f, (v, learned) in self.shape().items():
            prior = family.shape_params[f].prior
            shape[f] = (f"{type(prior()).__name__}{_dist_args(prior())}" if learned else f"fixed at {v:g}")
        return {
            "theta": f"Normal(LM estimate, ({self.scale:g} x LM standard error)^2), independent",
            "overrides": {(f"{AXES[a]}." if a is not None else "") + name: {"mean": m, "sd": s}
                          for (a, name), (m, s) in self.overrides},
            "sigma": {ax: (f"HalfNormal({s:g})" if s is not None else "HalfNormal(sd of the reference on this axis)")
                      for ax, s in zip(AXES, self.sigma)},
            **shape,
        }


def _dist_args(d) -> str:
    """``(2, rate 0.1)``-style arguments of a numpyro distribution for :meth:`NutsPriors.describe`."""
    args = [f"{k} {float(getattr(d, k)):g}" for k in d.arg_constraints if hasattr(d, k)]
    return "(" + ", ".join(args) + ")"


def _positive(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"priors.{where} = {value!r} must be a finite number > 0.")
    return float(value)


def _param_prior(value, where: str) -> tuple[float | None, float]:
    if isinstance(value, dict):
        unknown = set(value) - {"mean", "sd"}
        if unknown or "sd" not in value:
            raise ValueError(f"priors.{where} = {value!r} must be a number (the prior sd, centred at the LM "
                              f"estimate) or a table {{mean = ..., sd = ...}} with 'sd' given.")
        mean = value.get("mean")
        if mean is not None and (isinstance(mean, bool) or not isinstance(mean, (int, float))
                                 or not math.isfinite(mean)):
            raise ValueError(f"priors.{where}.mean = {mean!r} must be a finite number.")
        return (None if mean is None else float(mean)), _positive(value["sd"], where + ".sd")
    return None, _positive(value, where)


def parse_priors(priors: Mapping | None, param_names: Sequence[str], *, likelihood: str = "gaussian") -> NutsPriors:
    """Validate ``[nuts] priors`` against a model's parameter names.

    Keys: ``scale`` (> 0, prior sd in LM standard errors), ``sigma`` (> 0, HalfNormal scale
    of the noise in uT; a number or a table by axis), a shape field of the likelihood family
    (> 0, fixes it; e.g. ``df`` for ``"student_t"``, learned with the family's prior
    otherwise), a parameter name (a number:
    the prior sd around the LM estimate in the parameter's units; or ``{mean, sd}``), or an
    axis ``x``/``y``/``z`` holding a table of parameter priors for that axis only.

    Raises:
      ValueError: naming the bad key (``priors.<key>``) or value and the valid choices.

    Example:
      >>> p = parse_priors({"scale": 10.0, "Ks_x": 0.1, "y": {"O": {"mean": 0.0, "sd": 5.0}}},
      ...                  ("S_x", "Ks_x", "O"))
      >>> p.scale, dict(p.overrides)[(None, "Ks_x")], dict(p.overrides)[(1, "O")]
      (10.0, (None, 0.1), (0.0, 5.0))
    """
    if priors is None:
        priors = {}
    if not isinstance(priors, Mapping):
        raise ValueError(f"priors = {priors!r} must be a table, e.g. {{scale = 10.0, \"Ks_x\" = 0.1}}.")
    if likelihood not in LIKELIHOODS:
        raise ValueError(f"likelihood = {likelihood!r} is not valid; it must be one of {sorted(LIKELIHOODS)}.")
    family = get_likelihood(likelihood)
    own_shape = family.shape_names()
    any_shape = {f: cls.name for cls in LIKELIHOODS.values() for f in cls.shape_names()}
    names = tuple(param_names)
    valid = (f"'scale', 'sigma', {', '.join(repr(f) for f in own_shape) + ', ' if own_shape else ''}"
             f"an axis {list(AXES)} or a parameter name {list(names)}")
    scale, fixed, sigma, overrides = DEFAULT_PRIOR_SCALE, {}, [None, None, None], {}
    for key, value in priors.items():
        if key == "scale":
            scale = _positive(value, "scale")
        elif key in own_shape:
            fixed[key] = _positive(value, key)
        elif key in any_shape and key not in names:
            raise ValueError(f"priors.{key} = {value!r} applies only to likelihood = \"{any_shape[key]}\" "
                             f"(this job uses {likelihood!r}).")
        elif key == "sigma":
            if isinstance(value, dict):
                for ax, v in value.items():
                    if ax not in AXES:
                        raise ValueError(f"priors.sigma has unknown axis {ax!r}; valid: {list(AXES)}.")
                    sigma[AXES.index(ax)] = _positive(v, f"sigma.{ax}")
            else:
                sigma = [_positive(value, "sigma")] * 3
        elif key in AXES:
            if not isinstance(value, dict):
                raise ValueError(f"priors.{key} = {value!r} must be a table of parameter priors for axis "
                                 f"{key}, e.g. {key} = {{\"{names[0]}\" = 0.1}}.")
            for name, v in value.items():
                if name not in names:
                    raise ValueError(f"priors.{key}.{name}: unknown parameter {name!r}; this model's "
                                     f"parameters are {list(names)}.")
                overrides[(AXES.index(key), name)] = _param_prior(v, f"{key}.{name}")
        elif key in names:
            overrides[(None, key)] = _param_prior(value, key)
        else:
            raise ValueError(f"priors has unknown key {key!r}; valid keys: {valid}.")
    order = sorted(overrides.items(), key=lambda kv: (kv[0][0] is not None, kv[0][0] or 0, kv[0][1]))
    return NutsPriors(scale=scale, overrides=tuple(order), sigma=tuple(sigma), fixed=tuple(sorted(fixed.items())),
                      likelihood=likelihood)
