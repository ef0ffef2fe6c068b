"""Step-location intervals of discovery (issue #25, round 3): a step's time inside a run is
estimated over every sample time by the exact least-squares profile, and its 95 % interval
(moving-block bootstrap of that same profile) contains the estimate it is printed with.

The interval used to be a bootstrap over a 41-point grid (2.2 s apart on a 0.25 s record)
with parabolic interpolation of a profile that is flat between samples, printed next to a
value placed by a different fit (forward selection's): independent hysteresis seed 9 got
``at = 1810.57 s`` with the interval 1809.35 to 1809.70 s.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from bayesmag._src.pipeline.discover import intervals as I
from bayesmag._src.pipeline.discover.intervals import _profile

DT = 0.5


def _case(seed: int, frac: float, size: float, rho: float, n: int = 600, outputs: int = 1):
    """Two runs of n/2 rows; ``outputs`` series share a design (intercept, a regressor, run 1's
    offset) and a step of ``size`` noise sd at fraction ``frac`` of run 1 (a channel gain per
    output row, as a sensor-frame step); AR(1) noise of lag-1 correlation ``rho``.
    Returns (Z, col, y, rows, time, true step time)."""
    rng = np.random.default_rng(seed)
    run = np.repeat([0, 1], n // 2)
    time = np.arange(n) * DT + 30.0 * run
    rows = np.nonzero(run == 1)[0]
    t_step = float(time[rows[0]] + frac * (time[rows[-1]] - time[rows[0]]) + rng.uniform(0, DT))
    x = rng.standard_normal(n)
    Z1 = np.column_stack([np.ones(n), x, (run == 1) * 1.0])
    Z = np.kron(np.eye(outputs), Z1)
    g = rng.uniform(0.5, 1.5, (outputs, 1)) * np.ones((1, n))
    col = (g * (run == 1)).reshape(-1)
    e = rng.standard_normal((outputs, n))
    for k in range(1, n):
        e[:, k] = rho * e[:, k - 1] + np.sqrt(1 - rho**2) * e[:, k]
    on = np.tile((time >= t_step) * 1.0, outputs)
    y = Z @ rng.standard_normal(Z.shape[1]) + size * col * on + e.reshape(-1)
    return Z, col, y, rows, time, t_step


def test_step_profile_is_the_least_squares_sse_at_every_sample():
    """The cumulative-sum profile equals a full least-squares fit with the step at each candidate
    (three outputs sharing the rows), to 1e-9 of the profile's range."""
    Z, col, y, rows, time, _ = _case(3, 0.4, 2.0, 0.3, n=300, outputs=3)
    cand = np.arange(3, rows.size - 2)
    fast = I.step_profile(Z, col, y[:, None], rows, cand, outputs=3)[:, 0]
    slow = []
    for j in cand:
        on = np.zeros(300)
        on[rows[j:]] = 1.0
        slow.append(_profile(np.column_stack([Z, col * np.tile(on, 3)]), y[:, None])[0][0])
    slow = np.array(slow)
    assert np.max(np.abs(fast - slow)) <= 1e-9 * np.ptp(slow) + 1e-7, np.max(np.abs(fast - slow))


@settings(max_examples=40, deadline=None, derandomize=True)
@given(seed=st.integers(0, 10_000), frac=st.floats(0.05, 0.95), size=st.floats(0.3, 8.0),
       rho=st.floats(0.0, 0.6), outputs=st.sampled_from([1, 3]))
def test_step_interval_contains_its_estimate(seed, frac, size, rho, outputs):
    """Any step time, size (down to 0.3 noise sd, where the location is barely defined) and noise
    correlation: the interval contains the estimate, both inside the run, and the estimate is the
    minimiser of the profile (a midpoint between two samples)."""
    Z, col, y, rows, time, _ = _case(seed, frac, size, rho, outputs=outputs)
    s = I.step_interval(Z, col, y, rows, time, 20, outputs=outputs, n_boot=100, seed=seed)
    assert time[rows[0]] <= s["lower"] <= s["estimate"] <= s["upper"] <= time[rows[-1]], s
    k = int(np.searchsorted(time[rows], s["estimate"]))
    assert time[rows[k - 1]] < s["estimate"] < time[rows[k]]
    assert rows[k] == s["row"]


