r"""Catalogue of candidate physics: small named model extensions that discovery can name.

Each entry is one frozen class (a :class:`~bayesmag._src.core.physics.Term` or an
:class:`~bayesmag._src.core.physics.InputTransform`) with a one-sentence physical
``explanation``, its own parameters (in physical units) and, for linear terms, exact
design columns. All are registered in :data:`~bayesmag._src.core.physics.EXTRA_TERMS`, so a
``bayesmag run`` config can use them directly::

    [physics]
    extra_terms = ["cross_axis_quadratic", {name = "thermal_lag", tau0 = 40.0},
                   {name = "hysteresis", axis = "x", mode = "excursion", threshold = 25.0}]

Terms act on the *measured* field ``b`` (uT), the logged temperature ``t`` (C), ``time``
(s) and ``run`` of :class:`~bayesmag._src.core.physics.Inputs`; every output axis gets its
own coefficients. Conventions of each parameter are in the class docstrings.

=======================  ==========  =============================================  =====================
name                     kind        parameters per output axis                     simulator effect
=======================  ==========  =============================================  =====================
axis_quadratic           linear      q_xx q_yy q_zz (1/uT)                          axis_quadratic
cross_axis_quadratic     linear      q_xy q_xz q_yz (1/uT)                          cross_axis_quadratic
cubic_nonlinearity       linear      c_x c_y c_z (1/uT^2)                           cubic
temperature_quadratic    linear      Ko2 (uT/C^2) [+ Ks2_x Ks2_y Ks2_z (1/C^2)]     temperature_quadratic
thermal_lag              transform   log_tau (tau in s; nodes = 1 or 2)             thermal_lag
timing_offset            transform   delta (s)                                      timing_offset
magnitude_gain           transform   g (1/reading unit)                             magnitude_gain
hysteresis               linear      h (uT)                                         hysteresis
offset_drift             linear      drift_rate (uT/s) [+ run_step (uT/run)]        offset_drift
run_offset               linear      o_<run> per run after the first (uT)           (none)
run_step                 linear      step (uT) from time ``at`` inside run ``run_id``   (none)
=======================  ==========  =============================================  =====================

Every class also carries its discovery registry entry (:class:`Entry`): requirements, scope
(one channel, or the whole sensor), search grid, plain-words description, the variable it is
drawn against and a plausibility check of its nonlinear parameter. Adding a term is one class
(plus its tests); discovery iterates :data:`CATALOGUE` and has no per-name branches. A class
defined outside this module joins every registry with :func:`register` (``docs/extending.md``).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from bayesmag._src.core import physics as _physics
from bayesmag._src.core.physics import EXTRA_TERMS, InputTransform, Inputs, Term

__all__ = ["CATALOGUE", "make_extra", "AxisQuadratic", "CrossAxisQuadratic", "CubicNonlinearity", "TemperatureQuadratic",
           "ThermalLag", "TimingOffset", "MagnitudeGain", "Hysteresis", "OffsetDrift", "RunOffset", "RunStep", "SIMULATOR_NAMES", "explanation",
           "Entry", "Setting", "SearchContext", "register", "unregister"]

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


# --------------------------------------------------------------------------- registry interface


@dataclasses.dataclass(frozen=True)
class SearchContext:
    """What a catalogue entry needs to lay out its search grid on one recording.

    ``t0`` reference temperature (C); ``dt`` median sampling step (s); ``time_ref`` first time
    stamp; ``runs`` the run ids in order; ``run_span`` median run duration (s); ``reach`` 98th
    percentile of |measured field| per channel; ``step_noise`` sd of the row-to-row change of
    the measured field per channel (noise scale); ``cal`` the baseline thermo-affine
    coefficients of each output (``S_x S_y S_z Ks_x Ks_y Ks_z O Ko``) and ``ref_reach`` the 98th
    percentile of |reference field| per axis (for entries driven by the calibrated field);
    ``heated_span`` the longest run over which the logged temperature changes by >= 1 C (s; the
    longest run when none does); ``run_bounds`` ``(run, first time, last time)`` per run;
    ``magnitude_reach`` the 98th percentile of the measured field's magnitude |u|."""

    t0: float = 0.0
    dt: float = 1.0
    time_ref: float = 0.0
    runs: tuple = (0,)
    run_span: float = 1.0
    reach: tuple = (1.0, 1.0, 1.0)
    step_noise: tuple = (0.1, 0.1, 0.1)
    cal: tuple = ()
    ref_reach: tuple = ()
    heated_span: float = 1.0
    run_bounds: tuple = ()
    magnitude_reach: float = 1.0


@dataclasses.dataclass(frozen=True)
class Setting:
    """One concrete point of an entry's search grid: the component, the columns of its
    features that are used (None: all) and, for a transform, its fixed nonlinear value."""

    component: object
    cols: tuple | None = None
    nl: float | None = None


