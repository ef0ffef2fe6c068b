r"""Simulated magnetometer: known true parameters, seeded inputs, named distortion effects.

The sensor is the inverse of the paper's thermo-affine calibration model (Shetty & Marndi
2026, section 4.1). Given the true field :math:`B_\mathrm{ref}` and temperature :math:`T`,

.. math::  B_\mathrm{meas} = (S + K_s T)^{-1} (B_\mathrm{ref} - O - K_o T) + \varepsilon,
           \qquad \varepsilon \sim \mathcal N(0, \sigma^2 I),

so that the forward model :math:`B_\mathrm{ref} = (S + K_s T) B_\mathrm{meas} + O + K_o T`
holds exactly when :math:`\sigma = 0`. Distortion effects (:class:`Effect`) are then
applied in order to the noisy reading; the paper's study uses one,
``By_meas += 0.01 Bx_meas^2`` (:class:`AxisQuadratic`).

Inputs come from one of two seeded designs: :func:`draw_iid` (the paper's section 4:
uniform fields and temperatures) or :func:`draw_campaign` (a Helmholtz-coil campaign:
runs of held steps, rotations, room-temperature wander and heating ramps at 4 Hz), or
from any :class:`Conditions` (e.g. those of a real recording,
:meth:`Conditions.from_data`).

Units: field uT, temperature degrees C, time s.
"""

from __future__ import annotations

import abc
import dataclasses
import inspect
import math
import types
from typing import Callable, ClassVar, Mapping, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from bayesmag._src.core import physics as _physics
from bayesmag._src.core.data import CalibrationData

__all__ = [
    "TrueParams",
    "Conditions",
    "Effect",
    "EFFECTS",
    "get_effect",
    "draw_iid",
    "draw_campaign",
    "simulate",
    "simulate_from_config",
]

AXES = ("x", "y", "z")
#: Largest condition number of S + Ks T accepted over the simulated temperature range.
MAX_CONDITION = 100.0

Measure = Callable[[np.ndarray, np.ndarray], np.ndarray]


# --------------------------------------------------------------------------- true parameters


def _frozen(a, shape, name) -> np.ndarray:
    arr = np.array(a, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"TrueParams.{name} must have shape {shape}; got {arr.shape}.")
    if not np.isfinite(arr).all():
        raise ValueError(f"TrueParams.{name} has non-finite entries.")
    arr.setflags(write=False)
    return arr


@dataclasses.dataclass(frozen=True, eq=False)
class TrueParams:
    r"""True parameters of a simulated sensor (rows = output axes x, y, z).

    The forward (calibration) model is :math:`B_\mathrm{ref} = (S + K_s T) B_\mathrm{meas} + O + K_o T`
    with T in degrees C.

    Attributes:
      S: (3, 3) sensitivity / cross-axis matrix, dimensionless.
      Ks: (3, 3) temperature coefficients of S, 1/C.
      O: (3,) offsets at 0 C, uT.
      Ko: (3,) offset temperature coefficients, uT/C.

    Example:
      >>> p = TrueParams.paper()
      >>> p.theta.shape, float(p.S[1, 1])
      ((3, 8), 2.3696)
    """

    S: np.ndarray
    Ks: np.ndarray
    O: np.ndarray
    Ko: np.ndarray

    def __post_init__(self):
        for name, shape in (("S", (3, 3)), ("Ks", (3, 3)), ("O", (3,)), ("Ko", (3,))):
            object.__setattr__(self, name, _frozen(getattr(self, name), shape, name))

    @classmethod
    def paper(cls) -> "TrueParams":
        """The paper's Table 2 (thermo-affine fit on all 3378 Belsten rows, T in C).

        Note: ``S_yy + Ks_yy T = 2.3696 - 0.052 T`` vanishes at T = 45.6 C, so these
        parameters describe an invertible sensor only below about 45 C.
        """
        theta = np.array([
            [1.0257, -0.1629, -0.2111, 0.0032, 0.0047, 0.0080, -1.2102, 0.0360],
            [-0.1596, 2.3696, 0.0427, 0.0027, -0.0520, -0.0028, -0.0709, -0.0009],
            [-0.0862, 0.0963, 1.2140, 0.0046, -0.0011, -0.0040, 4.3228, -0.1607],
        ])
        return cls.from_theta(theta)

    @classmethod
    def from_theta(cls, theta) -> "TrueParams":
        """From a (3, 8) array in the model's order ``S_x S_y S_z Ks_x Ks_y Ks_z O Ko``."""
        theta = np.asarray(theta, dtype=np.float64)
        if theta.shape != (3, 8):
            raise ValueError(f"theta must have shape (3, 8) (rows x,y,z; columns S_x S_y S_z Ks_x Ks_y Ks_z O Ko); "
                             f"got {theta.shape}.")
        return cls(theta[:, 0:3], theta[:, 3:6], theta[:, 6], theta[:, 7])

    @property
    def theta(self) -> np.ndarray:
        """(3, 8) parameters in the model's order (``PhysicsModel.paper()`` with t0 = 0)."""
        return np.concatenate([self.S, self.Ks, self.O[:, None], self.Ko[:, None]], axis=1)

    def forward(self, b_meas, temperature) -> np.ndarray:
        r"""Calibration model :math:`(S + K_s T) B_\mathrm{meas} + O + K_o T`, (n, 3)."""
        b, t = np.asarray(b_meas, np.float64), np.asarray(temperature, np.float64)
        m = self.S + self.Ks * t[:, None, None]
        return np.einsum("nij,nj->ni", m, b) + self.O + self.Ko * t[:, None]

    def measure(self, b_ref, temperature) -> np.ndarray:
        r"""Noise-free sensor reading :math:`(S + K_s T)^{-1}(B_\mathrm{ref} - O - K_o T)`, (n, 3).

        One batched 3x3 solve per row (vectorised).
        """
        b, t = np.asarray(b_ref, np.float64), np.asarray(temperature, np.float64)
        m = self.S + self.Ks * t[:, None, None]
        rhs = b - self.O - self.Ko * t[:, None]
        return np.linalg.solve(m, rhs[..., None])[..., 0]

    def check_invertible(self, temperature, *, max_condition: float = MAX_CONDITION) -> None:
        """Raise ValueError if S + Ks T is singular or ill-conditioned anywhere in the temperature range."""
        t = np.asarray(temperature, np.float64)
        lo, hi = float(t.min()), float(t.max())
        grid = np.unique(np.concatenate([np.linspace(lo, hi, 513), [lo, hi]]))
        m = self.S + self.Ks * grid[:, None, None]
        sv = np.linalg.svd(m, compute_uv=False)
        cond = sv[:, 0] / np.maximum(sv[:, -1], 1e-300)
        det_sign = np.sign(np.linalg.det(m))
        crosses = np.flatnonzero(det_sign[1:] != det_sign[:-1])
        if crosses.size or cond.max() > max_condition:
            worst = grid[crosses[0]] if crosses.size else grid[int(np.argmax(cond))]
            raise ValueError(
                f"S + Ks*T is singular or ill-conditioned (condition number > {max_condition:g}) near "
                f"T = {worst:.1f} C, inside the simulated temperature range [{lo:.1f}, {hi:.1f}] C: the sensor "
                f"would read unbounded fields there. Keep temperatures where S + Ks*T is invertible (for "
                f"TrueParams.paper(), below about 45 C, where S_yy + Ks_yy*T = 2.37 - 0.052*T vanishes) or use "
                f"parameters with smaller Ks."
            )