def test_step_interval_covers_the_true_time_at_about_its_level():
    """200 simulated steps (1.5 to 4 noise sd, AR(1) noise up to 0.5, at 15-85 % of the run): the
    95 % interval contains the true step time in at least 88 % of them. Threshold: with a true
    coverage of 95 % the chance of 176 or fewer of 200 is about 1e-4; the bootstrap of a change
    point is known to run a little below its level for small steps (the replicates' minimisers
    are centred on the estimate, not the truth), so 88 % is the claim, not 95 %."""
    rng = np.random.default_rng(2025)
    hits, widths = 0, []
    for i in range(200):
        frac, size, rho = rng.uniform(0.15, 0.85), rng.uniform(1.5, 4.0), rng.uniform(0.0, 0.5)
        Z, col, y, rows, time, t_true = _case(i, frac, size, rho, outputs=1)
        s = I.step_interval(Z, col, y, rows, time, 20, outputs=1, n_boot=200, seed=i)
        hits += s["lower"] <= t_true <= s["upper"]
        widths.append(s["upper"] - s["lower"])
    assert hits >= 176, hits
    assert np.median(widths) < 0.1 * (time[rows[-1]] - time[rows[0]]), np.median(widths)


def _designs(d):
    """(designs, ctx) of a recording, as discovery builds them (thermo-affine base about the mean temperature)."""
    from bayesmag._src.core.physics import ThermoAffine, inputs_from_data, resolve_t0
    from bayesmag._src.pipeline.discover import pipeline as P
    from bayesmag._src.pipeline.discover.diagnostics import noise_floor
    from bayesmag._src.pipeline.discover.frame import Designs, gain_matrix, lstsq

    run = np.asarray(d.run)
    t0 = resolve_t0("mean", d.temperature)
    base = ThermoAffine(t0=t0, temperature=True)
    inputs = inputs_from_data(d)
    X0 = np.asarray(base.features(inputs))
    y = np.asarray(d.b_ref)
    W0 = np.stack([lstsq(X0, y[:, a]) for a in range(3)])
    floors = np.array([noise_floor((y - X0 @ W0.T)[:, a], run) for a in range(3)])
    designs = Designs(base, inputs, y, 1.0 / floors, gain_matrix(base, W0, np.asarray(d.temperature)))
    dt = float(np.median(np.diff(np.asarray(d.time))))
    return designs, P._context(d, t0, dt, W0)


