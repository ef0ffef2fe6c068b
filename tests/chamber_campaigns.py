"""A third generator of calibration campaigns: temperature-chamber programmes with slow sensor heat flow.

Written for issue #25, apart from :mod:`bayesmag.simulate` and ``independent_campaigns.py``
(no design code or sizing shared), and without reference to discovery's thresholds. What it
models:

* **the chamber**: a programme of holds (4-20 min) and ramps at 0.5-2 C/min, heating and
  cooling, between -10 and 55 C; the controller follows the set point with its own first-order
  response (20-60 s), and the logged air temperature is that response plus thermometer noise
  (0.005-0.03 C sd) quantised to 0.01 C, so the log is smooth;
* **the sensor's heat flow**: the die temperature trails the air either as a first-order lag
  (``lag_first_order``, tau) or through a housing node (``lag_two_node``: air -> housing with
  tau_h -> die with tau_d). ``params["tau"]`` is the *mean delay* of the heat path, tau for one
  node and tau_h + tau_d for two (the lag of the die behind a steady ramp), 30-600 s;
  ``clean``: the die follows the air at once;
* **the field**: a coil system in the chamber holds random field vectors (20-70 uT) for 3-12 s
  each with 1 s transitions; a reference magnetometer outside the chamber's thermal zone
  (noise 0.01-0.04 uT);
* **the sensor** is the ground truth: ``B = S(Td) u + O(Td)``, ``S(T) = S0 + Ks (T - 25)``,
  ``O(T) = O0 + Ko (T - 25)`` with relative gain tempco 0.15-0.4 %/C and offset tempco
  0.05-0.3 uT/C, so the thermo-affine calibration is exact when the die temperature is logged;
  reading noise 0.02-0.08 sensor units;
* **sessions**: 1-3 programme runs (each starting with a hold; the sensor starts in
  equilibrium) and, in three campaigns of five, 1-3 short check runs (150-400 rows at a held
  temperature, as an operator's quick tumble test would be), so the *median* run can be a few
  minutes long; sampled every 1-2 s, 40-170 min of recording in all; time stamps
  are the logger's clock (seconds since midnight, so never the row index).

``campaign(kind, seed, n)`` returns ``(CalibrationData, Planted)`` like ``independent_campaigns``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from bayesmag import CalibrationData

#: kind -> catalogue name discovery should report (None: nothing planted).
KINDS = {"clean": None, "lag_first_order": "thermal_lag", "lag_two_node": "thermal_lag"}
T_REF = 25.0


@dataclasses.dataclass(frozen=True)
class Planted:
    """What was concealed: ``kind``, the catalogue ``name`` to report (None: nothing), the
    ``channel`` ('all' for heat flow, which reaches every channel) and its parameters."""

    kind: str
    name: str | None
    channel: str | None
    params: dict


def first_order(x: np.ndarray, time: np.ndarray, run: np.ndarray, tau: float) -> np.ndarray:
    """Exact first-order response to ``x`` held between samples, equilibrium at each run start."""
    y = np.empty_like(x)
    for i in range(x.size):
        if i == 0 or run[i] != run[i - 1]:
            y[i] = x[i]
        else:
            a = np.exp(-(time[i] - time[i - 1]) / tau)
            y[i] = a * y[i - 1] + (1.0 - a) * x[i]
    return y


def programme(rng: np.random.Generator, duration: float) -> list:
    """[(t_start, t_end, T_start, T_end)] set-point segments covering ``duration`` s: holds and ramps."""
    segs, t, T = [], 0.0, float(rng.uniform(5, 35))
    hold = float(rng.uniform(240, 900))
    segs.append((t, t + hold, T, T))
    t += hold
    direction = float(rng.choice([-1.0, 1.0]))
    while t < duration:
        rate = float(rng.uniform(0.5, 2.0)) / 60.0                 # C/s
        span = float(rng.uniform(5, 30))
        target = T + direction * span
        if not -10.0 <= target <= 55.0:
            direction = -direction
            target = T + direction * span
        target = float(np.clip(target, -10.0, 55.0))
        dur = abs(target - T) / rate
        segs.append((t, t + dur, T, target))
        t, T = t + dur, target
        hold = float(rng.uniform(240, 1200))
        segs.append((t, t + hold, T, T))
        t += hold
        if rng.random() < 0.6:                                      # cooling follows heating, mostly
            direction = -direction
    return segs


def set_point(segs: list, t: np.ndarray) -> np.ndarray:
    out = np.full(t.shape, segs[-1][3])
    for a, b, Ta, Tb in segs:
        m = (t >= a) & (t < b)
        out[m] = Ta + (Tb - Ta) * (t[m] - a) / max(b - a, 1e-9)
    return out


def field(rng: np.random.Generator, t: np.ndarray) -> np.ndarray:
    """(m, 3) coil field: held random vectors with 1 s linear transitions."""
    edges = [0.0]
    while edges[-1] < t[-1] + 15:
        edges.append(edges[-1] + float(rng.uniform(3, 12)))
    edges = np.asarray(edges)
    d = rng.standard_normal((edges.size, 3))
    vecs = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(20, 70, (edges.size, 1))
    i = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, edges.size - 2)
    frac = np.clip(t - edges[i], 0, 1.0)[:, None]
    prev = vecs[np.maximum(i - 1, 0)]
    return prev * (1 - frac) + vecs[i] * frac


def campaign(kind: str = "clean", seed: int = 0, n: int = 5000,
             check_runs: int | None = None) -> tuple[CalibrationData, Planted]:
    """One chamber campaign of about ``n`` rows with the concealed heat path ``kind`` (see :data:`KINDS`);
    ``check_runs`` forces the number of short check runs (default: drawn, 0-3)."""
    if kind not in KINDS:
        raise ValueError(f"kind is {kind!r}; it must be one of {sorted(KINDS)}.")
    rng = np.random.default_rng([seed, 4243, list(KINDS).index(kind)])
    dt = float(rng.choice([1.0, 1.5, 2.0]))
    n_prog = int(rng.integers(1, 4))
    k_checks = int(rng.choice([0, 0, 1, 2, 3]))
    checks = [int(rng.integers(150, 400)) for _ in range(k_checks if check_runs is None else int(check_runs))]
    sizes = np.maximum(np.round(rng.dirichlet(np.full(n_prog, 8.0)) * (n - sum(checks))).astype(int), 600)
    plan = [("programme", int(m)) for m in sizes] + [("check", m) for m in checks]
    order = rng.permutation(len(plan))
    plan = [plan[0]] + [plan[i] for i in order if i != 0]          # a programme first
    n_runs = len(plan)
    times, runs, T_air, B = [], [], [], []
    t_now = float(rng.uniform(3600, 86400))                        # the logger's clock: seconds since midnight
    for r, (what, m) in enumerate(plan):
        tt = np.arange(m) * dt
        if what == "programme":
            segs = programme(rng, tt[-1])
        else:                                                      # a short check run at a held temperature
            T_hold = float(rng.uniform(0, 45))
            segs = [(0.0, tt[-1] + 1.0, T_hold, T_hold)]
        sp = set_point(segs, tt)
        air = first_order(sp, tt, np.zeros(m, int), float(rng.uniform(20, 60)))
        T_air.append(air)
        B.append(field(rng, tt))
        times.append(t_now + tt)
        runs.append(np.full(m, r))
        t_now += tt[-1] + float(rng.uniform(300, 3600))
    time, run, T_air, B = np.concatenate(times), np.concatenate(runs), np.concatenate(T_air), np.concatenate(B)

    params: dict = {"dt": dt, "n_runs": n_runs, "check_runs": len(checks)}
    if kind == "lag_first_order":
        tau = float(np.exp(rng.uniform(np.log(30), np.log(600))))
        T_die = first_order(T_air, time, run, tau)
        params.update(tau=tau, nodes=1)
    elif kind == "lag_two_node":
        total = float(np.exp(rng.uniform(np.log(30), np.log(600))))
        share = float(rng.uniform(0.2, 0.8))                       # housing's share of the delay
        tau_h, tau_d = share * total, (1 - share) * total
        T_die = first_order(first_order(T_air, time, run, tau_h), time, run, tau_d)
        params.update(tau=total, tau_housing=tau_h, tau_die=tau_d, nodes=2)
    else:
        T_die = T_air

    gains = rng.uniform(0.7, 1.4, 3)
    S0 = np.diag(gains) + rng.uniform(-0.03, 0.03, (3, 3)) * (1 - np.eye(3))
    Ks = np.diag(gains * rng.uniform(0.0015, 0.004, 3)) + rng.uniform(-2e-4, 2e-4, (3, 3)) * (1 - np.eye(3))
    O0 = rng.uniform(-8, 8, 3)
    Ko = rng.choice([-1, 1], 3) * rng.uniform(0.05, 0.3, 3)
    dT = T_die - T_REF
    S_T = S0[None] + Ks[None] * dT[:, None, None]
    u = np.linalg.solve(S_T, (B - O0 - Ko * dT[:, None])[..., None])[..., 0]
    sd_u = rng.uniform(0.02, 0.08, 3)
    u = u + rng.standard_normal(u.shape) * sd_u
    ref = B + rng.uniform(0.01, 0.04) * rng.standard_normal(B.shape)
    T_log = np.round(T_air + rng.uniform(0.005, 0.03) * rng.standard_normal(T_air.size), 2)
    params.update(noise_sd_sensor_units=sd_u.tolist(), lag_rms_C=float(np.sqrt(np.mean((T_die - T_air) ** 2))))
    planted = Planted(kind, KINDS[kind], None if kind == "clean" else "all", params)
    return CalibrationData(u, T_log, ref, time, run, f"chamber:{kind}:seed{seed}"), planted