class Entry:
    """Registry interface every catalogue class carries (so adding a term is one class).

    * ``requires``: what the recording must have: ``"time"``, ``"temperature"``, ``"runs"``
      (two or more runs);
    * ``scope``: ``"channel"`` (a distortion of one sensor reading, or of one calibrated
      output) or ``"sensor"`` (a transform of the whole input series);
    * ``simulator_name``: the :mod:`bayesmag.simulate` effect it represents (its twin), or None;
    * :meth:`grid` the settings tried on channel ``c`` (None for sensor-scope entries);
    * :meth:`describe` a plain-words phrase for the used columns;
    * :meth:`depends_on` the variable the effect is drawn against;
    * :meth:`implausible` a reason why a fitted nonlinear value is not this physics (or None);
    * ``localised``: ``"run"`` for an effect that is constant within each run and may sit in
      one run only (discovery then also scores it by run, not only by time block), else None;
    * ``frames``: where a channel-scope entry is tried (``"sensor"`` channels, calibrated ``"output"`` axes);
    * ``located``: the name of a field that places the effect in time (a step's ``at``): after
      selection discovery refines it and states it with an interval; :meth:`located_grid` the values tried;
    * :meth:`canonical` the component with its starting values reset (one compiled transform per form);
    * :meth:`variants` alternative forms tried after selection (e.g. a two-node heat path);
    * ``start_field``: a transform's field holding the starting value of its nonlinear parameter, and
      :meth:`started` the component started at a fitted value (what findings.json's ``extra_terms`` give);
    * :meth:`refine_step` the half-width of the first window in which a transform's value is refined;
    * ``rivals``: entries whose effect this one can take up on a recording (per-run offsets take up a
      thermal lag on runs with steady temperature ramps, or a drift): when a rival could not be
      searched (a column it needs is missing, or the time column's unit is suspect) a finding of this
      entry says so instead of stating its ``explanation`` as the cause.
    """

    requires: ClassVar[tuple] = ()
    scope: ClassVar[str] = "channel"
    localised: ClassVar[str | None] = None
    simulator_name: ClassVar[str | None] = None
    frames: ClassVar[tuple] = ("sensor", "output")
    located: ClassVar[str | None] = None
    start_field: ClassVar[str | None] = None
    rivals: ClassVar[tuple] = ()

    def canonical(self):
        return type(self)()

    def started(self, value: float):
        """The component with its nonlinear parameter starting at the fitted ``value`` (unchanged for a linear term)."""
        return self

    def refine_step(self, value: float) -> float:
        """Half-width of the first refinement window around a transform's grid value ``value``."""
        return 0.25 * max(abs(float(value)), 1e-3)

    def variants(self) -> tuple:
        return ()

    def located_grid(self, ctx: SearchContext, k: int = 41):
        return np.array([])

    @classmethod
    def grid(cls, ctx: SearchContext, c: int | None) -> list:
        return [Setting(cls())]

    def describe(self, cols) -> str:
        return self.name.replace("_", " ")

    def depends_on(self, cols) -> str:
        return "time"

    def implausible(self, value: float, ctx: SearchContext) -> str | None:
        return None


def _cols_names(names, cols):
    return [names[i] for i in (cols if cols is not None else range(len(names)))]


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
class AxisQuadratic(Term, Entry):
    r"""Squares of the measured field: :math:`\sum_j q_{jj} B_j^2` (``q`` in 1/uT)."""

    t0: float = 0.0
    thermal: bool = False
    name: ClassVar[str] = "axis_quadratic"
    temperature_centred: ClassVar[bool] = True       # T only as T - t0 (or not at all): physics.centred
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

    simulator_name: ClassVar[str] = "axis_quadratic"

    @classmethod
    def grid(cls, ctx, c):
        return [Setting(cls())]

    def describe(self, cols):
        return "reading gains " + " + ".join(f"B{n[2]}^2" for n in _cols_names(("q_xx", "q_yy", "q_zz"), cols)) + " terms"

    def depends_on(self, cols):
        return "B" + "xyz"[(cols or (0,))[0] % 3]


@dataclasses.dataclass(frozen=True)
class CrossAxisQuadratic(Term, Entry):
    r"""Products of two measured field components: :math:`q_{xy} B_x B_y + q_{xz} B_x B_z + q_{yz} B_y B_z`."""

    t0: float = 0.0
    thermal: bool = False
    name: ClassVar[str] = "cross_axis_quadratic"
    temperature_centred: ClassVar[bool] = True       # T only as T - t0 (or not at all): physics.centred
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

    simulator_name: ClassVar[str] = "cross_axis_quadratic"

    def describe(self, cols):
        pairs = {"q_xy": "Bx*By", "q_xz": "Bx*Bz", "q_yz": "By*Bz"}
        return "reading gains " + " + ".join(pairs[n] for n in _cols_names(tuple(pairs), cols)) + " terms"

    def depends_on(self, cols):
        return ("Bx", "Bx", "By")[(cols or (0,))[0] % 3]