# --------------------------------------------------------------------------- conditions (inputs)


class Conditions(NamedTuple):
    """What the sensor is exposed to: true field b_ref (n, 3) uT, temperature (n,) C, time (n,) s, run (n,)."""

    b_ref: np.ndarray
    temperature: np.ndarray
    time: np.ndarray
    run: np.ndarray

    @classmethod
    def from_data(cls, data: CalibrationData) -> "Conditions":
        """The reference field, temperature, time and runs of a recording (to simulate a sensor on them)."""
        if data.b_ref is None:
            raise ValueError("Conditions.from_data needs a recording with reference columns (b_ref).")
        return cls(np.asarray(data.b_ref), np.asarray(data.temperature), np.asarray(data.time),
                   np.asarray(data.run))

    @property
    def n(self) -> int:
        return int(self.temperature.shape[0])


def _check_conditions(c: Conditions) -> Conditions:
    b = np.asarray(c.b_ref, np.float64)
    n = b.shape[0] if b.ndim == 2 else -1
    if b.ndim != 2 or b.shape[1] != 3:
        raise ValueError(f"Conditions.b_ref must have shape (n, 3); got {b.shape}.")
    t, time = np.asarray(c.temperature, np.float64), np.asarray(c.time, np.float64)
    run = np.asarray(c.run).astype(np.int64)
    if t.shape != (n,) or time.shape != (n,) or run.shape != (n,):
        raise ValueError(f"Conditions.temperature, time and run must have shape ({n},).")
    for name, arr in (("b_ref", b), ("temperature", t), ("time", time)):
        if not np.isfinite(arr).all():
            raise ValueError(f"Conditions.{name} has non-finite values.")
    same_run = run[1:] == run[:-1]
    if np.unique(run).size != 1 + int(np.count_nonzero(~same_run)):
        raise ValueError("Conditions.run must be contiguous: each run id in one block of consecutive rows.")
    if np.any(np.diff(time)[same_run] <= 0):
        raise ValueError("Conditions.time must increase strictly within each run.")
    return Conditions(b, t, time, run)


def _rng(seed) -> np.random.Generator:
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer; got {seed!r}.")
    return np.random.default_rng(int(seed))


def draw_iid(
    n: int,
    seed: int = 0,
    field_range: float = 50.0,
    temp_range: tuple[float, float] = (0.0, 40.0),
    rate_hz: float = 4.0,
) -> Conditions:
    """The paper's section 4 design: independent rows, one run.

    ``b_ref`` uniform in ``+-field_range`` uT per axis, temperature uniform in
    ``temp_range`` C, ``time = arange(n) / rate_hz`` s, run id 1.
    """
    if int(n) < 1:
        raise ValueError(f"n must be a positive integer; got {n!r}.")
    lo, hi = map(float, temp_range)
    if not hi >= lo:
        raise ValueError(f"temp_range must be (low, high) with high >= low; got {temp_range!r}.")
    rng = _rng(seed)
    n = int(n)
    b = rng.uniform(-field_range, field_range, size=(n, 3))
    t = rng.uniform(lo, hi, size=n)
    return Conditions(b, t, np.arange(n, dtype=np.float64) / rate_hz, np.ones(n, dtype=np.int64))


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _wander(rng: np.random.Generator, s: np.ndarray, duration: float, amplitude: float) -> np.ndarray:
    """Slow smooth wander: three sinusoids with periods 0.5..2 run durations, rms ~ amplitude."""
    periods = duration * rng.uniform(0.5, 2.0, size=3)
    phases = rng.uniform(0.0, 2 * np.pi, size=3)
    return amplitude * np.sqrt(2.0 / 3.0) * np.sin(2 * np.pi * s[:, None] / periods + phases).sum(axis=1)


