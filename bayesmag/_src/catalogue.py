r"""Catalogue of candidate physics: small named model extensions that discovery can name.

Each entry is one frozen class (a :class:`~bayesmag._src.physics.Term` or an
:class:`~bayesmag._src.physics.InputTransform`) with a one-sentence physical
``explanation``, its own parameters (in physical units) and, for linear terms, exact
design columns. All are registered in :data:`~bayesmag._src.physics.EXTRA_TERMS`, so a
``bayesmag run`` config can use them directly::

    [physics]
    extra_terms = ["cross_axis_quadratic", {name = "thermal_lag", tau0 = 40.0},
                   {name = "hysteresis", axis = "x", mode = "excursion", threshold = 25.0}]

Terms act on the *measured* field ``b`` (uT), the logged temperature ``t`` (C), ``time``
(s) and ``run`` of :class:`~bayesmag._src.physics.Inputs`; every output axis gets its
own coefficients. Conventions of each parameter are in the class docstrings.

=======================  ==========  =============================================  =====================
name                     kind        parameters per output axis                     simulator effect
=======================  ==========  =============================================  =====================
axis_quadratic           linear      q_xx q_yy q_zz (1/uT)                          axis_quadratic
cross_axis_quadratic     linear      q_xy q_xz q_yz (1/uT)                          cross_axis_quadratic
cubic_nonlinearity       linear      c_x c_y c_z (1/uT^2)                           cubic
temperature_quadratic    linear      Ko2 (uT/C^2) [+ Ks2_x Ks2_y Ks2_z (1/C^2)]     temperature_quadratic
thermal_lag              transform   log_tau (tau in s)                             thermal_lag
timing_offset            transform   delta (s)                                      timing_offset
hysteresis               linear      h (uT)                                         hysteresis
offset_drift             linear      drift_rate (uT/s) [+ run_step (uT/run)]        offset_drift
=======================  ==========  =============================================  =====================
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from . import physics as _physics
from .physics import EXTRA_TERMS, InputTransform, Inputs, Term

__all__ = ["CATALOGUE", "AxisQuadratic", "CrossAxisQuadratic", "CubicNonlinearity", "TemperatureQuadratic",
           "ThermalLag", "TimingOffset", "Hysteresis", "OffsetDrift", "SIMULATOR_NAMES", "explanation"]

_AXES = ("x", "y", "z")


def _check_axis(value, field: str) -> None:
    if value not in _AXES:
        raise ValueError(f"{field} is {value!r}; it must be one of {list(_AXES)}.")


def _run_starts(run: jax.Array) -> jax.Array:
    return jnp.concatenate([jnp.array([True]), run[1:] != run[:-1]])


def _hold_last(value: jax.Array, has_value: jax.Array, run: jax.Array) -> jax.Array:
    """Carry the last ``value`` where ``has_value`` forward within each run (0 before any)."""
    starts = _run_starts(run)
    n = value.shape[0]
    idx = jnp.where(has_value | starts, jnp.arange(n), 0)
    idx = jax.lax.cummax(idx)
    v = jnp.where(has_value, value, 0.0)
    return v[idx]


def _run_first_last(run: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Index of the first and last row of each row's run (runs contiguous)."""
    n = run.shape[0]
    starts = _run_starts(run)
    ends = jnp.concatenate([run[1:] != run[:-1], jnp.array([True])])
    first = jax.lax.cummax(jnp.where(starts, jnp.arange(n), 0))
    last = jax.lax.cummin(jnp.where(ends, jnp.arange(n), n - 1), reverse=True)
    return first, last


# --------------------------------------------------------------------------- linear terms


def _with_thermal(term, X: jax.Array, inputs) -> jax.Array:
    """``X`` and, with ``term.thermal``, ``X * (T - t0)`` (the term's coefficients varying linearly with T)."""
    if not term.thermal:
        return X
    return jnp.concatenate([X, X * (inputs.t - term.t0)[..., None]], axis=-1)


def _thermal_names(term, names: tuple) -> tuple:
    return names + tuple(f"{n}_T" for n in names) if term.thermal else names


_THERMAL_DOC = """
    With ``thermal=True`` every coefficient gets a temperature slope (parameters ``<name>_T``,
    per C, about ``t0``): a distortion of the sensor's own reading reaches the calibrated
    output multiplied by the temperature-dependent gain :math:`S + K_s T`, so in calibrated
    units its coefficient changes with temperature (strongly on an axis whose gain changes a
    lot with T, such as y of the paper's sensor, whose gain falls from 2.4 to 0.3)."""


