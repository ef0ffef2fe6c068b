"""An independent generator of concealed-effect calibration campaigns.

Written apart from :mod:`bayesmag.simulate` (no design code or effect sizing shared with it)
to test discovery on data it was not tuned on. What differs:

* the *sensor* is the ground truth: readings ``u`` (sensor units) are generated from the true
  field ``B`` as ``u = S(T)^-1 (B - O(T)) + d + noise`` with ``S(T) = S0 + Ks (T - Tref)``,
  ``O(T) = O0 + Ko (T - Tref)``, so the thermo-affine calibration is exact on clean data;
* every planted distortion ``d`` acts on ONE sensor channel (or, for thermal lag and timing
  offset, on the whole sensor), with its size set in sensor units as a multiple of that
  channel's own noise sd (never sized from a fitted model);
* run designs of its own: coil sweeps of one axis over a slowly rotating background,
  constant-magnitude tumbles, and staircases of held field vectors; 3-5 runs with gaps of
  1-10 minutes between them, sampling at 2-10 Hz, temperature cycling 2-8 C per run;
* out-of-catalogue effects (periodic interference of ~55 s, gain drift in time) and per-run
  offset steps; hysteresis whose state persists across the gaps between runs.

``campaign(kind, seed)`` returns ``(CalibrationData, Planted)``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from bayesmag import CalibrationData

AXES = ("x", "y", "z")

#: kind -> catalogue name discovery should report (None: out of catalogue, to be reported unexplained).
KINDS = {
    "clean": None,
    "axis_quadratic": "axis_quadratic",
    "cross_axis_quadratic": "cross_axis_quadratic",
    "cubic": "cubic_nonlinearity",
    "temperature_offset_quadratic": "temperature_quadratic",
    "temperature_gain_quadratic": "temperature_quadratic",
    "thermal_lag": "thermal_lag",
    "timing_offset": "timing_offset",
    "hysteresis": "hysteresis",
    "offset_drift": "offset_drift",
    "run_offset": "run_offset",
    "periodic": None,
    "gain_drift": None,
}
IN_CATALOGUE = tuple(k for k, v in KINDS.items() if v is not None)
OUT_OF_CATALOGUE = ("periodic", "gain_drift")
WHOLE_SENSOR = ("thermal_lag", "timing_offset")


@dataclasses.dataclass(frozen=True)
class Planted:
    """What was concealed: ``kind``, the catalogue ``name`` that should be reported (None if
    out of catalogue), the sensor ``channel`` ('x', 'y', 'z' or 'all'), and its parameters."""

    kind: str
    name: str | None
    channel: str | None
    params: dict


def _lag(x, time, run, tau):
    """First-order lag of x with time constant tau (s), restarted at each run."""
    out = np.empty_like(x)
    for i in range(x.size):
        if i == 0 or run[i] != run[i - 1]:
            out[i] = x[i]
        else:
            a = np.exp(-(time[i] - time[i - 1]) / tau)
            out[i] = a * out[i - 1] + (1 - a) * x[i]
    return out


def _run_field(rng, kind, t):
    """(m, 3) true field (uT) of one run of the given design at times t (s from run start)."""
    m = t.size
    if kind == "sweep":
        k = rng.integers(3)
        period = rng.uniform(40, 120)
        amp = rng.uniform(30, 60)
        tri = 2 * np.abs(2 * ((t / period + rng.uniform()) % 1) - 1) - 1
        axis_b = np.zeros((m, 3))
        axis_b[:, k] = amp * tri
        w = 2 * np.pi / rng.uniform(150, 400)
        bg = 25 * np.stack([np.cos(w * t), np.sin(w * t), 0.6 * np.sin(0.7 * w * t + 1)], 1)
        return axis_b + bg @ _rotation(rng).T
    if kind == "tumble":
        mag = rng.uniform(40, 60)
        w1, w2 = 2 * np.pi / rng.uniform(60, 200), 2 * np.pi / rng.uniform(200, 500)
        theta = np.arccos(np.clip(np.cos(w2 * t + rng.uniform(0, 6)), -1, 1))
        phi = w1 * t
        u = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
        mag_t = mag * (1 + 0.3 * np.sin(2 * np.pi * t / rng.uniform(80, 160)))
        return (u * mag_t[:, None]) @ _rotation(rng).T
    # staircase of held vectors with 1-3 s ramps
    hold = rng.uniform(10, 30)
    n_steps = int(np.ceil(t[-1] / hold)) + 2
    vecs = rng.uniform(-55, 55, (n_steps, 3))
    pos = t / hold
    i = np.floor(pos).astype(int)
    ramp = rng.uniform(1, 3) / hold
    frac = np.clip((pos - i) / ramp, 0, 1)
    return vecs[i] * (1 - frac[:, None]) + vecs[i + 1] * frac[:, None]


def _rotation(rng):
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    return q * np.sign(np.diag(r))


def campaign(kind: str = "clean", seed: int = 0, n: int = 5000, log_noise: float = 0.02) -> tuple[CalibrationData, Planted]:
    """One campaign of about ``n`` rows with the concealed effect ``kind`` (see :data:`KINDS`);
    ``log_noise``: sd (C) of the temperature log's white noise (the same draws, scaled)."""
    if kind not in KINDS:
        raise ValueError(f"kind is {kind!r}; it must be one of {sorted(KINDS)}.")
    rng = np.random.default_rng([seed, 7919, list(KINDS).index(kind)])
    dt = float(rng.choice([0.1, 0.2, 0.25, 0.5]))
    n_runs = int(rng.integers(3, 6))
    sizes = rng.dirichlet(np.full(n_runs, 6.0)) * n
    sizes = np.maximum(np.round(sizes).astype(int), 300)
    designs = ["tumble", "staircase"] + list(rng.choice(["sweep", "tumble", "staircase"], n_runs - 2))
    rng.shuffle(designs)
    t_ref = 25.0
    times, runs, B, T = [], [], [], []
    t_now = 0.0
    for r, (m, des) in enumerate(zip(sizes, designs)):
        tt = np.arange(m) * dt
        B.append(_run_field(rng, des, tt))
        base = rng.uniform(15, 35)
        amp = rng.uniform(2, 8)
        T.append(base + amp * np.sin(2 * np.pi * tt / rng.uniform(300, 1500) + rng.uniform(0, 6))
                 + rng.uniform(-3, 3) * tt / max(tt[-1], 1))
        times.append(t_now + tt)
        runs.append(np.full(m, r))
        t_now += tt[-1] + rng.uniform(60, 600)
    time, run, B, T_true = np.concatenate(times), np.concatenate(runs), np.concatenate(B), np.concatenate(T)
    # the sensor: reading -> field map S(T), offsets O(T)
    gains = rng.uniform(0.4, 2.5, 3)
    S0 = np.diag(gains) + rng.uniform(-0.15, 0.15, (3, 3)) * (1 - np.eye(3)) * gains[None, :]
    Ks = rng.uniform(-0.004, 0.004, (3, 3)) * gains[None, :]
    O0, Ko = rng.uniform(-5, 5, 3), rng.uniform(-0.15, 0.15, 3)
    sd_u = rng.uniform(0.02, 0.1, 3)                  # sensor noise, sensor units
    sd_ref = rng.uniform(0.01, 0.06)                  # reference noise, uT
    rho = rng.uniform(0.0, 0.3)
    ch = int(rng.integers(3))
    planted = Planted(kind, KINDS[kind], None if kind == "clean" else AXES[ch], {})
    size = rng.uniform(8, 20) * sd_u[ch]              # peak effect, sensor units of channel ch

    T_sensor = T_true
    B_seen = B
    if kind == "thermal_lag":
        tau = float(rng.uniform(60, 240))
        T_sensor = _lag(T_true, time, run, tau)
        Ko = Ko + np.sign(Ko) * 0.3
        planted = Planted(kind, KINDS[kind], "all", {"tau": tau})
    if kind == "timing_offset":
        delta = float(rng.choice([-1, 1]) * rng.uniform(1.5, 3.0) * dt)
        B_seen = np.stack([np.concatenate([np.interp(time[run == r] - delta, time[run == r], B[run == r, k])
                                           for r in range(n_runs)]) for k in range(3)], 1)
        planted = Planted(kind, KINDS[kind], "all", {"delta": delta})
    dT = T_sensor - t_ref
    S_T = S0[None] + Ks[None] * dT[:, None, None]
    u0 = np.linalg.solve(S_T, (B_seen - O0 - Ko * dT[:, None])[..., None])[..., 0]
    d = np.zeros(time.size)
    j, i2 = int(rng.integers(3)), int(rng.integers(3))
    unit = lambda f: f / np.max(np.abs(f))         # noqa: E731  (peak 1)
    if kind == "axis_quadratic":
        d = size * unit(u0[:, j] ** 2)
    elif kind == "cross_axis_quadratic":
        a, b = [k for k in range(3) if k != j][:2]
        d = size * unit(u0[:, a] * u0[:, b])
        planted.params.update(pair=AXES[a] + AXES[b])
    elif kind == "cubic":
        d = size * unit(u0[:, ch] ** 3)
    elif kind == "temperature_offset_quadratic":
        d = size * unit((T_true - t_ref) ** 2)
    elif kind == "temperature_gain_quadratic":
        d = 1.5 * size * unit((T_true - t_ref) ** 2 * u0[:, ch])
    elif kind == "hysteresis":
        f = u0[:, j]
        thr = 0.5 * np.quantile(np.abs(f), 0.98)
        s = np.zeros(f.size)
        state = 0.0                                  # persists across the gaps between runs
        for k in range(f.size):
            if f[k] > thr:
                state = 1.0
            elif f[k] < -thr:
                state = -1.0
            s[k] = state
        d = 0.7 * size * s
        planted.params.update(drive=AXES[j])
    elif kind == "offset_drift":
        d = size * unit(time - time.mean())
    elif kind == "run_offset":
        steps = rng.choice([-1, 1], n_runs) * rng.uniform(0.5, 1.0, n_runs) * size
        steps[0] = 0.0
        d = steps[run]
        planted.params.update(steps=steps.tolist())
    elif kind == "periodic":
        period = float(rng.uniform(45, 65))
        d = 0.8 * size * np.sin(2 * np.pi * time / period + rng.uniform(0, 6))
        planted.params.update(period=period)
    elif kind == "gain_drift":
        d = size * unit((time - time.mean()) * u0[:, ch])
    u = u0.copy()
    u[:, ch] += d
    e = rng.standard_normal(u.shape) * sd_u
    for k in range(1, e.shape[0]):                   # mild AR(1) sensor noise inside runs
        if run[k] == run[k - 1]:
            e[k] = rho * e[k - 1] + np.sqrt(1 - rho**2) * e[k]
    u = u + e
    ref = B + sd_ref * rng.standard_normal(B.shape)
    T_log = T_true + log_noise * rng.standard_normal(T_true.size)
    planted.params.update(size_sensor_units=float(size), noise_sd_sensor_units=sd_u.tolist(), dt=dt,
                          n_runs=n_runs)
    data = CalibrationData(u, T_log, ref, time, run, f"independent:{kind}:seed{seed}")
    return data, planted