def _campaign_field(rng, s, duration, field_range, hold_s, segment_s, rotation_period_s) -> np.ndarray:
    """Alternating segments of held field steps and slow constant-magnitude rotations."""
    field = np.empty((s.size, 3))
    start, kind = 0.0, int(rng.integers(2))
    while start < duration:
        length = float(rng.uniform(*segment_s))
        sel = (s >= start) & (s < start + length)
        u = s[sel] - start
        if kind == 0:  # held steps: piecewise-constant field
            k = int(np.ceil(length / hold_s[0])) + 1
            ends = np.cumsum(rng.uniform(*hold_s, size=k))
            vectors = rng.uniform(-field_range, field_range, size=(k, 3))
            field[sel] = vectors[np.searchsorted(ends, u, side="right")]
        else:  # rotation: fixed magnitude, direction spiralling over the sphere
            mag = rng.uniform(0.4, 1.0) * field_range
            polar = np.pi * u / length
            azimuth = 2 * np.pi * u / rotation_period_s + rng.uniform(0, 2 * np.pi)
            dirs = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], 1)
            field[sel] = mag * dirs @ _random_rotation(rng).T
        start += length
        kind = 1 - kind
    return field


def draw_campaign(
    seed: int = 0,
    n_runs: int = 6,
    rate_hz: float = 4.0,
    *,
    rows_per_run: int | Sequence[int] = 800,
    run_kinds: Sequence[str] | None = None,
    field_range: float = 50.0,
    hold_s: tuple[float, float] = (10.0, 30.0),
    segment_s: tuple[float, float] = (40.0, 80.0),
    rotation_period_s: float = 60.0,
    room_temp: float = 24.0,
    peak_temp: float = 40.0,
    temp_wander: float = 0.3,
    coil_noise_sd: float = 0.02,
    gap_s: float = 60.0,
) -> Conditions:
    """A Helmholtz-coil campaign: ``n_runs`` runs sampled at ``rate_hz``, separated by gaps.

    Field (every run): alternating segments (``segment_s`` long) of held steps
    (piecewise-constant, uniform in ``+-field_range`` uT, each held ``hold_s`` seconds) and
    slow rotations (fixed magnitude 0.4..1 x ``field_range``, direction spiralling over the
    sphere, ``rotation_period_s`` per turn), plus coil noise ``coil_noise_sd`` uT.

    Temperature, by ``run_kinds`` (default alternating ``"thermal"``, ``"room"``, ...):
    ``"room"`` stays near ``room_temp`` with slow wander of about ``temp_wander`` C;
    ``"thermal"`` holds at room temperature, heats to ``peak_temp``, holds, then cools part
    of the way back (knots at 0, 10, 40, 55, 85 % of the run). The field keeps changing
    during ramps, so field and temperature are not confounded (unlike the real data).

    The default ``peak_temp`` is 40 C because :meth:`TrueParams.paper` is singular at
    45.6 C. Time is in seconds from 0; runs are ``gap_s`` seconds apart; run ids 1..n_runs.
    """
    rng = _rng(seed)
    if int(n_runs) < 1:
        raise ValueError(f"n_runs must be >= 1; got {n_runs!r}.")
    if rate_hz <= 0 or gap_s <= 0:
        raise ValueError(f"rate_hz and gap_s must be positive; got {rate_hz!r}, {gap_s!r}.")
    if not (0 < hold_s[0] <= hold_s[1] and 0 < segment_s[0] <= segment_s[1]):
        raise ValueError(f"hold_s and segment_s must be (low, high) positive ranges; got {hold_s!r}, {segment_s!r}.")
    rows = np.broadcast_to(np.asarray(rows_per_run, dtype=np.int64), (int(n_runs),))
    if np.any(rows < 2):
        raise ValueError(f"rows_per_run must be >= 2 for every run; got {rows_per_run!r}.")
    kinds = tuple(run_kinds) if run_kinds is not None else tuple(
        "thermal" if i % 2 == 0 else "room" for i in range(int(n_runs)))
    if len(kinds) != int(n_runs) or not set(kinds) <= {"room", "thermal"}:
        raise ValueError(f"run_kinds must list {n_runs} entries from ['room', 'thermal']; got {run_kinds!r}.")

    parts, start = [], 0.0
    for r, (m, kind) in enumerate(zip(rows, kinds), start=1):
        s = np.arange(m, dtype=np.float64) / rate_hz
        duration = m / rate_hz
        b = _campaign_field(rng, s, duration, field_range, hold_s, segment_s, rotation_period_s)
        b = b + rng.normal(0.0, coil_noise_sd, size=b.shape)
        t0 = room_temp + rng.uniform(-0.5, 0.5)
        if kind == "room":
            t = t0 + _wander(rng, s, duration, temp_wander)
        else:
            t_end = room_temp + (peak_temp - room_temp) * rng.uniform(0.1, 0.3)
            knots = duration * np.array([0.0, 0.10, 0.40, 0.55, 0.85, 1.0])
            t = np.interp(s, knots, [t0, t0, peak_temp, peak_temp, t_end, t_end])
            t = t + _wander(rng, s, duration, 0.1 * temp_wander)
        parts.append((b, t, start + s, np.full(m, r, dtype=np.int64)))
        start += duration + gap_s
    b, t, time, run = (np.concatenate(p) for p in zip(*parts))
    return Conditions(b, t, time, run)