@dataclasses.dataclass(frozen=True)
class CubicNonlinearity(Term, Entry):
    r"""Cubes of the measured field: :math:`\sum_j c_j B_j^3` (``c`` in 1/uT^2; saturation flattens the response)."""

    t0: float = 0.0
    thermal: bool = False
    name: ClassVar[str] = "cubic_nonlinearity"
    temperature_centred: ClassVar[bool] = True       # T only as T - t0 (or not at all): physics.centred
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

    simulator_name: ClassVar[str] = "cubic"

    def describe(self, cols):
        return "reading gains " + " + ".join(f"B{n[2]}^3" for n in _cols_names(("c_x", "c_y", "c_z"), cols)) + " terms"

    def depends_on(self, cols):
        return "B" + "xyz"[(cols or (0,))[0] % 3]


@dataclasses.dataclass(frozen=True)
class TemperatureQuadratic(Term, Entry):
    r"""Second-order thermal terms: :math:`K_{o2} T_c^2` and, with ``scale=True``, :math:`\sum_j K_{s2,j} T_c^2 B_j`.

    ``T_c = T - t0`` (C). ``Ko2`` in uT/C^2, ``Ks2_j`` in 1/C^2. With ``linear=True`` the
    first-order columns ``Ko1 T_c`` [and ``Ks1_j T_c B_j``] follow (for a distortion of the
    reading, which reaches the output through ``S + Ks T_c``). With ``cubic=True`` a
    further :math:`K_{o3} T_c^3` (uT/C^3): an offset curvature of the sensor's own reading
    reaches the calibrated output multiplied by the temperature-dependent gain
    :math:`S + K_s T`, i.e. as a cubic in T (strongly so on an axis whose gain changes a lot
    with temperature, such as y of the paper's sensor). Column order: Ko2, [Ko3], [Ks2_j], [Ko1, [Ks1_j]].
    """

    t0: float = 0.0
    scale: bool = False
    cubic: bool = False
    linear: bool = False
    name: ClassVar[str] = "temperature_quadratic"
    temperature_centred: ClassVar[bool] = True       # T only as T - t0 (or not at all): physics.centred
    degree: ClassVar[int] = 2           # T^2 and T^2 B_j: no input beyond the second power
    explanation: ClassVar[str] = ("The bridge offset (and sensitivity) drifts nonlinearly with temperature, beyond "
                                  "the linear Ko (and Ks) coefficients.")

    def param_names(self):
        return (("Ko2",) + (("Ko3",) if self.cubic else ())
                + (("Ks2_x", "Ks2_y", "Ks2_z") if self.scale else ())
                + ((("Ko1",) + (("Ks1_x", "Ks1_y", "Ks1_z") if self.scale else ())) if self.linear else ()))

    def linear_in_params(self):
        # its field ``linear`` (the first-order columns) hides Term.linear: linear in its parameters either way
        return True

    def features(self, inputs):
        tc = inputs.t - self.t0
        tc2 = (tc * tc)[..., None]
        cols = [tc2]
        if self.cubic:
            cols.append(tc2 * tc[..., None])
        if self.scale:
            cols.append(tc2 * inputs.b)
        if self.linear:
            cols.append(tc[..., None])
            if self.scale:
                cols.append(tc[..., None] * inputs.b)
        return jnp.concatenate(cols, axis=-1) if len(cols) > 1 else tc2

    requires: ClassVar[tuple] = ("temperature",)
    simulator_name: ClassVar[str] = "temperature_quadratic"

    @classmethod
    def grid(cls, ctx, c):
        # the channel's offset curving with T, or its gain (T^2 times its own reading)
        # with the first-order column too: a curvature about another temperature, (T - Tr)^2 =
        # Tc^2 + 2 (T0 - Tr) Tc + const, is not absorbed by Ko once it passes through S + Ks Tc
        return [Setting(cls(t0=ctx.t0, linear=True), cols=(0, 1)),
                Setting(cls(t0=ctx.t0, scale=True, linear=True), cols=(1 + c, 5 + c))]

    def describe(self, cols):
        if cols is not None and self.scale and all(1 <= i <= 3 or 5 <= i <= 7 for i in cols):
            return f"gain varies with (T-T0)^2 (T0 = {self.t0:.3g} C)"
        return f"offset varies with (T-T0)^2 (T0 = {self.t0:.3g} C)"

    def depends_on(self, cols):
        return "T"


#: Excursion thresholds discovery tries, as fractions of an axis' reach. A threshold between two of the field's
#: excursion peaks other than the true one flips the modelled state at the wrong excursions; with 0.3 / 0.5 / 0.7
#: 4 of 20 simulated hysteresis campaigns (threshold 15-30 uT) were missed (``benchmarks/bench_discovery.py``).
HYSTERESIS_FRACTIONS = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)


