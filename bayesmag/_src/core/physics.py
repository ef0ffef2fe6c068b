r"""Physics calibration models, built from small terms.

The model for output axis :math:`i` is a sum of terms evaluated on (possibly transformed)
inputs,

.. math::  \hat B_{\mathrm{ref},i} = \sum_k g_k(\theta_{i,k};\, \mathcal{T}(x; \theta_{i,\mathcal{T}}))

where the base term is the paper's temperature-compensated affine model (Shetty & Marndi
2026, eq. 1-2), written in :math:`T_c = T - T_0`,

.. math::  \sum_j (S_{ij} + K_{s,ij} T_c) B_{\mathrm{meas},j} + O_i + K_{o,i} T_c .

Extension points (each one small frozen class, nothing else changes):

* :class:`Term` -- an additive contribution ``g(params, inputs) -> (n,)``. A term that is
  linear in its parameters also exposes ``features(inputs) -> (n, k)`` so fits and the
  physics uncertainty can use exact linear algebra; ``degree`` is its largest power of any
  single input among (Bx, By, Bz, T) (``T*B_j`` has degree 1, ``B_j^2`` degree 2; ``None`` if
  not polynomial), used by the analytic uncertainty method (``degree + 1`` Gauss-Hermite
  nodes per input are exact).
* :class:`InputTransform` -- maps the whole input series to new inputs with its own
  (possibly nonlinear) parameters, e.g. a thermal lag or a timing delay.

Parameters of one axis are one flat vector: base term, extra terms, transforms, in order.
All axes share the structure, so three axes are handled with ``jax.vmap``.
"""

from __future__ import annotations

import abc
import dataclasses
import functools
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bayesmag._src.core.data import median_step  # noqa: F401 (re-exported: it lived here)

__all__ = ["T0_DEFAULT", "resolve_t0", "Inputs", "Term", "InputTransform", "ThermoAffine", "ThermalLag",
           "PhysicsModel", "inputs_from_data", "centred", "AXES"]

AXES = ("x", "y", "z")


class Inputs(NamedTuple):
    """Model inputs: field b (..., 3) in uT, temperature t (...,) in C, time (...,) in s, run id."""

    b: jax.Array
    t: jax.Array
    time: jax.Array
    run: jax.Array


def inputs_from_data(data) -> Inputs:
    """:class:`Inputs` (float64) from a :class:`~bayesmag.CalibrationData`.

    ``jax.device_put``, not ``jnp.asarray``: the same arrays, without compiling a conversion program for
    every new row count (a job calls this for many row sets; each program costs tracing and lowering
    even when the persistent cache holds it).
    """
    return Inputs(*(jax.device_put(np.asarray(a)) for a in (data.b_meas, data.temperature, data.time, data.run)))


class Term(abc.ABC):
    """An additive model term for one output axis.

    Subclasses are frozen dataclasses and set ``name``, ``linear`` and ``degree``.
    """

    name: ClassVar[str]
    linear: ClassVar[bool] = True
    #: Largest power of any single input (Bx, By, Bz, T) in the features; None if not polynomial.
    #: A larger value is still exact, only slower.
    degree: ClassVar[int | None] = 1
    #: True: temperature enters only as ``T - t0`` or through operations that commute with adding a constant
    #: to T (:func:`centred`). Read from the class's own body, not inherited: a subclass that changes how
    #: temperature enters must declare it again. Default False (always correct, compiled once per T0).
    temperature_centred: ClassVar[bool] = False
    #: True: a row's features depend on earlier rows (a remanent state), so they exist only on the whole series.
    #: The physics UQ then takes them from the unperturbed series (:meth:`PhysicsModel.history_columns`): the
    #: input noise is not propagated through them. Such a term must be linear in its parameters.
    history: ClassVar[bool] = False

    @abc.abstractmethod
    def param_names(self) -> tuple[str, ...]: ...

    def init_params(self, axis: int) -> np.ndarray:
        """Starting values for output ``axis``; zeros unless the term says otherwise."""
        return np.zeros(len(self.param_names()))

    def features(self, inputs: Inputs) -> jax.Array:
        """(..., k) design columns such that ``self(p, inputs) == features @ p`` (linear terms)."""
        raise NotImplementedError(f"term {self.name!r} is not linear in its parameters")

    def linear_in_params(self) -> bool:
        """The class's ``linear``; a term with a dataclass field of that name (which hides it) overrides this."""
        return self.linear

    def bound_runs(self) -> tuple:
        """The run ids of the training recording whose rows this term alone describes (``run_offset``, ``run_step``:
        parameters a new session does not share; empty for every other term). A new session's rows are predicted
        with their run ids moved past these (:func:`new_session_runs`), so the term gives them what it gives rows
        of no listed run: the reference state (a run offset of 0)."""
        return ()

    def restricted(self, runs) -> "Term | None":
        """This term for a model fitted on the runs ``runs`` only (leave-one-run-out): a term bound to runs
        (:meth:`bound_runs`) keeps those of its runs that are there, or is dropped (None); others are kept."""
        return self

    def history_settled(self, inputs: Inputs) -> bool:
        """True if the features at the last row of the series ``inputs`` are what they are on any longer series
        that ends with ``inputs`` (so a piece of a recording needs no earlier rows). Always True for a term without
        :attr:`history`; a history term that does not override this is never settled (the whole recording is
        needed)."""
        return not self.history

    def __call__(self, params: jax.Array, inputs: Inputs) -> jax.Array:
        return self.features(inputs) @ params