_DESIGNS = {"iid": draw_iid, "campaign": draw_campaign}


# --------------------------------------------------------------------------- effects

_REGISTRY: dict[str, type["Effect"]] = {}
#: Registered effects by name (read-only view; new :class:`Effect` subclasses appear here).
EFFECTS: Mapping[str, type["Effect"]] = types.MappingProxyType(_REGISTRY)


def _axis(value, field: str) -> int:
    if value not in AXES:
        raise ValueError(f"{field} is {value!r}; it must be one of {list(AXES)}.")
    return AXES.index(value)


@dataclasses.dataclass(frozen=True)
class Effect(abc.ABC):
    """A distortion of the sensor reading, beyond the thermo-affine model.

    Subclasses are frozen dataclasses that set ``name`` and a one-sentence physical
    ``explanation``; defining one registers it (:data:`EFFECTS`, :func:`get_effect`).
    Parameters are dataclass fields; axes are named ``"x"``, ``"y"``, ``"z"``.

    ``apply`` works on whole (n, ...) arrays, rows ordered by run then time, and returns
    ``(b_meas, temperature)``: the distorted reading and the temperature the sensor
    element sees (which later effects use; the logged column is never changed).
    Effects that change what the sensor is exposed to (``thermal_lag``,
    ``timing_offset``) re-measure the noise-free part with ``measure(b_ref, T)``, the
    true inverse model, keeping the noise and earlier distortions additively; list them
    first when combining with nonlinear distortions.
    """

    name: ClassVar[str]
    explanation: ClassVar[str]

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        name = cls.__dict__.get("name")
        if name is None:
            return
        if not isinstance(cls.__dict__.get("explanation"), str):
            raise TypeError(f"Effect {cls.__name__} must set a one-sentence 'explanation'.")
        if name in _REGISTRY and _REGISTRY[name].__qualname__ != cls.__qualname__:
            raise ValueError(f"an effect named {name!r} is already registered ({_REGISTRY[name].__name__}).")
        _REGISTRY[name] = cls

    @abc.abstractmethod
    def apply(self, b_meas: np.ndarray, temperature: np.ndarray, time: np.ndarray, run: np.ndarray,
              b_ref: np.ndarray, key: jax.Array, *, measure: Measure | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        """Distorted ``(b_meas (n, 3), sensor temperature (n,))``."""

    def describe(self) -> dict:
        """``{"name": ..., **parameters}`` (the form :func:`simulate_from_config` accepts)."""
        return {"name": self.name, **dataclasses.asdict(self)}


def _add(b_meas, axis: int, delta) -> np.ndarray:
    out = np.array(b_meas, dtype=np.float64)
    out[:, axis] += delta
    return out


def _need(measure, name):
    if measure is None:
        raise ValueError(f"effect {name!r} re-measures the field and needs measure=TrueParams.measure.")
    return measure


def _run_starts(run: np.ndarray) -> np.ndarray:
    return np.concatenate([[True], run[1:] != run[:-1]])


def _hold_last(value: np.ndarray, has_value: np.ndarray, run: np.ndarray, initial: float = 0.0) -> np.ndarray:
    """Carry the last ``value`` where ``has_value`` forward within each run (``initial`` before any)."""
    starts = _run_starts(run)
    idx = np.where(has_value | starts, np.arange(value.size), 0)
    idx = np.maximum.accumulate(idx)
    v = np.where(has_value, value, initial)
    return v[idx]


@dataclasses.dataclass(frozen=True)
class AxisQuadratic(Effect):
    r"""``B_meas[out] += coeff * B_meas[inp]^2`` (paper: out ``y``, inp ``x``, coeff 0.01 /uT).

    Fields: ``out``, ``inp`` axes; ``coeff`` in 1/uT.
    """

    out: str = "y"
    inp: str = "x"
    coeff: float = 0.01
    name: ClassVar[str] = "axis_quadratic"
    explanation: ClassVar[str] = ("Bridge asymmetry and imperfect shielding make one axis respond to the square "
                                  "of the field along another.")

    def __post_init__(self):
        for f in ("out", "inp"):
            _axis(getattr(self, f), f)

    def apply(self, b_meas, temperature, time, run, b_ref, key, *, measure=None):
        i = _axis(self.inp, "inp")
        return _add(b_meas, _axis(self.out, "out"), self.coeff * b_meas[:, i] ** 2), temperature


@dataclasses.dataclass(frozen=True)
class CrossAxisQuadratic(Effect):
    r"""``B_meas[out] += coeff * B_meas[inp1] * B_meas[inp2]``.

    Fields: ``out``, ``inp1``, ``inp2`` axes; ``coeff`` in 1/uT.
    """

    out: str = "z"
    inp1: str = "x"
    inp2: str = "y"
    coeff: float = 0.005
    name: ClassVar[str] = "cross_axis_quadratic"
    explanation: ClassVar[str] = ("Nonlinear coupling between the bridges makes one axis respond to the product "
                                  "of the fields along two others.")

    def __post_init__(self):
        for f in ("out", "inp1", "inp2"):
            _axis(getattr(self, f), f)

    def apply(self, b_meas, temperature, time, run, b_ref, key, *, measure=None):
        j, k = _axis(self.inp1, "inp1"), _axis(self.inp2, "inp2")
        return _add(b_meas, _axis(self.out, "out"), self.coeff * b_meas[:, j] * b_meas[:, k]), temperature


@dataclasses.dataclass(frozen=True)
class Cubic(Effect):
    r"""``B_meas[out] += coeff * B_meas[inp]^3`` (saturation when ``coeff < 0``).

    Fields: ``out``, ``inp`` axes; ``coeff`` in 1/uT^2 (default -2e-5: -2.5 uT at 50 uT).
    """

    out: str = "x"
    inp: str = "x"
    coeff: float = -2e-5
    name: ClassVar[str] = "cubic"
    explanation: ClassVar[str] = "The magnetoresistive response flattens as the film approaches saturation."

    def __post_init__(self):
        for f in ("out", "inp"):
            _axis(getattr(self, f), f)

    def apply(self, b_meas, temperature, time, run, b_ref, key, *, measure=None):
        i = _axis(self.inp, "inp")
        return _add(b_meas, _axis(self.out, "out"), self.coeff * b_meas[:, i] ** 3), temperature


@dataclasses.dataclass(frozen=True)
class MagnitudeGain(Effect):
    r"""The gain depends on the field's magnitude, on every axis alike: ``B_meas *= 1 + g |B_meas|``.

    Acts on the whole reading (noise included, as the other reading distortions do); its catalogue twin
    (``magnitude_gain``) inverts it exactly. Field: ``g`` in 1/uT (default 2e-4: +1 % at |B_meas| = 50 uT).
    """

    g: float = 2e-4
    name: ClassVar[str] = "magnitude_gain"
    explanation: ClassVar[str] = ("The sensor's sensitivity changes with the strength of the field on every axis "
                                  "alike.")

    def __post_init__(self):
        if not np.isfinite(self.g):
            raise ValueError(f"g is {self.g!r}; it must be a finite number (1/uT).")

    def apply(self, b_meas, temperature, time, run, b_ref, key, *, measure=None):
        b = np.asarray(b_meas, dtype=np.float64)
        return b * (1.0 + self.g * np.linalg.norm(b, axis=1))[:, None], temperature


@dataclasses.dataclass(frozen=True)
class TemperatureQuadratic(Effect):
    r"""Offset curvature ``B_meas[axis] += coeff * (T_sensor - t_ref)^2``.

    Fields: ``axis``; ``coeff`` in uT/C^2; ``t_ref`` in C.
    """

    axis: str = "y"
    coeff: float = 0.002
    t_ref: float = 24.0
    name: ClassVar[str] = "temperature_quadratic"
    explanation: ClassVar[str] = "The bridge offset drifts nonlinearly with temperature, beyond the linear Ko term."

    def __post_init__(self):
        _axis(self.axis, "axis")

    def apply(self, b_meas, temperature, time, run, b_ref, key, *, measure=None):
        dt = np.asarray(temperature) - self.t_ref
        return _add(b_meas, _axis(self.axis, "axis"), self.coeff * dt * dt), temperature


@dataclasses.dataclass(frozen=True)
class ThermalLag(Effect):
    r"""The sensor element follows the logged temperature through a first-order lag.

    .. math::  \tau \dot T_s = T - T_s,\quad T_s = T \text{ at each run start},

    discretised as :class:`bayesmag._src.core.physics.ThermalLag` (so a fit with that transform
    can recover ``tau`` exactly). The reading is re-measured at :math:`T_s`; the logged
    temperature is unchanged. Field: ``tau`` in s.
    """

    tau: float = 30.0
    name: ClassVar[str] = "thermal_lag"
    explanation: ClassVar[str] = ("The sensor die heats and cools more slowly than the thermometer that logs the "
                                  "temperature.")

    def __post_init__(self):
        if not self.tau > 0:
            raise ValueError(f"tau is {self.tau!r}; it must be > 0 seconds.")

    def lagged(self, temperature, time, run) -> np.ndarray:
        """Sensor temperature :math:`T_s` (n,)."""
        t = jnp.asarray(temperature, dtype=jnp.float64)
        inputs = _physics.Inputs(jnp.zeros(t.shape + (3,)), t, jnp.asarray(time, jnp.float64), jnp.asarray(run))
        lag = _physics.ThermalLag()
        return np.asarray(lag(jnp.array([np.log(self.tau)]), inputs).t)

    def apply(self, b_meas, temperature, time, run, b_ref, key, *, measure=None):
        measure = _need(measure, self.name)
        ts = self.lagged(temperature, time, run)
        return b_meas + measure(b_ref, ts) - measure(b_ref, temperature), ts


@dataclasses.dataclass(frozen=True)
class TimingOffset(Effect):
    r"""The sensor stream lags the reference by ``delta`` s: reading at t = clean reading at t - delta.

    The exposure (field and temperature) is interpolated linearly within each run, held
    at the run's first/last sample beyond its ends, and re-measured. Field: ``delta`` in s
    (negative: the sensor leads).
    """

    delta: float = 0.5
    name: ClassVar[str] = "timing_offset"
    explanation: ClassVar[str] = ("The sensor and reference are sampled by different clocks, so the sensor "
                                  "row is logged a fixed latency after the field it saw.")

    def apply(self, b_meas, temperature, time, run, b_ref, key, *, measure=None):
        measure = _need(measure, self.name)
        temperature = np.asarray(temperature, np.float64)
        b_d, t_d = np.empty_like(b_ref), np.empty_like(temperature)
        bounds = np.flatnonzero(np.concatenate([_run_starts(run), [True]]))
        for lo, hi in zip(bounds[:-1], bounds[1:]):
            tr, tq = time[lo:hi], time[lo:hi] - self.delta
            t_d[lo:hi] = np.interp(tq, tr, temperature[lo:hi])
            for k in range(3):
                b_d[lo:hi, k] = np.interp(tq, tr, b_ref[lo:hi, k])
        return b_meas + measure(b_d, t_d) - measure(b_ref, temperature), t_d


@dataclasses.dataclass(frozen=True)
class Hysteresis(Effect):
    r"""Offset ``+h`` or ``-h`` on ``axis`` set by the field's history along that axis.

    ``mode="excursion"``: the sign of the last excursion of the true field component beyond
    ``+-threshold`` uT; ``mode="direction"``: the sign of the last sample-to-sample change of
    that component larger than ``min_step`` uT (direction of travel). Zero before the first
    event of each run. Fields: ``axis``; ``h``, ``threshold``, ``min_step`` in uT; ``mode``.
    """

    axis: str = "x"
    h: float = 0.2
    threshold: float = 25.0
    mode: str = "excursion"
    min_step: float = 0.5
    name: ClassVar[str] = "hysteresis"
    explanation: ClassVar[str] = ("The permalloy film keeps a remanent magnetisation whose sign follows the "
                                  "last large field excursion, shifting the bridge offset.")

    def __post_init__(self):
        _axis(self.axis, "axis")
        if self.mode not in ("excursion", "direction"):
            raise ValueError(f"mode is {self.mode!r}; it must be one of ['excursion', 'direction'].")
        if not (self.threshold >= 0 and self.min_step >= 0):
            raise ValueError(f"threshold and min_step must be >= 0 uT; got {self.threshold!r}, {self.min_step!r}.")

    def state(self, b_ref, run) -> np.ndarray:
        """(n,) magnetisation sign in {-1, 0, +1}."""
        f = np.asarray(b_ref)[:, _axis(self.axis, "axis")]
        if self.mode == "excursion":
            sign = np.where(f > self.threshold, 1.0, np.where(f < -self.threshold, -1.0, 0.0))
        else:
            d = np.diff(f, prepend=f[:1])
            d[_run_starts(run)] = 0.0
            sign = np.where(np.abs(d) > self.min_step, np.sign(d), 0.0)
        return _hold_last(sign, sign != 0, run)

    def apply(self, b_meas, temperature, time, run, b_ref, key, *, measure=None):
        return _add(b_meas, _axis(self.axis, "axis"), self.h * self.state(b_ref, run)), temperature


@dataclasses.dataclass(frozen=True)
class OffsetDrift(Effect):
    r"""Offset on ``axis`` drifting with time: ``rate (t - t_0) + step k_run + random walk``.

    ``k_run`` is the run's index (0, 1, ...) in sorted run ids; the random walk has
    increments :math:`\mathcal N(0, \mathrm{walk\_sd}^2 \Delta t)` (drawn from ``key``).
    Fields: ``axis``; ``rate`` in uT/s; ``step`` in uT per run; ``walk_sd`` in uT/sqrt(s).
    """

    axis: str = "x"
    rate: float = 1e-3
    step: float = 0.0
    walk_sd: float = 0.0
    name: ClassVar[str] = "offset_drift"
    explanation: ClassVar[str] = ("Ageing, stress relaxation and slow electronics drift move the offset over "
                                  "time and between sessions.")

    def __post_init__(self):
        _axis(self.axis, "axis")
        if not self.walk_sd >= 0:
            raise ValueError(f"walk_sd is {self.walk_sd!r}; it must be >= 0 uT/sqrt(s).")

    def apply(self, b_meas, temperature, time, run, b_ref, key, *, measure=None):
        time = np.asarray(time, np.float64)
        k_run = np.unique(run, return_inverse=True)[1].reshape(-1)
        drift = self.rate * (time - time[0]) + self.step * k_run
        if self.walk_sd > 0:
            dt = np.maximum(np.diff(time, prepend=time[:1]), 0.0)
            z = np.asarray(jax.random.normal(key, time.shape, dtype=jnp.float64))
            drift = drift + np.cumsum(self.walk_sd * np.sqrt(dt) * z)
        return _add(b_meas, _axis(self.axis, "axis"), drift), temperature


@dataclasses.dataclass(frozen=True)
class Periodic(Effect):
    r"""Sinusoidal interference ``amplitude * sin(2 pi t / period + phase)`` on ``axis``.

    Not a physics-catalogue effect: a stand-in for unexplained structure. Fields:
    ``axis``; ``amplitude`` in uT; ``period`` in s; ``phase`` in rad.
    """

    axis: str = "z"
    amplitude: float = 0.5
    period: float = 10.0
    phase: float = 0.0
    name: ClassVar[str] = "periodic"
    explanation: ClassVar[str] = "Nearby equipment (a pump, a fan, mains beating) adds a periodic stray field."

    def __post_init__(self):
        _axis(self.axis, "axis")
        if not self.period > 0:
            raise ValueError(f"period is {self.period!r}; it must be > 0 seconds.")

    def apply(self, b_meas, temperature, time, run, b_ref, key, *, measure=None):
        wave = self.amplitude * np.sin(2 * np.pi * np.asarray(time) / self.period + self.phase)
        return _add(b_meas, _axis(self.axis, "axis"), wave), temperature


def get_effect(name: str, **params) -> Effect:
    """The registered effect ``name`` with ``params`` (ValueError for an unknown name,
    TypeError for an unknown parameter; both list the valid set).

    Example:
      >>> get_effect("axis_quadratic", coeff=0.02).coeff
      0.02
    """
    if name not in _REGISTRY:
        raise ValueError(f"unknown effect {name!r}; valid effects: {sorted(_REGISTRY)}.")
    cls = _REGISTRY[name]
    valid = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(params) - set(valid))
    if unknown:
        raise TypeError(f"effect {name!r} has no parameter(s) {unknown}; valid parameters: {valid}.")
    return cls(**params)