def _designs_with_step(seed: int, frac: float, factor: float):
    """(designs, ctx, step extension placed on a 41-point grid over its run, true step time, rows
    per block) of an independent clean campaign (2000 rows) whose channel-0 reading steps by
    ``factor`` noise sd at fraction ``frac`` of run 1."""
    import bayesmag
    from bayesmag._src.core import catalogue as C
    from bayesmag._src.pipeline.discover.frame import Extension
    from independent_campaigns import campaign

    d, p = campaign("clean", seed, n=2000)
    run, time = np.asarray(d.run), np.asarray(d.time)
    t1 = time[run == 1]
    at = float(t1[0] + frac * (t1[-1] - t1[0]))
    u = np.array(d.b_meas)
    u[:, 0] += factor * p.params["noise_sd_sensor_units"][0] * ((run == 1) & (time >= at))
    d = bayesmag.CalibrationData(u, d.temperature, d.b_ref, d.time, d.run, "step inside run 1")
    designs, ctx = _designs(d)
    ext = Extension(C.Setting(C.RunStep(run_id=1, at=0.0)), "sensor", 0)
    grid = np.linspace(t1[0] + 0.02 * np.ptp(t1), t1[-1] - 0.02 * np.ptp(t1), 41)
    sse = [_profile(designs.matrix((dataclasses.replace(ext, setting=C.Setting(C.RunStep(run_id=1, at=float(v)))),)),
                    designs.y[:, None])[0][0] for v in grid]
    placed = dataclasses.replace(ext, setting=C.Setting(C.RunStep(run_id=1, at=float(grid[int(np.argmin(sse))]))))
    return designs, ctx, placed, at, max(10, 2000 // 60)


@settings(max_examples=6, deadline=None, derandomize=True)
@given(seed=st.integers(0, 50), frac=st.floats(0.2, 0.8), factor=st.floats(4.0, 12.0))
def test_located_step_interval_contains_the_value_it_is_printed_with(seed, frac, factor):
    """discover's statement of a step's place (``_locate_interval``, given the other findings):
    its interval contains its value, whatever value selection left on the step (here the best
    of a 41-point grid over the run, as a coarse search gives), and the value lies within 2 %
    of the run of the true step time (a step of >= 4 noise sd; the interval's coverage of the
    truth is a rate, tested above, not a per-case property). Before the fix the value was the
    one selection left and the interval a grid bootstrap with parabolic interpolation: on
    hysteresis seed 9 and on these campaigns it excluded the value."""
    from bayesmag._src.pipeline.discover.pipeline import _locate_interval
    designs, ctx, ext, t_true, block = _designs_with_step(seed, frac, factor)
    loc = _locate_interval(designs, (), ext, ctx, block, seed)
    lo, hi = loc["interval95"]
    assert lo <= loc["value"] <= hi, loc
    run = np.asarray(designs.inputs.run)
    span = float(np.ptp(np.asarray(designs.inputs.time)[run == 1]))
    assert abs(loc["value"] - t_true) <= 0.02 * span, (loc, t_true, span)


def test_refined_hysteresis_threshold_explains_the_step_its_grid_value_left():
    """Independent hysteresis seed 9 (z, driven by y): with the search grid's threshold (0.5 of
    By's reach, 21.92 uT) the modelled state flips at an excursion the generator's state does
    not flip at, and a run_step inside run 2 took up the misfit. The threshold refined after
    selection (``search.refine_threshold``) fits better without any step than the grid's
    threshold does with the best step (exact SSE over every sample time of the run)."""
    from bayesmag._src.core import catalogue as C
    from bayesmag._src.pipeline.discover.frame import Extension
    from bayesmag._src.pipeline.discover.search import refine_threshold, relocate
    from independent_campaigns import campaign

    d, _ = campaign("hysteresis", 9, n=5000)
    designs, ctx = _designs(d)
    hyst = [s for s in C.Hysteresis.grid(ctx, 2) if s.component.axis == "y" and s.component.mode == "excursion"
            and s.component.across_runs and abs(s.component.threshold - 0.5 * ctx.reach[1]) < 1e-3][0]
    grid_ext = Extension(hyst, "sensor", 2)
    folds3 = np.tile(np.arange(d.n) * 5 // d.n, 3)
    step = relocate(designs, (grid_ext,), Extension(C.Setting(C.RunStep(run_id=2, at=0.0)), "sensor", 2), folds3, ctx)
    sse = lambda exts: _profile(designs.matrix(exts), designs.y[:, None])[0][0]   # noqa: E731
    refined = refine_threshold(designs, (), grid_ext, folds3)
    assert refined.component.threshold != grid_ext.component.threshold
    assert sse((refined,)) < sse((grid_ext, step)) < sse((grid_ext,)), (sse((refined,)), sse((grid_ext, step)))


@pytest.mark.parametrize("sd", [0.0, 0.005, 0.02, 0.1])
def test_temperature_log_sd_reads_white_noise_off_ramps_and_holds(sd):
    """The log's white-noise sd that tau's se takes in (``frame.temperature_log_sd``): on a chamber
    programme of ramps (1 C/min) and holds in three runs, sampled at 1 s, within 10 % of the
    planted sd (20,000 samples: the MAD estimator's relative sd is ~0.6 %), 0 for a noiseless log."""
    from bayesmag._src.pipeline.discover.frame import temperature_log_sd
    rng = np.random.default_rng(7)
    t = np.arange(20_000.0)
    prog = np.interp(t % 6000, [0, 1200, 2400, 3600, 6000], [20, 40, 40, 10, 20])
    run = (t // 6700).astype(int)
    est = temperature_log_sd(prog + sd * rng.standard_normal(t.size), run)
    assert (est == 0.0) if sd == 0 else abs(est / sd - 1) < 0.1, (est, sd)