class InputTransform(abc.ABC):
    """A transform of the whole input series with its own parameters (often nonlinear)."""

    name: ClassVar[str]
    temperature_centred: ClassVar[bool] = False      # as Term.temperature_centred

    @abc.abstractmethod
    def param_names(self) -> tuple[str, ...]: ...

    @abc.abstractmethod
    def init_params(self, axis: int) -> np.ndarray: ...

    @abc.abstractmethod
    def __call__(self, params: jax.Array, inputs: Inputs) -> Inputs: ...

    def memory_rows(self, params: np.ndarray, dt: float) -> int | None:
        """Rows before and after a row that its transformed value depends on (to double precision) at sampling
        step ``dt`` (s); None: not known (a piece of a series is then predicted with a whole piece around it)."""
        return None

    def unsupported(self, params: np.ndarray, sd: np.ndarray, dt: float) -> str | None:
        """Why fitted ``params`` (standard errors ``sd``) describe no effect the data hold, so that their
        uncertainty is meaningless, or None (default). ``dt``: the median sampling step (s). A fit with
        ``check_rank`` refuses such a transform, as it refuses a rank-deficient Jacobian."""
        return None


#: The one default reference temperature of every settings type (config ``[physics] t0``, :class:`~bayesmag.Calibrator`,
#: :func:`~bayesmag.discover`): the training rows' mean temperature, which decorrelates S from Ks and O from Ko.
T0_DEFAULT = "mean"


def resolve_t0(t0, temperature) -> float:
    """The reference temperature (C) a model is built with: ``t0`` itself, or with ``"mean"`` the mean of
    ``temperature`` (the training rows'). The one place where ``"mean"`` is resolved.

    Example:
      >>> resolve_t0("mean", [20.0, 30.0]), resolve_t0(0, [20.0, 30.0])
      (25.0, 0.0)
    """
    if isinstance(t0, str):
        if t0 != "mean":
            raise ValueError(f"t0 = {t0!r} must be a number (C) or \"mean\".")
        t = np.asarray(temperature, dtype=np.float64)
        return float(np.mean(t)) if t.size else 0.0     # no rows: the caller refuses them (too few rows)
    check_t0(t0, temperature)
    return float(t0)


#: A reference temperature this far (C) outside every training temperature is not a choice but a unit slip: 273.15
#: (kelvin for C) is the one seen (``physics.t0 = 298.15`` beside kelvin data: a certificate at "T0 = 298.1 C" whose
#: parameters were extrapolated 270 C, 18 correlation notes blaming the motion).
T0_FAR_C = 150.0


def check_t0(t0, temperature, name: str = "t0") -> None:
    """Refuse (:class:`~bayesmag.DataError`, naming ``name``) a numeric ``t0`` more than :data:`T0_FAR_C` outside the
    finite ``temperature`` values (C)."""
    from bayesmag._src.core.data import DataError
    t = np.asarray(temperature, dtype=np.float64)
    t = t[np.isfinite(t)]
    if not t.size or isinstance(t0, str):
        return
    lo, hi = float(t.min()), float(t.max())
    gap = max(lo - float(t0), float(t0) - hi, 0.0)
    if gap > T0_FAR_C:
        k = " (it reads as kelvin: t0 is in C, like the converted data)" if 150 < float(t0) < 450 else ""
        raise DataError(f"{name} = {t0!r} C lies {gap:.0f} C outside the training temperatures ({lo:.1f} to {hi:.1f} C)"
                         f"{k}; the thermal parameters would be extrapolated that far. Give t0 in C within or near "
                         f"that range, or \"mean\".")