def _effect(e) -> Effect:
    """An :class:`Effect` from an instance, a name or a config table ``{"name": ..., **params}``."""
    if isinstance(e, str):
        return get_effect(e)
    if isinstance(e, dict):
        if not isinstance(e.get("name"), str):
            raise TypeError(f"an effect table needs a 'name' (one of {sorted(_REGISTRY)}); got {e!r}.")
        return get_effect(e["name"], **{k: v for k, v in e.items() if k != "name"})
    if not isinstance(e, Effect):
        raise TypeError(f"effects must be Effect instances, effect names or tables {{name = ..., parameters}}; "
                        f"got {e!r}.")
    return e


# --------------------------------------------------------------------------- simulate


def _conditions(design, n, seed, design_kwargs) -> tuple[Conditions, str]:
    if isinstance(design, Conditions):
        if design_kwargs:
            raise TypeError(f"design is a Conditions; design keyword(s) {sorted(design_kwargs)} do not apply.")
        c = _check_conditions(design)
        if n is not None and n != c.n:
            raise ValueError(f"n is {n} but the given Conditions have {c.n} rows.")
        return c, "conditions"
    if design not in _DESIGNS:
        raise ValueError(f"design is {design!r}; it must be one of {sorted(_DESIGNS)} or a Conditions.")
    fn = _DESIGNS[design]
    valid = [p for p in inspect.signature(fn).parameters if p not in ("n", "seed")]
    unknown = sorted(set(design_kwargs) - set(valid))
    if unknown:
        raise TypeError(f"design {design!r} has no option(s) {unknown}; valid options: {valid}.")
    kw = dict(design_kwargs)
    if design == "iid":
        c = draw_iid(50_000 if n is None else n, seed, **kw)
    else:
        if n is not None:
            if "rows_per_run" in kw:
                raise ValueError("give n or rows_per_run for the campaign design, not both.")
            kw["rows_per_run"] = [len(a) for a in np.array_split(np.arange(int(n)), int(kw.get("n_runs", 6)))]
        c = draw_campaign(seed, **kw)
    return _check_conditions(c), design


