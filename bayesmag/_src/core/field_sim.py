r"""Simulated field campaigns with ground truth: a magnetometer turned around in the Earth's field.

The Earth field in the local north-east-down frame is ``F (cos I cos D, cos I sin D, sin I)``
(inclination I, declination D). A body attitude :math:`C_k` (NED -> body) gives the true field
in the body frame :math:`B_k = C_k B_{ned}`. The sensor (gain, cross-axis, misalignment, thermal
terms) and the vehicle (hard iron h, symmetric soft iron :math:`S_v`) fold into one thermo-affine
calibration, exactly:

.. math::  B = S_v^{-1}\big(M_s(T) u + o_s(T) - h\big) = M(T)\,u + o(T),

so the reading is :math:`u = M(T)^{-1}(B - o(T)) + \varepsilon`, :math:`\varepsilon \sim N(0, \sigma^2 I)`.
A scalar reference reads :math:`F_{ref} = \lVert B\rVert + N(0, \sigma_{ref}^2)`.

Motions (:data:`MOTIONS`): ``dance`` (tumbled by hand through all directions), ``level_turns``
(yaw turns with a few degrees of tilt), ``two_temperature`` (a level turn, a pitch turn and a roll
turn at each of two temperatures), ``few_orientations`` (a few static attitudes).

Example:
  >>> c = simulate_field("dance", n=500, seed=1)
  >>> c.data.n, round(float(np.median(np.linalg.norm(c.truth.b_body, axis=1))), 1)
  (500, 50.0)
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from bayesmag._src.core.data import CalibrationData
from bayesmag._src.core.field import gauge_form, heading, invariants

__all__ = ["FieldTruth", "FieldCampaign", "simulate_field", "simulate_field_sessions", "MOTIONS",
           "field_campaign_from_config"]

MOTIONS = ("dance", "level_turns", "two_temperature", "few_orientations")


@dataclasses.dataclass(frozen=True)
class FieldTruth:
    """Ground truth of a field campaign: the total calibration (body frame) and every part of it."""

    S: np.ndarray
    Ks: np.ndarray
    O: np.ndarray
    Ko: np.ndarray
    t0: float
    sensor: dict
    vehicle: dict
    earth_ned: np.ndarray
    attitude: np.ndarray      # (n, 3, 3) NED -> body
    b_body: np.ndarray        # (n, 3) true field in the body frame
    level: np.ndarray         # (n,) bool: tilt below 5 degrees

    def M(self, t):
        return self.S + self.Ks * (np.asarray(t) - self.t0)[..., None, None]

    def o(self, t):
        return self.O + self.Ko * (np.asarray(t) - self.t0)[..., None]

    def invariants(self, t0: float | None = None) -> np.ndarray:
        """The 18 gauge-free numbers at ``t0`` (default the truth's)."""
        dt = 0.0 if t0 is None else t0 - self.t0
        return np.asarray(invariants(self.S + self.Ks * dt, self.Ks, self.O + self.Ko * dt, self.Ko))

    def alignment(self, t) -> np.ndarray:
        """(n, 3, 3) rotation from the gauge frame (M upper-triangular) to the body frame, per temperature."""
        return np.stack([gauge_form(m)[0] for m in self.M(np.asarray(t))])

    @property
    def heading(self) -> np.ndarray:
        return heading(self.b_body)


@dataclasses.dataclass(frozen=True)
class FieldCampaign:
    """A simulated campaign: the recording (``data.b_ref`` is the true body field), ``f_ref`` and the truth."""

    kind: str
    data: CalibrationData
    f_ref: np.ndarray
    truth: FieldTruth
    settings: dict


def _attitudes(kind: str, n: int, rng, *, tilt_deg: float, n_orient: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3, 3) NED->body attitudes and (n,) segment index (0/1 for the two temperatures)."""
    seg = np.zeros(n, dtype=int)
    if kind == "dance":
        key = Rotation.random(24, random_state=rng)
        s = Slerp(np.linspace(0, 1, 24), key)
        R = s(np.linspace(0, 1, n))
    elif kind == "level_turns":
        k = np.linspace(0, 1, n)
        yaw = 360.0 * 3 * k + rng.uniform(0, 360)
        roll = tilt_deg * np.sin(2 * np.pi * 7.3 * k + rng.uniform(0, 6.3))
        pitch = tilt_deg * np.sin(2 * np.pi * 5.1 * k + rng.uniform(0, 6.3))
        R = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    elif kind == "two_temperature":
        half = [n // 2, n - n // 2]
        parts = []
        for h in half:
            m = [h // 3, h // 3, h - 2 * (h // 3)]
            ang = [np.linspace(0, 360, mm, endpoint=False) + rng.uniform(0, 360) for mm in m]
            parts += [Rotation.from_euler("Z", ang[0][:, None], degrees=True),      # a level turn, then a
                      Rotation.from_euler("Y", ang[1][:, None], degrees=True),      # pitch and a roll turn
                      Rotation.from_euler("X", ang[2][:, None], degrees=True)]
        R = Rotation.concatenate(parts)
        seg[n // 2:] = 1
    elif kind == "few_orientations":
        key = Rotation.random(n_orient, random_state=rng)
        idx = np.minimum(np.arange(n) * n_orient // n, n_orient - 1)
        R = key[idx]
    else:
        raise ValueError(f"field motion {kind!r} is not known; it must be one of {list(MOTIONS)}.")
    # scipy's Rotation maps body -> world; the attitude NED -> body is its inverse
    return R.inv().as_matrix(), seg


def simulate_field(kind: str = "dance", *, n: int = 2000, seed: int = 0, field: float = 50.0,
                   inclination: float = 60.0, declination: float = 0.0, noise_sd: float = 0.05,
                   ref_sd: float = 0.01, temperature: tuple[float, float] = (20.0, 20.0),
                   temperatures: tuple[float, float] = (15.0, 40.0), t0: float = 25.0, vehicle: bool = True,
                   tilt_deg: float = 3.0, n_orient: int = 12, field_variation: float = 0.0,
                   sample_rate: float = 10.0, sensor_seed: int | None = None, hard_iron_shift=None,
                   soft_iron_shift=None) -> FieldCampaign:
    """One simulated field campaign (all draws from ``seed``).

    Args:
      kind: one of :data:`MOTIONS`.
      n: rows. field: Earth field magnitude, uT. inclination, declination: degrees.
      noise_sd: sensor noise per axis, uT. ref_sd: scalar reference noise, uT.
      temperature: (start, end) of a linear temperature ramp, C (``two_temperature`` uses ``temperatures``).
      t0: the truth's reference temperature. vehicle: add hard and soft iron.
      tilt_deg: tilt amplitude of level turns. n_orient: attitudes of ``few_orientations``.
      field_variation: relative amplitude of a slow change of the field magnitude along the path
        (a scalar reference sees it; a ``constant`` model does not).
      sensor_seed: draw the sensor and vehicle (S, Ks, O, Ko, hard and soft iron) from this seed and the motion
        and noise from ``seed``: campaigns with one ``sensor_seed`` and different ``seed`` are new recordings of
        one sensor (None: everything from ``seed``, as before).
      hard_iron_shift: (3,) uT added to the vehicle's hard iron (a session's change: a payload, a battery, a power
        state); soft_iron_shift: (3, 3) added to its soft iron (symmetrised). Both need ``vehicle``.
    """
    rng = np.random.default_rng(seed)
    srng = rng if sensor_seed is None else np.random.default_rng(sensor_seed)
    S_s = np.eye(3) + np.diag(srng.normal(0, 0.03, 3)) + srng.normal(0, 0.01, (3, 3)) * (1 - np.eye(3))
    Ks_s = srng.normal(0, 2e-4, (3, 3))
    O_s = srng.normal(0, 2.0, 3)
    Ko_s = srng.normal(0, 0.02, 3)
    if vehicle:
        h = srng.normal(0, 10.0, 3)
        A = srng.normal(0, 0.03, (3, 3))
        Sv = np.eye(3) + 0.5 * (A + A.T)
        if hard_iron_shift is not None:
            h = h + np.asarray(hard_iron_shift, np.float64).reshape(3)
        if soft_iron_shift is not None:
            d = np.asarray(soft_iron_shift, np.float64).reshape(3, 3)
            Sv = Sv + 0.5 * (d + d.T)
    else:
        if hard_iron_shift is not None or soft_iron_shift is not None:
            raise ValueError("hard_iron_shift and soft_iron_shift change the vehicle: they need vehicle=True")
        h, Sv = np.zeros(3), np.eye(3)
    Svi = np.linalg.inv(Sv)
    S, Ks, O, Ko = Svi @ S_s, Svi @ Ks_s, Svi @ (O_s - h), Svi @ Ko_s
    C, seg = _attitudes(kind, n, rng, tilt_deg=tilt_deg, n_orient=n_orient)
    I, D = np.radians(inclination), np.radians(declination)
    e_ned = field * np.array([np.cos(I) * np.cos(D), np.cos(I) * np.sin(D), np.sin(I)])
    k = np.linspace(0, 1, n)
    scale = 1.0 + field_variation * np.sin(2 * np.pi * 1.5 * k + rng.uniform(0, 6.3))
    B = np.einsum("nij,j->ni", C, e_ned) * scale[:, None]
    if kind == "two_temperature":
        t = np.where(seg == 0, temperatures[0], temperatures[1]).astype(float)
    else:
        t = np.linspace(temperature[0], temperature[1], n)
    t = t + rng.normal(0, 0.05, n)
    tc = t - t0
    M = S + Ks * tc[:, None, None]
    o = O + Ko * tc[:, None]
    u = np.linalg.solve(M, (B - o)[..., None])[..., 0] + rng.normal(0, noise_sd, (n, 3))
    f_ref = np.linalg.norm(B, axis=1) + rng.normal(0, ref_sd, n)
    tilt = np.degrees(np.arccos(np.clip(C[:, 2, 2], -1, 1)))        # angle between body z and down
    truth = FieldTruth(S, Ks, O, Ko, t0, {"S": S_s, "Ks": Ks_s, "O": O_s, "Ko": Ko_s}, {"hard_iron": h, "soft_iron": Sv},
                       e_ned, C, B, tilt < 5.0)
    time = np.arange(n) / sample_rate
    run = seg.astype(np.int64)
    data = CalibrationData(u, t, B, time, run, source=f"simulated field campaign: {kind}, seed {seed}"
                           + ("" if sensor_seed is None else f", sensor {sensor_seed}"))
    settings = dict(kind=kind, n=n, seed=seed, field=field, inclination=inclination, declination=declination,
                    noise_sd=noise_sd, ref_sd=ref_sd, temperature=list(temperature), temperatures=list(temperatures),
                    t0=t0, vehicle=vehicle, tilt_deg=tilt_deg, n_orient=n_orient, field_variation=field_variation,
                    sensor_seed=sensor_seed,
                    hard_iron_shift=None if hard_iron_shift is None else [float(v) for v in np.ravel(hard_iron_shift)],
                    soft_iron_shift=None if soft_iron_shift is None else np.asarray(soft_iron_shift).tolist())
    return FieldCampaign(kind, data, f_ref, truth, settings)


def simulate_field_sessions(kind: str = "dance", *, sessions: int = 8, n: int = 1000, seed: int = 0,
                            sensor_seed: int = 0, hard_iron_sd: float = 0.3, soft_iron_sd: float = 0.0,
                            shift_df: float | None = None, temperature_spread: float = 0.0,
                            **kw) -> tuple[FieldCampaign, ...]:
    r"""Several sessions (flights, campaigns) of one sensor on one vehicle whose hard and soft iron change between them.

    Session ``k`` is :func:`simulate_field` with ``sensor_seed`` (the same sensor and vehicle), motion and noise from
    ``seed * 1000 + k``, the vehicle's hard iron moved by a draw of sd ``hard_iron_sd`` uT per axis and its soft
    iron by one of sd ``soft_iron_sd`` per element (Gaussian, or Student-t with ``shift_df`` dof scaled to that sd:
    heavy-tailed changes); with ``temperature_spread`` > 0 its temperature ramp is shifted by a uniform draw in
    +-``temperature_spread`` C. Every row of session ``k`` has ``run = k``; each campaign's truth is its own.

    Example:
      >>> s = simulate_field_sessions(sessions=3, n=200, hard_iron_sd=0.5)
      >>> [int(c.data.run[0]) for c in s], bool(np.ptp([c.truth.vehicle["hard_iron"][0] for c in s]) > 0)
      ([0, 1, 2], True)
    """
    if not (isinstance(sessions, (int, np.integer)) and sessions >= 1):
        raise ValueError(f"sessions = {sessions!r} must be an integer >= 1")
    if shift_df is not None and not shift_df > 2:
        raise ValueError(f"shift_df = {shift_df!r} must be > 2 (a finite variance) or None (Gaussian)")
    rng = np.random.default_rng([seed, 7919])

    def draw(size):
        if shift_df is None:
            return rng.normal(0.0, 1.0, size)
        return rng.standard_t(shift_df, size) / np.sqrt(shift_df / (shift_df - 2.0))

    out = []
    for k in range(sessions):
        kw_k = dict(kw)
        if temperature_spread > 0:
            dt = rng.uniform(-temperature_spread, temperature_spread)
            kw_k["temperature"] = tuple(float(v) + dt for v in kw.get("temperature", (20.0, 20.0)))
            kw_k["temperatures"] = tuple(float(v) + dt for v in kw.get("temperatures", (15.0, 40.0)))
        c = simulate_field(kind, n=n, seed=seed * 1000 + k, sensor_seed=sensor_seed,
                           hard_iron_shift=hard_iron_sd * draw(3), soft_iron_shift=soft_iron_sd * draw((3, 3)), **kw_k)
        out.append(dataclasses.replace(c, data=dataclasses.replace(c.data, run=np.full(n, k, np.int64),
                                                                   source=f"{c.data.source}, session {k}")))
    return tuple(out)


def field_campaign_from_config(d: dict) -> FieldCampaign:
    """A campaign from a config table (``[data.field_simulate]``): keys as :func:`simulate_field`'s arguments."""
    d = dict(d)
    kind = d.pop("kind", "dance")
    for key in ("temperature", "temperatures"):
        if key in d:
            d[key] = tuple(float(x) for x in d[key])
    known = set(simulate_field.__code__.co_varnames[:simulate_field.__code__.co_argcount
                                                   + simulate_field.__code__.co_kwonlyargcount])
    bad = sorted(set(d) - known)
    if bad:
        raise ValueError(f"unknown field simulation key(s) {bad}; valid keys: {sorted(known)}.")
    return simulate_field(kind, **d)