@dataclasses.dataclass(frozen=True)
class ThermoAffine(Term):
    """The paper's base model: ``(S + Ks Tc) B + O + Ko Tc`` with ``Tc = T - t0``.

    Parameters per axis (paper order): ``S_x S_y S_z Ks_x Ks_y Ks_z O Ko``; with
    ``temperature=False`` only ``S_x S_y S_z O`` (for recordings at constant temperature).
    """

    t0: float = 0.0
    temperature: bool = True
    name: ClassVar[str] = "thermo_affine"
    degree: ClassVar[int] = 1           # B_j, T, T*B_j: each input at most to the first power
    temperature_centred: ClassVar[bool] = True

    def param_names(self):
        if self.temperature:
            return ("S_x", "S_y", "S_z", "Ks_x", "Ks_y", "Ks_z", "O", "Ko")
        return ("S_x", "S_y", "S_z", "O")

    def init_params(self, axis):
        p = np.zeros(len(self.param_names()))
        p[axis] = 1.0
        return p

    def features(self, inputs):
        b = inputs.b
        one = jnp.ones_like(inputs.t)
        if not self.temperature:
            return jnp.concatenate([b, one[..., None]], axis=-1)
        tc = inputs.t - self.t0
        return jnp.concatenate([b, tc[..., None] * b, one[..., None], tc[..., None]], axis=-1)


@dataclasses.dataclass(frozen=True)
class ThermalLag(InputTransform):
    r"""Sensor temperature as a first-order lag of the logged temperature.

    .. math::  \tau\, \dot T_s = T - T_s, \quad T_s(0) = T(0) \text{ at each run start},

    discretised exactly for piecewise-constant input between samples
    (:math:`a = e^{-\Delta t/\tau}`), run with ``lax.scan``. Parameter ``log_tau``
    (tau in seconds, log-parametrised so it stays positive).
    """

    tau0: float = 30.0
    name: ClassVar[str] = "thermal_lag"
    temperature_centred: ClassVar[bool] = True      # a linear filter of unit gain: lag(T - c) = lag(T) - c

    def param_names(self):
        return ("log_tau",)

    def init_params(self, axis):
        return np.array([np.log(self.tau0)])

    def memory_rows(self, params, dt):
        # the start's weight after k rows is exp(-k dt / tau) (times a polynomial in k for cascaded nodes):
        # under 1e-17 after 45 tau
        return int(np.ceil(45.0 * float(np.exp(params[0])) / max(float(dt), 1e-12)))

    def unsupported(self, params, sd, dt):
        # tau below one step: the filter is the identity to within exp(-dt/tau), log_tau's gradient vanishes
        # (a fit on data without a lag walks there; log_tau sd 5e7 seen), and sampling it gives absurd lags
        tau, s = float(np.exp(params[0])), float(sd[0])
        if tau < dt:
            return (f"the fitted tau is {tau:.3g} s, shorter than one sampling step ({dt:.3g} s; log_tau sd "
                    f"{s:.2g}), i.e. no lag")
        if not s <= np.log(10.0):
            # an axis whose output barely depends on temperature leaves tau free: its draws would span decades
            factor = f"{np.exp(s):.3g}" if s < 46 else "over 1e20"
            return f"tau = {tau:.3g} s is not determined (log_tau sd {s:.2g}: a factor {factor} at one sd)"
        return None

    def __call__(self, params, inputs):
        tau = jnp.exp(params[0])
        dt = jnp.diff(inputs.time, prepend=inputs.time[:1])
        new_run = jnp.concatenate([jnp.array([True]), inputs.run[1:] != inputs.run[:-1]])

        def step(ts, xs):
            t, d, fresh = xs
            a = jnp.exp(-jnp.maximum(d, 0.0) / tau)
            nxt = jnp.where(fresh, t, a * ts + (1 - a) * t)
            return nxt, nxt

        _, ts = jax.lax.scan(step, inputs.t[0], (inputs.t, dt, new_run))
        return inputs._replace(t=ts)