@dataclasses.dataclass(frozen=True)
class AxisQuadratic(Term):
    r"""Squares of the measured field: :math:`\sum_j q_{jj} B_j^2` (``q`` in 1/uT)."""

    t0: float = 0.0
    thermal: bool = False
    name: ClassVar[str] = "axis_quadratic"
    explanation: ClassVar[str] = ("Bridge asymmetry and imperfect set/reset make an axis respond to the square of "
                                  "the field along an axis (even-order nonlinearity).")

    @property
    def degree(self) -> int:
        """Largest power of any single input (2; 2 + 1 with the temperature slopes)."""
        return 2 + int(self.thermal)

    def param_names(self):
        return _thermal_names(self, ("q_xx", "q_yy", "q_zz"))

    def features(self, inputs):
        return _with_thermal(self, inputs.b * inputs.b, inputs)


@dataclasses.dataclass(frozen=True)
class CrossAxisQuadratic(Term):
    r"""Products of two measured field components: :math:`q_{xy} B_x B_y + q_{xz} B_x B_z + q_{yz} B_y B_z`."""

    t0: float = 0.0
    thermal: bool = False
    name: ClassVar[str] = "cross_axis_quadratic"
    explanation: ClassVar[str] = ("Nonlinear coupling between the bridges (cross-field effect of AMR films) makes "
                                  "one axis respond to the product of the fields along two axes.")

    @property
    def degree(self) -> int:
        """Largest power of any single input (2; 2 + 1 with the temperature slopes)."""
        return 2 + int(self.thermal)

    def param_names(self):
        return _thermal_names(self, ("q_xy", "q_xz", "q_yz"))

    def features(self, inputs):
        b = inputs.b
        X = jnp.stack([b[..., 0] * b[..., 1], b[..., 0] * b[..., 2], b[..., 1] * b[..., 2]], axis=-1)
        return _with_thermal(self, X, inputs)


@dataclasses.dataclass(frozen=True)
class CubicNonlinearity(Term):
    r"""Cubes of the measured field: :math:`\sum_j c_j B_j^3` (``c`` in 1/uT^2; saturation flattens the response)."""

    t0: float = 0.0
    thermal: bool = False
    name: ClassVar[str] = "cubic_nonlinearity"
    explanation: ClassVar[str] = ("The magnetoresistive response flattens (or steepens) as the film approaches "
                                  "saturation, an odd-order nonlinearity of the transfer curve.")

    @property
    def degree(self) -> int:
        """Largest power of any single input (3; 3 + 1 with the temperature slopes)."""
        return 3 + int(self.thermal)

    def param_names(self):
        return _thermal_names(self, ("c_x", "c_y", "c_z"))

    def features(self, inputs):
        return _with_thermal(self, inputs.b ** 3, inputs)


@dataclasses.dataclass(frozen=True)
class TemperatureQuadratic(Term):
    r"""Second-order thermal terms: :math:`K_{o2} T_c^2` and, with ``scale=True``, :math:`\sum_j K_{s2,j} T_c^2 B_j`.

    ``T_c = T - t0`` (C). ``Ko2`` in uT/C^2, ``Ks2_j`` in 1/C^2. With ``cubic=True`` a
    further :math:`K_{o3} T_c^3` (uT/C^3): an offset curvature of the sensor's own reading
    reaches the calibrated output multiplied by the temperature-dependent gain
    :math:`S + K_s T`, i.e. as a cubic in T (strongly so on an axis whose gain changes a lot
    with temperature, such as y of the paper's sensor). Column order: Ko2, [Ko3], [Ks2_j].
    """

    t0: float = 0.0
    scale: bool = False
    cubic: bool = False
    name: ClassVar[str] = "temperature_quadratic"
    degree: ClassVar[int] = 2           # T^2 and T^2 B_j: no input beyond the second power
    explanation: ClassVar[str] = ("The bridge offset (and sensitivity) drifts nonlinearly with temperature, beyond "
                                  "the linear Ko (and Ks) coefficients.")

    def param_names(self):
        return (("Ko2",) + (("Ko3",) if self.cubic else ())
                + (("Ks2_x", "Ks2_y", "Ks2_z") if self.scale else ()))

    def features(self, inputs):
        tc = inputs.t - self.t0
        tc2 = (tc * tc)[..., None]
        cols = [tc2]
        if self.cubic:
            cols.append(tc2 * tc[..., None])
        if self.scale:
            cols.append(tc2 * inputs.b)
        return jnp.concatenate(cols, axis=-1) if len(cols) > 1 else tc2