def simulate(
    n: int | None = None,
    *,
    design: str | Conditions = "iid",
    seed: int = 0,
    params: TrueParams = TrueParams.paper(),
    noise_sd: float | Sequence[float] = 0.5,
    temp_noise_sd: float = 0.0,
    effects: Sequence[Effect | str | dict] = (),
    **design_kwargs,
) -> CalibrationData:
    r"""Simulate a calibration recording of a sensor with known parameters.

    .. math::  B_\mathrm{meas} = \mathrm{effects}\big((S + K_s T)^{-1}(B_\mathrm{ref} - O - K_o T)
               + \varepsilon\big), \quad \varepsilon_{k} \sim \mathcal N(0, \sigma_k^2)

    Args:
      n: rows. ``iid``: default 50 000 (the paper's smallest study); ``campaign``: split
        evenly over the runs (default ``n_runs x rows_per_run``).
      design: ``"iid"`` (:func:`draw_iid`), ``"campaign"`` (:func:`draw_campaign`) or a
        :class:`Conditions`.
      seed: one non-negative integer; the inputs use ``default_rng(seed)``, the noise
        ``default_rng([seed, 1])`` and effect ``i`` the key ``fold_in(PRNGKey(seed), i)``.
      params: true parameters (default the paper's Table 2).
      noise_sd: Gaussian noise sd on the reading, uT, scalar or per axis (paper: 0.5).
      temp_noise_sd: Gaussian noise sd on the *logged* temperature, C (the sensor sees the true one).
      effects: :class:`Effect` instances, names (default parameters) or tables as a config writes them
        (``{"name": "axis_quadratic", "coeff": 0.02}``), applied in order.
      **design_kwargs: options of the design function.

    Returns:
      :class:`CalibrationData` with ``b_ref`` the true field, ``b_meas`` the reading,
      ``temperature`` the logged temperature.

    Example:
      >>> d = simulate(1000, seed=1, effects=[get_effect("axis_quadratic")])
      >>> d.n, d.b_meas.shape
      (1000, (1000, 3))
    """
    if not isinstance(params, TrueParams):
        raise TypeError(f"params must be a TrueParams; got {type(params).__name__}.")
    sd = np.broadcast_to(np.asarray(noise_sd, dtype=np.float64), (3,))
    if np.any(sd < 0) or not temp_noise_sd >= 0:
        raise ValueError(f"noise_sd and temp_noise_sd must be >= 0; got {noise_sd!r}, {temp_noise_sd!r}.")
    effects = tuple(_effect(e) for e in effects)
    cond, label = _conditions(design, n, seed, design_kwargs)
    params.check_invertible(cond.temperature)

    rng = np.random.default_rng([int(seed), 1])
    b = params.measure(cond.b_ref, cond.temperature) + sd * rng.standard_normal((cond.n, 3))
    logged = cond.temperature + temp_noise_sd * rng.standard_normal(cond.n)
    t_sensor = cond.temperature
    if effects:
        base = jax.random.PRNGKey(int(seed))
        for i, e in enumerate(effects):
            b, t_sensor = e.apply(b, t_sensor, cond.time, cond.run, cond.b_ref, jax.random.fold_in(base, i),
                                  measure=params.measure)
            b, t_sensor = np.asarray(b, np.float64), np.asarray(t_sensor, np.float64)
    if not np.isfinite(b).all():
        raise ValueError("the simulated reading has non-finite values; check the effects' parameters.")
    names = ", ".join(e.name for e in effects) or "none"
    source = (f"simulated {label} (n={cond.n}, seed={seed}, noise_sd={noise_sd}, "
              f"temp_noise_sd={temp_noise_sd}, effects: {names})")
    return CalibrationData(b, logged, cond.b_ref, cond.time, cond.run, source)