_CHECKED_TERMS: set = set()


def _check_feature_columns(term) -> None:
    """A linear term's ``features`` give one column per parameter (checked once per term on two rows): a term with
    2 columns for 3 ``param_names`` registered, and the job failed inside JAX with "dot_general requires contracting
    dimensions to have the same shape", naming no term (sixth outside pass)."""
    try:
        key = (type(term), term)
        if key in _CHECKED_TERMS or not term.linear_in_params() or getattr(term, "history", False):
            return
    except TypeError:                   # an unhashable term: check it every time
        key = None
    names = tuple(term.param_names())
    rows = Inputs(jnp.asarray([[20.0, 5.0, -40.0], [25.0, -3.0, 38.0]]), jnp.asarray([20.0, 25.0]),
                  jnp.asarray([0.0, 1.0]), jnp.asarray([0, 0]))
    try:
        k = np.shape(term.features(rows))[-1]
    except Exception:  # noqa: BLE001 -- a term that needs other rows fails, if at all, where it is used
        return
    if k != len(names):
        raise ValueError(f"physics term {term.name!r} ({type(term).__name__}): features gives {k} column(s) for its "
                         f"{len(names)} parameter(s) {list(names)}; a linear term needs one column per parameter "
                         f"(docs/extending.md).")
    if key is not None:
        _CHECKED_TERMS.add(key)