@dataclasses.dataclass(frozen=True)
class Hysteresis(Term):
    r"""Offset :math:`h\,s(t)` with :math:`s \in \{-1, 0, +1\}` set by the history of measured field ``axis``.

    ``mode="excursion"``: ``s`` is the sign of the last excursion of the measured component
    beyond ``+-threshold`` uT. ``mode="direction"``: ``s`` is the sign of the last change
    ``B(t) - B(t - lag samples)`` larger than ``min_step`` uT (direction of travel; the lag
    averages down the sensor noise). ``s = 0`` before the first event of each run.
    Parameter ``h`` in uT. Thresholds are in *measured* uT (before calibration), unless
    ``cal`` is given: the 8 (or 4, without temperature terms) thermo-affine coefficients
    ``S_x S_y S_z Ks_x Ks_y Ks_z O Ko`` (``S_x S_y S_z O``) of the output ``axis``, about
    ``t0``; the history is then that of the *calibrated* field ``(S + Ks T_c) . B + O + Ko T_c``
    and the thresholds are in calibrated uT (needed where the axis' gain changes strongly
    with temperature, so a fixed measured threshold is no fixed field).
    """

    axis: str = "x"
    mode: str = "excursion"
    threshold: float = 25.0
    min_step: float = 2.0
    lag: int = 4
    t0: float = 0.0
    thermal: bool = False
    cal: tuple = ()
    name: ClassVar[str] = "hysteresis"
    degree: ClassVar[None] = None
    explanation: ClassVar[str] = ("The permalloy film keeps a remanent magnetisation whose sign follows the last "
                                  "large field excursion (or the direction of travel), shifting the bridge offset.")

    def __post_init__(self):
        _check_axis(self.axis, "hysteresis axis")
        if self.mode not in ("excursion", "direction"):
            raise ValueError(f"hysteresis mode is {self.mode!r}; it must be one of ['excursion', 'direction'].")
        object.__setattr__(self, "cal", tuple(float(c) for c in self.cal))
        if len(self.cal) not in (0, 4, 8):
            raise ValueError(f"hysteresis cal has {len(self.cal)} values; it must have 0, 4 (S_x S_y S_z O) or 8 "
                             f"(S_x S_y S_z Ks_x Ks_y Ks_z O Ko).")
        if not (self.threshold >= 0 and self.min_step >= 0 and int(self.lag) >= 1):
            raise ValueError(f"hysteresis threshold and min_step must be >= 0 uT and lag >= 1 sample; got "
                             f"{self.threshold!r}, {self.min_step!r}, {self.lag!r}.")

    def param_names(self):
        return _thermal_names(self, ("h",))

    def state(self, inputs: Inputs) -> jax.Array:
        """(n,) magnetisation sign in {-1, 0, +1}."""
        level = self.threshold if self.mode == "excursion" else self.min_step
        return hysteresis_state(self.drive(inputs), inputs.run, level, mode=self.mode, lag=int(self.lag))

    def drive(self, inputs: Inputs) -> jax.Array:
        """(n,) the field whose history sets the state: measured ``axis``, or calibrated with ``cal``."""
        b = inputs.b
        if not self.cal:
            return b[:, _AXES.index(self.axis)]
        c = jnp.asarray(self.cal, dtype=b.dtype)
        if c.size == 4:
            return b @ c[:3] + c[3]
        tc = inputs.t - self.t0
        return b @ c[:3] + tc * (b @ c[3:6]) + c[6] + c[7] * tc

    def features(self, inputs):
        return _with_thermal(self, self.state(inputs)[:, None], inputs)


@dataclasses.dataclass(frozen=True)
class OffsetDrift(Term):
    r"""Offset changing with time: ``drift_rate (time - time_ref)`` and, with ``steps=True``, ``run_step (run - run_ref)``.

    ``drift_rate`` in uT/s, ``run_step`` in uT per unit of run id (runs numbered
    consecutively). Set ``time_ref`` near the data (e.g. its first time stamp) so the rate
    is not collinear with the offset numerically.
    """

    time_ref: float = 0.0
    run_ref: int = 0
    rate: bool = True
    steps: bool = False
    name: ClassVar[str] = "offset_drift"
    degree: ClassVar[None] = None
    explanation: ClassVar[str] = ("Ageing, stress relaxation and slow electronics drift move the offset over time "
                                  "and between sessions.")

    def __post_init__(self):
        if not (self.rate or self.steps):
            raise ValueError("offset_drift needs rate=true, steps=true or both; got neither.")

    def param_names(self):
        return (("drift_rate",) if self.rate else ()) + (("run_step",) if self.steps else ())

    def features(self, inputs):
        cols = []
        if self.rate:
            cols.append(inputs.time - self.time_ref)
        if self.steps:
            cols.append((inputs.run - self.run_ref).astype(inputs.time.dtype))
        return jnp.stack(cols, axis=-1)