_CONFIG_KEYS = ("n", "design", "seed", "params", "noise_sd", "temp_noise_sd", "effects")
#: Fewest rows a simulation config may ask for (a calibration of 8 parameters per axis needs many more).
SIMULATE_MIN_N = 50


def check_simulate_config(config: Mapping) -> None:
    """Check a ``[data.simulate]`` table without simulating; ValueError naming the key, the value and the valid set.

    ``n`` an integer >= :data:`SIMULATE_MIN_N` (or absent), ``seed`` an integer >= 0, ``noise_sd`` (scalar
    or 3 values) and ``temp_noise_sd`` finite and >= 0, ``design``, keys and effects known.
    """
    if not isinstance(config, Mapping):
        raise ValueError(f"the simulation config must be a mapping; got {type(config).__name__}.")
    design = config.get("design", "iid")
    if design not in _DESIGNS:
        raise ValueError(f"'design' = {design!r} is not known; it must be one of {sorted(_DESIGNS)}.")
    design_keys = [p for p in inspect.signature(_DESIGNS[design]).parameters if p not in ("n", "seed")]
    valid = list(_CONFIG_KEYS) + design_keys
    unknown = sorted(set(config) - set(valid))
    if unknown:
        raise ValueError(f"unknown simulation config key(s) {unknown}; valid keys for design {design!r}: {valid}.")
    seed = config.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"'seed' = {seed!r} must be an integer >= 0.")
    for key in ("noise_sd", "temp_noise_sd"):
        v = config.get(key, 0.0)
        vals = v if isinstance(v, (list, tuple)) else [v]
        ok = (len(vals) in ((1, 3) if key == "noise_sd" else (1,)) and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x >= 0 for x in vals))
        if not ok:
            raise ValueError(f"'{key}' = {v!r} must be a finite standard deviation >= 0"
                             + (" (uT; one value or one per axis)." if key == "noise_sd" else " (C)."))
    effects = config.get("effects", ())
    if not isinstance(effects, (list, tuple)):
        raise ValueError(f"'effects' = {effects!r} must be a list of effect names or tables with a 'name'.")
    for item in effects:
        spec = {"name": item} if isinstance(item, str) else dict(item) if isinstance(item, Mapping) else None
        if spec is None or "name" not in spec:
            raise ValueError(f"each effect must be a name or a mapping with a 'name'; got {item!r}.")
        try:
            get_effect(spec.pop("name"), **spec)
        except TypeError as e:
            raise ValueError(str(e)) from None
    _params_from_config(config.get("params"))
    n = config.get("n")
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < SIMULATE_MIN_N):
        raise ValueError(f"'n' = {n!r} must be an integer of at least {SIMULATE_MIN_N} (rows to simulate).")