@dataclasses.dataclass(frozen=True)
class PhysicsModel:
    """A calibration model for one output axis: terms summed on transformed inputs.

    Example:
      >>> m = PhysicsModel.paper()
      >>> m.param_names[:3], m.n_params
      (('S_x', 'S_y', 'S_z'), 8)
    """

    terms: tuple[Term, ...]
    transforms: tuple[InputTransform, ...] = ()

    def __post_init__(self):
        # T0 has one source, the model: the base term's (the first component with a ``t0`` field).
        # Every other component that centres temperature is given the same T0 here, so no term can
        # silently use another reference temperature than the one the report and exports state.
        t0 = self.t0
        fix = lambda c: dataclasses.replace(c, t0=t0) if _has_t0(c) and c.t0 != t0 else c  # noqa: E731
        object.__setattr__(self, "terms", tuple(fix(c) for c in self.terms))
        object.__setattr__(self, "transforms", tuple(fix(c) for c in self.transforms))
        for c in self.terms:
            _check_feature_columns(c)

    @property
    def t0(self) -> float:
        """The model's reference temperature T0 (C): ``Tc = T - T0`` in every term that uses temperature."""
        return next((float(c.t0) for c in self.terms + self.transforms if _has_t0(c)), 0.0)

    @classmethod
    def paper(cls, *, t0: float = 0.0, temperature: bool = True, extra: tuple = ()) -> "PhysicsModel":
        """The paper's thermo-affine model plus optional extra terms/transforms."""
        terms = (ThermoAffine(t0=t0, temperature=temperature),) + tuple(e for e in extra if isinstance(e, Term))
        transforms = tuple(e for e in extra if isinstance(e, InputTransform))
        return cls(terms, transforms)

    # ---- parameter bookkeeping (static) --------------------------------------------
    @property
    def components(self) -> tuple:
        return self.terms + self.transforms

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(n for c in self.components for n in c.param_names())

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def _slices(self):
        out, i = [], 0
        for c in self.components:
            k = len(c.param_names())
            out.append(slice(i, i + k))
            i += k
        return out

    def init_params(self, axis: int) -> np.ndarray:
        return np.concatenate([c.init_params(axis) for c in self.components])

    def init_params_all(self) -> np.ndarray:
        """(3, p) starting values for the three output axes."""
        return np.stack([self.init_params(a) for a in range(3)])

    @property
    def is_linear(self) -> bool:
        """True if the prediction is linear in all parameters (exact linear algebra applies)."""
        return not self._nonlinear()

    @property
    def degree(self) -> int | None:
        """Largest power of any single input in the features (see :class:`Term`), or None."""
        if self.transforms or any(t.degree is None for t in self.terms):
            return None
        return max(t.degree for t in self.terms)

    # ---- evaluation -------------------------------------------------------------------
    def transform(self, theta: jax.Array, inputs: Inputs) -> Inputs:
        """Apply the input transforms (whole series) for parameters ``theta`` (p,)."""
        sl = self._slices()[len(self.terms):]
        for tr, s in zip(self.transforms, sl):
            inputs = tr(theta[s], inputs)
        return inputs

    def pointwise(self, theta: jax.Array, inputs: Inputs, fixed: tuple | None = None) -> jax.Array:
        """Sum of the additive terms on already-transformed inputs, any leading shape; ``fixed``: as
        :meth:`features`."""
        sl = self._slices()
        out = 0.0
        for k, (term, s) in enumerate(zip(self.terms, sl)):
            if fixed is not None and fixed[k] is not None:
                out = out + _broadcast_rows(fixed[k], inputs) @ theta[s]
            else:
                out = out + term(theta[s], inputs)
        return out

    @property
    def has_history(self) -> bool:
        """True if a term's features depend on earlier rows (:attr:`Term.history`)."""
        return any(t.history for t in self.terms)

    def history_columns(self, inputs: Inputs) -> tuple:
        """Per term: its ``(n, k)`` features on the whole series ``inputs`` if it is a history term, else None
        (the ``fixed`` argument of :meth:`features` and :meth:`pointwise`)."""
        return tuple(t.features(inputs) if t.history else None for t in self.terms)

    @property
    def needs_series(self) -> bool:
        """True if a row's prediction depends on its neighbours (input transforms, history terms): rows cut from a
        recording are then fitted and predicted within it (``calibrate(series=)``, ``fit_physics(keep=)``)."""
        return bool(self.transforms) or self.has_history

    @property
    def bound_runs(self) -> tuple:
        """Every run id a term is bound to (:meth:`Term.bound_runs`), sorted; empty for most models."""
        return tuple(sorted({int(r) for t in self.terms for r in t.bound_runs()}))

    def history_settled(self, inputs: Inputs) -> bool:
        """True if every history term's state at the last row of ``inputs`` no longer depends on earlier rows
        (:meth:`Term.history_settled`)."""
        return all(t.history_settled(inputs) for t in self.terms)

    def memory_rows(self, theta3: np.ndarray, dt: float) -> int | None:
        """Rows of context a piece of a series needs on each side for its input transforms to give what they give
        on the whole series (:meth:`InputTransform.memory_rows`, the largest over transforms and axes); 0 without
        transforms, None if a transform does not say."""
        sl = self._slices()[len(self.terms):]
        need = 0
        for tr, s in zip(self.transforms, sl):
            for a in range(np.shape(theta3)[0]):
                k = tr.memory_rows(np.asarray(theta3)[a, s], dt)
                if k is None:
                    return None
                need = max(need, int(k))
        return need

    def predict(self, theta: jax.Array, inputs: Inputs) -> jax.Array:
        """Calibrated field of one axis, (n,), for parameters ``theta`` (p,)."""
        return self.pointwise(theta, self.transform(theta, inputs))

    def _nonlinear(self) -> tuple:
        return self.transforms + tuple(t for t in self.terms if not t.linear_in_params())

    def features(self, inputs: Inputs, fixed: tuple | None = None) -> jax.Array:
        """(..., p) design matrix of a linear model: ``predict(theta) == features @ theta``.

        ``fixed``: per term, None or its ``(n, k)`` columns to use instead (:meth:`history_columns`; broadcast
        over the extra axes of perturbed inputs ``(n, q)``), for rows cut from a series or perturbed by noise."""
        if not self.is_linear:
            raise ValueError("features() needs a model linear in its parameters; this one has "
                             f"nonlinear components {[c.name for c in self._nonlinear()]}.")
        return jnp.concatenate([t.features(inputs) if fixed is None or fixed[k] is None
                                else _broadcast_rows(fixed[k], inputs) for k, t in enumerate(self.terms)], axis=-1)

    def predict_all(self, theta3: jax.Array, inputs: Inputs) -> jax.Array:
        """(n, 3) calibrated field for per-axis parameters ``theta3`` (3, p); one compiled program per model
        (its T0 aside: :func:`centred`) and shape (called eagerly, the vmapped terms were a dozen small programs)."""
        model, inputs = centred(self, inputs)
        return _predict_all(model, theta3, inputs)

    def describe(self) -> dict:
        return {
            "terms": [dict(name=t.name, **dataclasses.asdict(t)) for t in self.terms],
            "transforms": [dict(name=t.name, **dataclasses.asdict(t)) for t in self.transforms],
            "param_names": list(self.param_names),
        }