def hysteresis_state(f: jax.Array, run: jax.Array, level, *, mode: str, lag: int = 4) -> jax.Array:
    """Sign of the last excursion of ``f`` beyond +-``level`` (``mode="excursion"``) or of the
    last change ``f(t) - f(t - lag)`` larger than ``level`` (``mode="direction"``), held within runs."""
    if mode == "excursion":
        sign = jnp.where(f > level, 1.0, jnp.where(f < -level, -1.0, 0.0))
    else:
        prev = jnp.concatenate([jnp.zeros((lag,), f.dtype), f[:-lag]])
        prev_run = jnp.concatenate([jnp.full((lag,), -1, run.dtype), run[:-lag]])
        d = jnp.where(prev_run == run, f - prev, 0.0)
        sign = jnp.where(jnp.abs(d) > level, jnp.sign(d), 0.0)
    return _hold_last(sign, sign != 0, run)


# --------------------------------------------------------------------------- transforms


@dataclasses.dataclass(frozen=True)
class ThermalLag(_physics.ThermalLag):
    r"""Sensor temperature as a first-order lag of the logged temperature (time constant tau, s).

    See :class:`bayesmag._src.physics.ThermalLag`; parameter ``log_tau``; ``tau0`` is the
    starting value in seconds.
    """

    explanation: ClassVar[str] = ("The sensor die heats and cools more slowly than the thermometer that logs the "
                                  "temperature, so it sees a lagged temperature.")


@dataclasses.dataclass(frozen=True)
class TimingOffset(InputTransform):
    r"""The sensor stream is delayed by ``delta`` s against the reference.

    The row logged at time :math:`t` saw the field of time :math:`t - \delta`, so the
    calibrated field at :math:`t` uses the readings (and temperature) interpolated at
    :math:`t + \delta`, linearly within each run and held at the run's ends. Parameter
    ``delta`` in s (positive: the sensor lags); ``delta0`` is its starting value.
    """

    delta0: float = 0.0
    name: ClassVar[str] = "timing_offset"
    explanation: ClassVar[str] = ("The sensor and the reference are sampled by different clocks, so each sensor row "
                                  "is logged a fixed latency after the field it saw.")

    def param_names(self):
        return ("delta",)

    def init_params(self, axis):
        return np.array([float(self.delta0)])

    def __call__(self, params, inputs):
        delta = params[0]
        time = inputs.time
        first, last = _run_first_last(inputs.run)
        t_first, t_last = time[first], time[last]
        order = jnp.cumsum(_run_starts(inputs.run)).astype(time.dtype)
        width = jnp.max(t_last - t_first) + 1.0
        tm = time - t_first + order * width                     # strictly increasing across runs
        q = jnp.clip(time + delta, t_first, t_last) - t_first + order * width
        b = jnp.stack([jnp.interp(q, tm, inputs.b[:, k]) for k in range(3)], axis=-1)
        t = jnp.interp(q, tm, inputs.t)
        return inputs._replace(b=b, t=t)


for _cls in (AxisQuadratic, CrossAxisQuadratic, CubicNonlinearity, Hysteresis):
    _cls.__doc__ = (_cls.__doc__ or "") + _THERMAL_DOC

#: The discovery catalogue: name -> class.
CATALOGUE: dict[str, type] = {
    c.name: c for c in (AxisQuadratic, CrossAxisQuadratic, CubicNonlinearity, TemperatureQuadratic, ThermalLag,
                        TimingOffset, Hysteresis, OffsetDrift)
}

#: Simulator effect name (:mod:`bayesmag.simulate`) -> catalogue name that represents it.
SIMULATOR_NAMES: dict[str, str] = {
    "axis_quadratic": "axis_quadratic", "cross_axis_quadratic": "cross_axis_quadratic",
    "cubic": "cubic_nonlinearity", "temperature_quadratic": "temperature_quadratic",
    "thermal_lag": "thermal_lag", "timing_offset": "timing_offset", "hysteresis": "hysteresis",
    "offset_drift": "offset_drift",
}


def explanation(name: str) -> str:
    """The one-sentence physical explanation of catalogue entry ``name``."""
    if name not in CATALOGUE:
        raise ValueError(f"catalogue entry {name!r} is not known; it must be one of {sorted(CATALOGUE)}.")
    return CATALOGUE[name].explanation


EXTRA_TERMS.update(CATALOGUE)