def _params_from_config(value) -> TrueParams:
    if value is None or value == "paper":
        return TrueParams.paper()
    if isinstance(value, Mapping):
        if set(value) == {"theta"}:
            return TrueParams.from_theta(value["theta"])
        if set(value) == {"S", "Ks", "O", "Ko"}:
            return TrueParams(**value)
    raise ValueError(f"params must be 'paper', {{'theta': (3, 8)}} or {{'S', 'Ks', 'O', 'Ko'}}; got {value!r}.")


def simulate_from_config(config: Mapping) -> CalibrationData:
    """:func:`simulate` from a plain dict (e.g. a TOML table), validated loudly.

    Keys: ``n, design ("iid" | "campaign"), seed, params ("paper" | {"theta": ...} |
    {"S", "Ks", "O", "Ko"}), noise_sd, temp_noise_sd, effects`` (a list of names or of
    ``{"name": ..., **parameters}``) plus the chosen design's options. Unknown keys,
    effects and effect parameters raise ValueError naming them and the valid set.

    Example:
      >>> cfg = {"n": 500, "seed": 0, "effects": [{"name": "axis_quadratic", "coeff": 0.01}]}
      >>> simulate_from_config(cfg).n
      500
    """
    check_simulate_config(config)
    design = config.get("design", "iid")
    design_keys = [p for p in inspect.signature(_DESIGNS[design]).parameters if p not in ("n", "seed")]
    effects = []
    for item in config.get("effects", ()):
        spec = {"name": item} if isinstance(item, str) else dict(item) if isinstance(item, Mapping) else None
        if spec is None or "name" not in spec:
            raise ValueError(f"each effect must be a name or a mapping with a 'name'; got {item!r}.")
        try:
            effects.append(get_effect(spec.pop("name"), **spec))
        except TypeError as e:
            raise ValueError(str(e)) from None
    kw = {k: v for k, v in config.items() if k in design_keys}
    for k in ("temp_range", "hold_s", "segment_s"):
        if k in kw:
            kw[k] = tuple(kw[k])
    return simulate(
        config.get("n"),
        design=design,
        seed=config.get("seed", 0),
        params=_params_from_config(config.get("params")),
        noise_sd=config.get("noise_sd", 0.5),
        temp_noise_sd=config.get("temp_noise_sd", 0.0),
        effects=effects,
        **kw,
    )