@dataclasses.dataclass(frozen=True)
class Hysteresis(Term, Entry):
    r"""Offset :math:`h\,s(t)` with :math:`s \in \{-1, 0, +1\}` set by the history of measured field ``axis``.

    ``mode="excursion"``: ``s`` is the sign of the last excursion of the measured component
    beyond ``+-threshold`` uT. ``mode="direction"``: ``s`` is the sign of the last change
    ``B(t) - B(t - lag samples)`` larger than ``min_step`` uT (direction of travel; the lag
    averages down the sensor noise). ``s = 0`` before the first event of each run; with
    ``across_runs=True`` the state is held across the gaps between runs (remanence survives
    a power cycle), ``s = 0`` only before the first event of the recording.
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
    across_runs: bool = False
    name: ClassVar[str] = "hysteresis"
    history: ClassVar[bool] = True        # the state is set by earlier rows: Term.history
    temperature_centred: ClassVar[bool] = True       # T only as T - t0 (or not at all): physics.centred
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
        run = jnp.zeros_like(inputs.run) if self.across_runs else inputs.run
        return hysteresis_state(self.drive(inputs), run, level, mode=self.mode, lag=int(self.lag))

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

    def history_settled(self, inputs: Inputs) -> bool:
        """True if ``inputs`` alone set the state of its last row: its run starts within ``inputs`` (not with
        ``across_runs``), or an event of that run lies in it (in ``direction`` mode at least ``lag`` rows after
        the start of ``inputs``, whose change is then known)."""
        f, run = np.asarray(self.drive(inputs), np.float64), np.asarray(inputs.run)
        n = f.size
        if n == 0:
            return False
        if not self.across_runs and (run[1:] != run[:-1]).any():
            return True                           # the last row's run starts inside: its state starts at 0 there
        if self.mode == "excursion":
            event = np.abs(f) > self.threshold
        else:
            lag = int(self.lag)
            same = (run[lag:] == run[:-lag]) | self.across_runs
            event = np.abs(np.where(same, f[lag:] - f[:-lag], 0.0)) > self.min_step
        return bool(event.any())

    simulator_name: ClassVar[str] = "hysteresis"

    @classmethod
    def grid(cls, ctx, c):
        """Excursion thresholds at :data:`HYSTERESIS_FRACTIONS` of the axis' reach (raw and calibrated), and the
        direction mode; reset at each run or held across runs."""
        out = []
        for k, ax in enumerate(_AXES):
            m = float(ctx.reach[k])
            if m <= 0:
                continue
            for across in (False, True):
                for frac in HYSTERESIS_FRACTIONS:
                    out.append(Setting(cls(axis=ax, mode="excursion", threshold=round(frac * m, 4),
                                           across_runs=across)))
                out.append(Setting(cls(axis=ax, mode="direction", min_step=round(6.0 * float(ctx.step_noise[k]), 4),
                                       lag=4, across_runs=across)))
            if ctx.cal and ctx.ref_reach:
                # excursions of the calibrated field: a fixed field threshold even where the
                # channel's gain changes with temperature
                coef = tuple(round(float(v), 10) for v in ctx.cal[k])
                for frac in HYSTERESIS_FRACTIONS:
                    out.append(Setting(cls(axis=ax, mode="excursion", threshold=round(frac * float(ctx.ref_reach[k]), 4),
                                           t0=ctx.t0, cal=coef)))
        return out

    def describe(self, cols):
        how = (f"the last excursion of B{self.axis} beyond +-{self.threshold:.3g}" if self.mode == "excursion"
               else f"the direction of travel of B{self.axis}")
        return (f"offset switches with {how} (remanent state"
                + (", held across the gaps between runs)" if self.across_runs else ", reset at each run)"))

    def depends_on(self, cols):
        return f"dir{self.axis}" if self.mode == "direction" else f"B{self.axis}"


@dataclasses.dataclass(frozen=True)
class OffsetDrift(Term, Entry):
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
    temperature_centred: ClassVar[bool] = True       # T only as T - t0 (or not at all): physics.centred
    degree: ClassVar[int] = 0                        # reads only time and run ids: no power of a noisy input
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

    requires: ClassVar[tuple] = ("time",)
    simulator_name: ClassVar[str] = "offset_drift"

    @classmethod
    def grid(cls, ctx, c):
        return [Setting(cls(time_ref=ctx.time_ref, run_ref=int(ctx.runs[0]), rate=True, steps=False))]

    def describe(self, cols):
        return "offset drifts linearly in time"


@dataclasses.dataclass(frozen=True)
class RunOffset(Term, Entry):
    r"""A separate offset for each run after the first: ``sum_k o_k [run == runs[k]]``, k >= 1 (uT).

    Power cycling and set/reset pulses re-seat the bridge offset between runs; ``runs`` lists
    the run ids (the first is the reference). Parameters ``o_<run>``.
    """

    runs: tuple = (0, 1)
    name: ClassVar[str] = "run_offset"
    temperature_centred: ClassVar[bool] = True       # T only as T - t0 (or not at all): physics.centred
    degree: ClassVar[int] = 0                        # reads only run ids: no power of a noisy input
    requires: ClassVar[tuple] = ("runs",)
    localised: ClassVar[str | None] = "run"
    #: a thermal lag on runs with steady ramps (Ko tau dT/dt, a constant per run), a drift, or a step inside a run
    #: also give each run its own mean offset
    rivals: ClassVar[tuple] = ("thermal_lag", "offset_drift", "run_step")
    explanation: ClassVar[str] = ("Power cycling and set/reset pulses re-seat the bridge offset, so the offset steps "
                                  "between runs.")

    def __post_init__(self):
        object.__setattr__(self, "runs", tuple(int(r) for r in self.runs))
        if len(self.runs) < 2 or len(set(self.runs)) != len(self.runs):
            raise ValueError(f"run_offset runs is {self.runs!r}; it must list two or more distinct run ids.")

    def param_names(self):
        return tuple(f"o_{r}" for r in self.runs[1:])

    def bound_runs(self):
        return tuple(int(r) for r in self.runs)

    def restricted(self, runs):
        kept = tuple(r for r in self.runs if int(r) in runs)
        return dataclasses.replace(self, runs=kept) if len(kept) >= 2 else None

    def features(self, inputs):
        return (inputs.run[..., None] == jnp.asarray(self.runs[1:])).astype(inputs.t.dtype)

    @classmethod
    def grid(cls, ctx, c):
        return [Setting(cls(runs=tuple(ctx.runs)))]

    def describe(self, cols):
        if cols is None or len(cols) == len(self.runs) - 1:
            return "offset steps between runs"
        which = ", ".join(str(self.runs[1:][c]) for c in cols)
        return f"offset of run{'s' if len(cols) > 1 else ''} {which} differs from the other runs'"

    def depends_on(self, cols):
        return "run"


@dataclasses.dataclass(frozen=True)
class RunStep(Term, Entry):
    r"""The offset of one run steps by a constant at time ``at`` inside it: ``step [run == run_id, time >= at]`` (uT).

    A set/reset flip, a power cycle without a new run, or a knock re-seats the bridge offset
    part-way through a run. Distinct from ``run_offset`` (a constant for a *whole* run): the step
    sits inside the run, at a time discovery locates (``at``, s) and states with an interval.
    Parameter ``step`` (sensor units where it distorts a channel).
    """

    run_id: int = 0
    at: float = 0.0
    name: ClassVar[str] = "run_step"
    temperature_centred: ClassVar[bool] = True       # T only as T - t0 (or not at all): physics.centred
    degree: ClassVar[int] = 0                        # reads only run and time: no power of a noisy input
    requires: ClassVar[tuple] = ("time",)
    frames: ClassVar[tuple] = ("sensor",)
    located: ClassVar[str | None] = "at"
    #: Candidate step times per run: these fractions of the run (the ends are run offsets).
    FRACTIONS: ClassVar[tuple] = (1 / 6, 2 / 6, 3 / 6, 4 / 6, 5 / 6)
    explanation: ClassVar[str] = ("A set/reset flip, a power cycle or a mechanical knock re-seats the bridge offset "
                                  "part-way through a run, so the reading steps by a constant from that moment on.")

    def param_names(self):
        return ("step",)

    def bound_runs(self):
        return (int(self.run_id),)

    def restricted(self, runs):
        return self if int(self.run_id) in runs else None

    def features(self, inputs):
        on = (inputs.run == int(self.run_id)) & (inputs.time >= self.at)
        return on.astype(inputs.t.dtype)[..., None]

    @classmethod
    def grid(cls, ctx, c):
        return [Setting(cls(run_id=int(r), at=round(float(a + f * (b - a)), 6)))
                for r, a, b in ctx.run_bounds for f in cls.FRACTIONS if b > a]

    def located_grid(self, ctx, k=41):
        """Step times tried when the step is refined: +-1/6 of its run around ``at`` (the spacing of
        the search grid), inside the run."""
        for r, a, b in ctx.run_bounds:
            if int(r) == int(self.run_id):
                w = (b - a) / 6
                lo, hi = max(a + 0.02 * (b - a), self.at - w), min(b - 0.02 * (b - a), self.at + w)
                return np.linspace(lo, hi, k)
        return np.array([self.at])

    def describe(self, cols):
        return f"offset steps inside run {self.run_id} at t = {self.at:.6g} s (stays stepped to the run's end)"

    def depends_on(self, cols):
        return "time"


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
class ThermalLag(_physics.ThermalLag, Entry):
    r"""Sensor temperature as a lag of the logged temperature: one node, or a housing and a die node.

    ``nodes=1``: :class:`bayesmag._src.core.physics.ThermalLag`, :math:`\tau \dot T_s = T - T_s`.
    ``nodes=2``: the heat reaches the die through its housing, :math:`\tau_h \dot T_h = T - T_h`,
    :math:`\tau_d \dot T_s = T_h - T_s` with :math:`\tau_h = \text{split}\,\tau`,
    :math:`\tau_d = (1 - \text{split})\,\tau`. In both forms ``tau`` is the *mean delay* of the
    heat path (the lag of the die behind a steady ramp; :math:`\tau_h + \tau_d` for two nodes).
    Parameter ``log_tau``; ``tau0`` is the starting value in seconds; each node starts in
    equilibrium with the log at every run start.

    Example:
      >>> import numpy as np; from bayesmag._src.core.physics import Inputs
      >>> t = np.arange(2000.0); x = Inputs(np.zeros((2000, 3)), t / 60, t, np.zeros(2000, int))
      >>> lag = ThermalLag(nodes=2)(np.array([np.log(120.0)]), x).t
      >>> round(float(x.t[-1] - lag[-1]) * 60, 1)    # 1 C/min: the die trails by tau (less dt/2 per node)
      119.0
    """

    nodes: int = 1
    split: float = 0.5
    explanation: ClassVar[str] = ("The sensor die heats and cools more slowly than the thermometer that logs the "
                                  "temperature, so it sees a lagged temperature.")
    requires: ClassVar[tuple] = ("time", "temperature")
    scope: ClassVar[str] = "sensor"
    simulator_name: ClassVar[str] = "thermal_lag"
    temperature_centred: ClassVar[bool] = True       # one or two unit-gain linear filters: physics.centred
    #: A lag shorter than this many samples is smoothing of the temperature log, not heat flow.
    MIN_SAMPLES: ClassVar[float] = 10.0
    #: Shortest lag searched (s), and the search's upper cap (s): half the longest heated run, at most TAU_MAX.
    TAU_MIN: ClassVar[float] = 1.0
    TAU_MAX: ClassVar[float] = 900.0

    def __post_init__(self):
        if int(self.nodes) not in (1, 2):
            raise ValueError(f"thermal_lag nodes is {self.nodes!r}; it must be 1 (one node) or 2 (housing and die).")
        if not 0.0 < float(self.split) < 1.0:
            raise ValueError(f"thermal_lag split is {self.split!r}; it must lie strictly between 0 and 1 "
                             f"(the housing's share of the mean delay).")

    def __call__(self, params, inputs):
        if int(self.nodes) == 1:
            return super().__call__(params, inputs)
        tau = params[0]
        first = super().__call__(jnp.atleast_1d(tau + jnp.log(self.split)), inputs)
        return super().__call__(jnp.atleast_1d(tau + jnp.log(1.0 - self.split)), first)

    start_field: ClassVar[str] = "tau0"

    def canonical(self):
        return ThermalLag(nodes=int(self.nodes), split=float(self.split))

    def started(self, value):
        return dataclasses.replace(self, tau0=round(float(np.exp(value)), 4))

    def refine_step(self, value):
        return 0.35                                   # in log tau: the grid is ~1.8x apart

    def variants(self):
        return (ThermalLag(tau0=self.tau0, nodes=2, split=0.5),) if int(self.nodes) == 1 else ()

    @classmethod
    def grid(cls, ctx, c):
        lo = max(cls.MIN_SAMPLES * ctx.dt, cls.TAU_MIN)
        hi = max(2 * lo, min(cls.TAU_MAX, ctx.heated_span / 2))
        k = max(4, int(np.ceil(np.log(hi / lo) / np.log(1.8))) + 1)
        return [Setting(cls(tau0=float(t)), nl=float(np.log(t))) for t in np.geomspace(lo, hi, k)]

    def describe(self, cols):
        if int(self.nodes) == 2:
            return "temperature the sensor sees lags the logged temperature (through its housing: two nodes)"
        return "temperature the sensor sees lags the logged temperature"

    def depends_on(self, cols):
        return "dT/dt"

    def implausible(self, value, ctx):
        tau = float(np.exp(value))
        if tau < self.MIN_SAMPLES * ctx.dt:
            return (f"tau = {tau:.3g} s is under {self.MIN_SAMPLES:g} samples ({self.MIN_SAMPLES * ctx.dt:.3g} s): "
                    f"that smooths the noise of the temperature log; it is not heat flow")
        # each run starts in equilibrium, so a lag longer than the run is still seen (the die's
        # response bends over the run): identified up to twice the longer of the longest heated run
        # and the median run (never stricter than b64e352's 2x median run, which named a 185 s lag
        # in runs of 84-119 s that "longer than the longest heated run" threw away)
        limit = 2.0 * max(ctx.heated_span, ctx.run_span)
        if tau > limit:
            return (f"tau = {tau:.3g} s is longer than twice the longest run over which the temperature changes "
                    f"({ctx.heated_span:.3g} s) and twice the median run ({ctx.run_span:.3g} s): not identified")
        return None


@dataclasses.dataclass(frozen=True)
class TimingOffset(InputTransform, Entry):
    r"""The sensor stream is delayed by ``delta`` s against the reference.

    The row logged at time :math:`t` saw the field of time :math:`t - \delta`, so the
    calibrated field at :math:`t` uses the readings (and temperature) interpolated at
    :math:`t + \delta`, linearly within each run and held at the run's ends. Parameter
    ``delta`` in s (positive: the sensor lags); ``delta0`` is its starting value.
    """

    delta0: float = 0.0
    name: ClassVar[str] = "timing_offset"
    temperature_centred: ClassVar[bool] = True       # T only as T - t0 (or not at all): physics.centred
    explanation: ClassVar[str] = ("The sensor and the reference are sampled by different clocks, so each sensor row "
                                  "is logged a fixed latency after the field it saw.")

    requires: ClassVar[tuple] = ("time", "increasing_time")
    scope: ClassVar[str] = "sensor"
    simulator_name: ClassVar[str] = "timing_offset"

    @classmethod
    def grid(cls, ctx, c):
        return [Setting(cls(delta0=float(d)), nl=float(d)) for d in np.arange(-8, 9) * ctx.dt / 2 if d != 0]

    def describe(self, cols):
        return "sensor stream is delayed against the reference"

    def depends_on(self, cols):
        return "dBx/dt"

    def implausible(self, value, ctx):
        if abs(value) > 10 * ctx.dt:
            return f"delta = {value:.3g} s is more than 10 samples: not a clock latency"
        return None

    start_field: ClassVar[str] = "delta0"

    def canonical(self):
        return TimingOffset()

    def started(self, value):
        return dataclasses.replace(self, delta0=round(float(value), 4))

    def memory_rows(self, params, dt):
        # interpolation between the neighbours of t + delta, clamped to the run's first and last rows
        return int(np.ceil(abs(float(params[0])) / max(float(dt), 1e-12))) + 2

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


def magnitude_of_undistorted(m, g):
    r"""|u0| from |u| = m for a reading :math:`u = (1 + g|u_0|)\,u_0`: the root of
    :math:`g x^2 + x - m = 0` that tends to ``m`` as ``g -> 0``, :math:`x = 2m / (1 + \sqrt{1 + 4 g m})`
    (the discriminant clipped at 1e-12 where :math:`g m < -1/4`, beyond which no ``u0`` gives ``u``)."""
    return 2.0 * m / (1.0 + jnp.sqrt(jnp.maximum(1.0 + 4.0 * g * m, 1e-12)))


@dataclasses.dataclass(frozen=True)
class MagnitudeGain(InputTransform, Entry):
    r"""The sensor's gain depends on the magnitude of the field: the reading is :math:`u = (1 + g\,|u_0|)\,u_0`.

    :math:`u_0` is the reading the thermo-affine model describes, :math:`B = (S + K_s T_c) u_0 + O + K_o T_c`,
    so the calibrated field gains :math:`(1 + g|B|)` in the sensor's own gain, on every channel alike. The
    transform inverts it exactly, :math:`u_0 = u / (1 + g\,x)` with :math:`x = |u_0|` from
    :func:`magnitude_of_undistorted`, so a campaign simulated with the ``magnitude_gain`` effect
    (:mod:`bayesmag.simulate`) is fitted with the planted ``g``. Parameter ``g`` in 1 / (reading unit; uT for a
    reading in uT); ``g0`` its starting value. Distinct from a cubic: on a field of constant magnitude
    (a tumble) it is a plain gain change, which S absorbs; it shows only between fields of different magnitude.

    Example:
      >>> import numpy as np; from bayesmag._src.core.physics import Inputs
      >>> u0 = np.array([[30.0, 40.0, 0.0]]); u = u0 * (1 + 1e-3 * 50.0)
      >>> x = Inputs(u, np.zeros(1), np.zeros(1), np.zeros(1, int))
      >>> np.round(np.asarray(MagnitudeGain()(np.array([1e-3]), x).b), 9).tolist()
      [[30.0, 40.0, 0.0]]
    """

    g0: float = 0.0
    name: ClassVar[str] = "magnitude_gain"
    temperature_centred: ClassVar[bool] = True       # reads only the field
    explanation: ClassVar[str] = ("The sensor's sensitivity changes with the strength of the field on every axis "
                                  "alike (a bridge or front end whose gain compresses or expands in strong fields), "
                                  "so the reading scales by (1 + g |B|).")
    scope: ClassVar[str] = "sensor"
    simulator_name: ClassVar[str] = "magnitude_gain"
    start_field: ClassVar[str] = "g0"
    #: Grid: relative gain changes at the field's reach (98th percentile of |u|), both signs.
    FRACTIONS: ClassVar[tuple] = (0.002, 0.005, 0.01, 0.02, 0.05, 0.1)
    #: A gain change of this fraction or more across the reach is not a small nonlinearity (for g < 0 the
    #: inverse stops existing at g |u| = -1/4).
    MAX_FRACTION: ClassVar[float] = 0.25

    def param_names(self):
        return ("g",)

    def init_params(self, axis):
        return np.array([float(self.g0)])

    def memory_rows(self, params, dt):
        return 0                                       # row by row

    def __call__(self, params, inputs):
        g = params[0]
        m = jnp.sqrt(jnp.sum(inputs.b * inputs.b, axis=-1))
        return inputs._replace(b=inputs.b / (1.0 + g * magnitude_of_undistorted(m, g))[..., None])

    def canonical(self):
        return MagnitudeGain()

    def started(self, value):
        return dataclasses.replace(self, g0=float(f"{float(value):.6g}"))

    def refine_step(self, value):
        return 0.4 * max(abs(float(value)), 1e-12)     # the grid is 2-2.5x apart

    @classmethod
    def grid(cls, ctx, c):
        m = max(float(ctx.magnitude_reach), 1e-9)
        return [Setting(cls(g0=float(sg * f / m)), nl=float(sg * f / m)) for f in cls.FRACTIONS for sg in (-1.0, 1.0)]

    def describe(self, cols):
        return "gain varies with the field magnitude |B| (the reading scales by 1 + g |B|, on every channel alike)"

    def depends_on(self, cols):
        return "|B|"

    def implausible(self, value, ctx):
        change = abs(float(value)) * float(ctx.magnitude_reach)
        if change >= self.MAX_FRACTION:
            return (f"g = {value:.3g} changes the gain by {change:.0%} across the field's reach (|u| = "
                    f"{ctx.magnitude_reach:.3g}): that is saturation or a wrong field unit, not a magnitude-dependent "
                    f"gain (limit {self.MAX_FRACTION:.0%})")
        return None


for _cls in (AxisQuadratic, CrossAxisQuadratic, CubicNonlinearity, Hysteresis):
    _cls.__doc__ = (_cls.__doc__ or "") + _THERMAL_DOC

#: The discovery catalogue: name -> class (each class carries its own grid, label, requirements, twin).
CATALOGUE: dict[str, type] = {
    c.name: c for c in (AxisQuadratic, CrossAxisQuadratic, CubicNonlinearity, TemperatureQuadratic, ThermalLag,
                        TimingOffset, MagnitudeGain, Hysteresis, OffsetDrift, RunOffset, RunStep)
}

#: Simulator effect name (:mod:`bayesmag.simulate`) -> catalogue name that represents it.
SIMULATOR_NAMES: dict[str, str] = {c.simulator_name: n for n, c in CATALOGUE.items() if c.simulator_name}


def explanation(name: str) -> str:
    """The one-sentence physical explanation of catalogue entry ``name``."""
    if name not in CATALOGUE:
        raise ValueError(f"catalogue entry {name!r} is not known; it must be one of {sorted(CATALOGUE)}.")
    return CATALOGUE[name].explanation


EXTRA_TERMS.update(CATALOGUE)


def register(cls: type) -> type:
    """Add catalogue class ``cls`` to :data:`CATALOGUE`, :data:`~bayesmag._src.core.physics.EXTRA_TERMS`
    and :data:`SIMULATOR_NAMES` (so fit, discover, NUTS and saved calibrations know it); returns
    ``cls``, so it can decorate the class. Undo with :func:`unregister`."""
    if not (isinstance(cls, type) and issubclass(cls, Entry) and issubclass(cls, (Term, InputTransform))
            and dataclasses.is_dataclass(cls)):
        raise TypeError(f"a catalogue entry must be a dataclass subclassing Entry and Term or InputTransform; "
                        f"got {cls!r}.")
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not isinstance(getattr(cls, "explanation", None), str):
        raise TypeError(f"catalogue entry {cls.__name__} must set a string 'name' and a one-sentence 'explanation'.")
    if name in EXTRA_TERMS or name == "thermo_affine":
        raise ValueError(f"a physics term named {name!r} is already registered; registered: {sorted(EXTRA_TERMS)}.")
    if cls.scope not in ("channel", "sensor"):
        raise ValueError(f"catalogue entry {name!r} has scope {cls.scope!r}; it must be one of ['channel', 'sensor'].")
    CATALOGUE[name] = EXTRA_TERMS[name] = cls
    if cls.simulator_name:
        SIMULATOR_NAMES[cls.simulator_name] = name
    return cls


def unregister(name: str) -> type:
    """Remove catalogue entry ``name`` (e.g. one a test registered) from every registry; returns its class."""
    if name not in CATALOGUE:
        raise ValueError(f"catalogue entry {name!r} is not registered; registered: {sorted(CATALOGUE)}.")
    cls = CATALOGUE.pop(name)
    EXTRA_TERMS.pop(name, None)
    if SIMULATOR_NAMES.get(cls.simulator_name) == name:
        del SIMULATOR_NAMES[cls.simulator_name]
    return cls


def make_extra(spec, *, t0: float = 0.0):
    """Build an extra term/transform from a name or a ``{name = ..., field = value}`` table."""
    if isinstance(spec, str):
        spec = {"name": spec}
    spec = dict(spec)
    name = spec.pop("name", None)
    if name not in EXTRA_TERMS:
        raise ValueError(f"physics extra term {name!r} is not known; it must be one of {sorted(EXTRA_TERMS)}.")
    cls = EXTRA_TERMS[name]
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = set(spec) - fields
    if unknown:
        raise ValueError(f"physics extra term {name!r} has no parameter(s) {sorted(unknown)}; valid: {sorted(fields)}.")
    if "t0" in fields:
        if "t0" in spec and float(spec["t0"]) != float(t0):
            raise ValueError(f"physics extra term {name!r} has t0 = {spec['t0']!r}, but a term's reference "
                             f"temperature is the model's ([physics] t0, here {t0:g} C): remove 't0' from the term.")
        spec["t0"] = t0
    return cls(**spec)