def restricted(model: PhysicsModel, runs) -> PhysicsModel:
    """``model`` for a fit on the runs ``runs`` only (:meth:`Term.restricted`): a run offset keeps the offsets of
    those runs, a step in a run not among them is dropped. ``model`` itself without terms bound to runs."""
    if not model.bound_runs:
        return model
    runs = {int(r) for r in runs}
    terms = tuple(t for t in (c.restricted(runs) for c in model.terms) if t is not None)
    return dataclasses.replace(model, terms=terms)


def new_session_runs(model: PhysicsModel, run, new=True) -> np.ndarray:
    """Run ids for predicting rows of a new session (``new``: True or an (n,) mask): moved past every id the
    model's terms are bound to (:attr:`PhysicsModel.bound_runs`) and every id in ``run``, so a run offset or a
    step fitted to a training run does not land on a new recording's run of the same number; runs stay distinct
    (their starts, which reset a hysteresis state or a thermal lag, are kept). ``run`` itself without such terms.

    Example:
      >>> from bayesmag._src.core.catalogue import RunOffset
      >>> m = PhysicsModel.paper(extra=(RunOffset(runs=(1, 2, 3)),))
      >>> new_session_runs(m, np.array([1, 1, 2])).tolist()
      [4, 4, 5]
    """
    run = np.asarray(run)
    bound = model.bound_runs
    if not bound or run.size == 0:
        return run
    shift = max(max(bound), int(run.max())) - int(run.min()) + 1
    return np.where(np.broadcast_to(np.asarray(new, bool), run.shape), run + shift, run)


def _broadcast_rows(cols, inputs: Inputs) -> jax.Array:
    """``(n, k)`` columns broadcast to the leading shape of ``inputs`` (``(n,)`` or ``(n, q)``): ``(..., k)``."""
    lead = inputs.t.shape
    return jnp.broadcast_to(cols.reshape(cols.shape[:1] + (1,) * (len(lead) - 1) + cols.shape[1:]),
                            lead + cols.shape[1:])


def _has_t0(component) -> bool:
    return dataclasses.is_dataclass(component) and any(f.name == "t0" for f in dataclasses.fields(component))


def centred(model: PhysicsModel, inputs: Inputs) -> tuple[PhysicsModel, Inputs]:
    r"""``(model at T0 = 0, inputs with T - T0)``: the same predictions, one compiled program for every T0.

    jit takes a model as a static argument, so its T0 (a float in it) was part of every program: each
    recording with its own training-mean T0 compiled the fit and the uncertainty anew (about 1.4 s of a
    1.6 s physics ``calibrate`` on 2000 rows, against 0.16 s once compiled). Exact where every component
    declares ``temperature_centred`` (it sees :math:`T - t_0` only, or commutes with a constant shift of
    T); otherwise ``(model, inputs)`` unchanged. Call it on the host, at a jit boundary; the fit keeps
    ``model`` (parameters, reports and exports are about T0).
    """
    t0 = model.t0
    exact = all(type(c).__dict__.get("temperature_centred", False) for c in model.components)
    if t0 == 0.0 or not exact or isinstance(inputs.t, jax.core.Tracer):
        return model, inputs
    return _at_t0_zero(model), inputs._replace(t=jax.device_put(np.asarray(inputs.t) - t0))


@functools.lru_cache(maxsize=64)
def _at_t0_zero(model: PhysicsModel) -> PhysicsModel:
    fix = lambda c: dataclasses.replace(c, t0=0.0) if _has_t0(c) else c  # noqa: E731
    return PhysicsModel(tuple(fix(c) for c in model.terms), tuple(fix(c) for c in model.transforms))


@functools.partial(jax.jit, static_argnums=0)
def _predict_all(model: PhysicsModel, theta3, inputs: Inputs):
    return jax.vmap(model.predict, in_axes=(0, None), out_axes=1)(theta3, inputs)


#: Named model extensions usable as ``[physics] extra_terms = ["name", {name = "...", ...}]``;
#: filled by :mod:`bayesmag._src.core.catalogue` (the discovery catalogue, which builds them by name
#: with :func:`~bayesmag._src.core.catalogue.make_extra`). physics does not import the catalogue: no cycle.
EXTRA_TERMS: dict[str, type] = {}
