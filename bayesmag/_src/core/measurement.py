r"""Measurement models: what a calibration recording knows about the true field, row by row.

The sensor model is always the thermo-affine one, :math:`B = M(T)\,u + o(T)` with
:math:`M = S + K_s T_c`, :math:`o = O + K_o T_c` (:mod:`bayesmag._src.core.physics`). The
measurement model says what it is compared with:

========== ============================================== ===========================================
name        known per row                                  residual
========== ============================================== ===========================================
vector      the reference field :math:`B_{ref}` (3 values)  :math:`B - B_{ref}` (3 per row)
scalar      a reference magnitude :math:`F_{ref}`          :math:`\lVert B\rVert - F_{ref}`
constant    one magnitude F for the whole recording        :math:`\lVert B\rVert - F` (F known or fitted)
========== ============================================== ===========================================

A magnitude cannot see a rotation (:math:`\lVert R B\rVert = \lVert B\rVert`), so a magnitude model
fixes a *gauge*: M(T) upper-triangular (:attr:`MeasurementModel.gauge`). With F left free the
overall scale is not observable either: the gauge then also fixes ``trace(S) = 3``.

One abstraction per extension point: a new measurement model is one small frozen class with
``name``, ``gauge``, ``n_extra`` and :meth:`MeasurementModel.residual`.

Example:
  >>> import jax.numpy as jnp
  >>> Scalar().residual(jnp.array([[3.0, 4.0, 0.0]]), jnp.array([5.5]), jnp.zeros(0)).tolist()
  [-0.5]
"""

from __future__ import annotations

import abc
import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp

__all__ = ["MeasurementModel", "Vector", "Scalar", "Constant", "MEASUREMENTS", "measurement_from_spec"]


class MeasurementModel(abc.ABC):
    """How the calibrated field ``B`` (n, 3) is compared with what each row knows.

    Attributes:
      name: the config name.
      gauge: ``"none"`` (every entry of M observable) or ``"upper"`` (M(T) upper-triangular: the
        3 rotation degrees of freedom a magnitude cannot see are fixed).
      scale_gauge: True when the overall scale is not observable (then ``trace(S) = 3``).
      n_extra: number of parameters of the measurement model itself (e.g. a free F).
      per_row: residuals per row (1 for magnitudes, 3 for a vector).
    """

    name: ClassVar[str]
    gauge: ClassVar[str] = "upper"
    per_row: ClassVar[int] = 1

    @property
    def n_extra(self) -> int:
        return 0

    @property
    def scale_gauge(self) -> bool:
        return False

    @property
    def reference_sd(self) -> float:
        """Noise sd of the reference magnitude, uT (0: exact or negligible, e.g. one known field)."""
        return 0.0

    def extra_names(self) -> tuple[str, ...]:
        return ()

    def extra_init(self, target) -> list[float]:
        return []

    @abc.abstractmethod
    def residual(self, B: jax.Array, target: jax.Array, extra: jax.Array) -> jax.Array:
        """Residuals (n * per_row,) of the calibrated field ``B`` (n, 3) against ``target``."""

    def magnitude(self, target: jax.Array, extra: jax.Array) -> jax.Array:
        """The reference magnitude per row, (n,) (vector: its norm)."""
        return target

    def describe(self) -> dict:
        return {"name": self.name, "gauge": self.gauge, **dataclasses.asdict(self)}


@dataclasses.dataclass(frozen=True)
class Vector(MeasurementModel):
    """A reference vector magnetometer (the paper's set-up): every entry of M is observable."""

    name: ClassVar[str] = "vector"
    gauge: ClassVar[str] = "none"
    per_row: ClassVar[int] = 3

    def residual(self, B, target, extra):
        return (B - target).reshape(-1)

    def magnitude(self, target, extra):
        return jnp.linalg.norm(target, axis=-1)


@dataclasses.dataclass(frozen=True)
class Scalar(MeasurementModel):
    """A scalar magnetometer's magnitude per row (proton/Overhauser, optically pumped, a coil's magnitude).

    ``ref_sd``: the reference's own noise sd, uT (default 0: negligible beside the readings' noise). When > 0 the
    fit removes the pull it would otherwise exert on directions the motion left weak (``fit_field``).
    """

    ref_sd: float = 0.0
    name: ClassVar[str] = "scalar"

    @property
    def reference_sd(self) -> float:
        return float(self.ref_sd)

    def residual(self, B, target, extra):
        return jnp.linalg.norm(B, axis=-1) - target


@dataclasses.dataclass(frozen=True)
class Constant(MeasurementModel):
    """One field magnitude for the whole recording: ``field`` in uT (e.g. from IGRF/WMM), or None to fit it.

    With ``field=None`` the overall scale is a gauge (``trace(S) = 3``) and F is fitted in those units:
    directions (heading) are unaffected, magnitudes are relative.
    """

    field: float | None = None
    name: ClassVar[str] = "constant"

    @property
    def n_extra(self):
        return 1 if self.field is None else 0

    @property
    def scale_gauge(self):
        return self.field is None

    def extra_names(self):
        return ("F",) if self.field is None else ()

    def extra_init(self, target):
        return [float(jnp.mean(target))] if self.field is None else []

    def residual(self, B, target, extra):
        f = extra[0] if self.field is None else self.field
        return jnp.linalg.norm(B, axis=-1) - f

    def magnitude(self, target, extra):
        f = extra[0] if self.field is None else self.field
        return jnp.full(target.shape[:1], f)


MEASUREMENTS = {"vector": Vector, "scalar": Scalar, "constant": Constant}


def measurement_from_spec(kind: str, field: float | str | None = None, reference_sd: float = 0.0) -> MeasurementModel:
    """Build a measurement model from config values: ``kind`` in :data:`MEASUREMENTS`, ``field`` for constant,
    ``reference_sd`` (uT) for scalar.

    Example:
      >>> measurement_from_spec("constant", 50.0)
      Constant(field=50.0)
    """
    if kind not in MEASUREMENTS:
        raise ValueError(f"measurement kind {kind!r} is not known; it must be one of {sorted(MEASUREMENTS)}.")
    if kind == "constant":
        if field in (None, "free"):
            return Constant(None)
        f = float(field)
        if not (f > 0 and f < 1e6):
            raise ValueError(f"constant field {field!r} must be a positive magnitude in uT, or \"free\".")
        lo, hi = 1.0, 2000.0          # the readings' plausible range (core.data._PLAUSIBLE_P99_UT)
        if not lo <= f <= hi:
            unit = "nT (x1000)" if f > hi else "mT (/1000) or gauss (/100)"
            raise ValueError(f"constant field {field!r} is not a magnitude in uT (the Earth's field is 25-65 uT, a "
                             f"calibration coil a few hundred): it looks like {unit}. Give it in uT.")
        return Constant(f)
    if kind == "scalar":
        if not 0 <= float(reference_sd) < 1e3:
            raise ValueError(f"scalar reference_sd {reference_sd!r} must be a noise sd >= 0 uT.")
        return Scalar(float(reference_sd))
    return MEASUREMENTS[kind]()
