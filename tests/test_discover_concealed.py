"""Three concealed effects an outside tester found misnamed (and the report wording around them).

1. A thermal lag without a time column (or with ms stamps) and a random-walk offset were named
   ``run_offset`` with a power-cycling story: a per-run term must now be constant within its runs
   (``checks.constant_within_runs``), and a finding whose rivals could not be searched says so.
2. A gain that depends on the field magnitude was named a cubic: the catalogue has ``magnitude_gain``.
3. The report quoted 2 % (code and docs: 5 %), showed the drop-one z that did not decide, and said "no
   extension improves" where the closest candidate had just missed.

Thresholds are declared with each test. The seeds were fixed before they were first run and not changed after
(20-24: a one-off sweep of |B| gains and cubics on both generators, docs/discovery.md; 31-33: walks, lags and
offsets); development used seeds 0-5. Every outcome on them is asserted, not a rate.
"""

import dataclasses

import numpy as np
import pytest

import bayesmag
from bayesmag._src.core import catalogue as C
from bayesmag._src.pipeline.discover import discover
from bayesmag._src.pipeline.discover.diagnostics import serial_contrast, structure
from bayesmag._src.pipeline.discover.options import MIN_GAIN, N_PERM, Z_DISTINCT, Z_MIN, Z_RUN, DiscoverOptions
from bayesmag._src.pipeline.discover.pipeline import _explanation, _untested
from bayesmag._src.pipeline.discover.result import DiscoveryResult, report_markdown
from bayesmag.simulate import get_effect, simulate
from independent_campaigns import campaign

N = 5000


# --------------------------------------------------------------------------- 1. per-run constants


def _blocks(n_runs=6, per_run=5, rows=100):
    run = np.repeat(np.arange(n_runs), per_run * rows)
    blocks = np.repeat(np.arange(n_runs * per_run), rows)
    return run, blocks


@pytest.mark.parametrize("seed", range(5))
def test_serial_contrast_sees_a_random_walk_inside_runs_and_not_constant_runs(seed):
    """Six runs of five 100-row blocks (the shape of a 5000-row campaign with long blocks). Constant per-run offsets
    plus white noise: block means are exchangeable within a run, z < Z_DISTINCT. A random walk whose drift over a
    run is 3x the noise sd of a block mean (3x0.1 here; the walk of ``simulate``'s offset_drift at walk_sd 0.05 uT/s^0.5
    over a 208 s run is ~7x): neighbouring blocks alike, z >= Z_DISTINCT."""
    rng = np.random.default_rng([seed, 5])
    run, blocks = _blocks()
    steps = rng.normal(0, 3.0, 6)[run]
    noise = rng.standard_normal(run.size)
    z0, p0 = serial_contrast(steps + noise, blocks, run, seed=seed)
    walk = np.concatenate([np.cumsum(rng.standard_normal(500)) * 0.3 / np.sqrt(500 / 5) for _ in range(6)])
    z1, p1 = serial_contrast(steps + noise + 3 * walk, blocks, run, seed=seed)
    assert z0 < Z_DISTINCT and z1 >= Z_DISTINCT, (z0, p0, z1, p1)
    assert 1 / (N_PERM + 1) <= p1 <= p0


def test_serial_contrast_needs_neighbouring_pairs():
    run, blocks = _blocks(n_runs=2, per_run=2)
    assert serial_contrast(np.arange(run.size, dtype=float), blocks, run) == (0.0, 1.0)


def test_rivals_are_catalogue_entries_and_a_missing_time_column_qualifies_the_cause():
    """A run offset's rivals (a lag on steady ramps, a drift, a step inside a run) are catalogue names; when they were
    not searched the explanation becomes one possible cause, naming them, why and how to test them."""
    assert set(C.RunOffset.rivals) <= set(C.CATALOGUE)
    skipped = [{"candidate": n, "reason": "needs a time column"} for n in ("thermal_lag", "offset_drift", "run_step")]
    text = _explanation(C.RunOffset(), _untested(skipped, {}, None))
    assert text.startswith("One possible cause: power cycling") and "Not established" in text
    assert "thermal_lag" in text and "needs a time column" in text and "time column (seconds)" in text
    assert _explanation(C.RunOffset(), {}) == C.RunOffset.explanation
    assert _explanation(C.AxisQuadratic(), _untested(skipped, {}, None)) == C.AxisQuadratic.explanation
    cands = {("thermal_lag", "whole", None): [], ("run_offset", "sensor", 0): [], ("run_step", "sensor", 0): []}
    ms = _untested([], cands, "median time step 250 s")
    assert set(ms) == {"thermal_lag", "run_step"} and "ms or us" in ms["thermal_lag"]
    assert "declare the time column's unit" in _explanation(C.RunOffset(), ms)


def test_time_scale_without_a_time_column_is_in_rows():
    """Time equals the row index: the correlation time is in rows, no seconds and no spectrum period are claimed
    (a no-time thermal lag campaign said 'time scale 320 s')."""
    rng = np.random.default_rng(1)
    n = 3000
    r = np.convolve(rng.standard_normal(n + 200), np.ones(200) / 14, "valid")[:n, None] * np.ones((1, 3))
    d = bayesmag.CalibrationData(np.zeros((n, 3)), np.full(n, 25.0), np.zeros((n, 3)), None, np.zeros(n, int), "t")
    u = structure(d, r, [], dt=1.0, time_available=False)
    assert u and all(x["time_scale_s"] is None and x["time_scale_rows"] > 10 for x in u)
    assert all("rows (correlation time; no time column)" in x["description"] for x in u)
    assert structure(d, r, [], dt=1.0)[0]["time_scale_s"] is not None


def test_correlation_time_is_not_made_white_by_a_few_spikes():
    """An AR(1) residual of correlation time ~25 rows with 6 spikes of 40 sd (Belsten's z channel, once its offset
    left the model: 0.25 s, one sample): the correlation time stays within 20 % of the spike-free one."""
    from bayesmag._src.pipeline.discover.diagnostics import correlation_time
    rng = np.random.default_rng(3)
    e = rng.standard_normal(4000)
    r = np.empty_like(e)
    r[0] = e[0]
    for k in range(1, e.size):
        r[k] = 0.96 * r[k - 1] + 0.28 * e[k]
    spiky = r.copy()
    spiky[rng.choice(r.size, 6, replace=False)] += 40 * r.std()
    clean = correlation_time(r, 1.0)
    assert clean > 10 and abs(correlation_time(spiky, 1.0) / clean - 1) < 0.2, (clean, correlation_time(spiky, 1.0))


@pytest.mark.extended
@pytest.mark.parametrize("seed", [31, 32])
def test_thermal_lag_without_time_is_not_given_a_power_cycling_cause(seed):
    """The independent generator's thermal lag (tau 60-240 s), time column dropped: a lag cannot be searched. Whatever
    discovery names, no finding states the run-offset story as established: every run_offset is either rejected as
    wandering within runs (and reported as unexplained) or carries ``cause_established = False`` naming thermal_lag
    as untested for want of a time column. The old code named run_offset with the bare power-cycling explanation
    (seed 0: on the z channel and the y output, block z 3.61 / 3.69)."""
    d, _ = campaign("thermal_lag", seed, n=4000)
    r = discover(bayesmag.CalibrationData(d.b_meas, d.temperature, d.b_ref, None, d.run, "no time"), figures=False)
    assert "thermal_lag" in {s["candidate"] for s in r.skipped}
    assert r.findings or r.unexplained
    for f in r.findings:
        if f["effect"] == "run_offset":
            assert f["cause_established"] is False, f
            assert "thermal_lag" in {x["effect"] for x in f["untested_rivals"]}, f
            assert f["explanation"].startswith("One possible cause") and "time column" in f["explanation"], f
    for u in r.unexplained:
        assert u["time_scale_s"] is None and "not searched: thermal_lag" in u["description"], u


@pytest.mark.extended
def test_run_offset_with_ms_stamps_says_lags_were_searched_on_the_wrong_time_scale():
    """Genuine per-run offsets (independent run_offset, seed 31) with ms time stamps: still named, constant within
    runs, but the lag and step searches read the ms as seconds, so the cause is stated as one possibility."""
    d, p = campaign("run_offset", 31, n=N)
    ms = bayesmag.CalibrationData(d.b_meas, d.temperature, d.b_ref, d.time * 1000.0, d.run, "ms stamps")
    r = discover(ms, figures=False)
    f = [f for f in r.findings if f["effect"] == "run_offset" and f["channel"] == p.channel]
    assert len(f) == 1, r.findings
    assert not f[0]["evidence"]["within_run"]["wanders"], f[0]["evidence"]
    assert f[0]["cause_established"] is False and "ms or us" in f[0]["untested_rivals"][0]["reason"], f[0]
    assert any("time_unit" in n for n in r.notes)


@pytest.mark.extended
@pytest.mark.parametrize("seed", [31, 32, 33])
def test_random_walk_offset_is_not_named_a_per_run_constant(seed):
    """``simulate``'s offset_drift with only a random walk (walk_sd 0.1 uT/s^0.5 on y, reading noise 0.5 uT, 5000 rows
    in 6 runs of 208 s): the offset wanders within runs (and across the 60 s gaps). No run_offset on y states the
    power-cycling cause: measured, seed 31 rejects it as wandering (serial z 2.88, pieces of runs 39 % better) and
    reports y unexplained; seed 32 names offset_drift on y (the catalogue twin of this simulate effect, whose linear
    rate takes up part of the walk) and reports y unexplained; seed 33 keeps it with the cause in doubt (pieces 15 %
    better out of sample, serial z 1.73 < 2). y holds unexplained structure in all three. Before, a walk of 0.05 was named run_offset on y by z_run 3.70 with the
    power-cycling explanation (seed 0)."""
    d = simulate(N, design="campaign", seed=seed, noise_sd=0.5,
                 effects=[get_effect("offset_drift", axis="y", rate=0.0, walk_sd=0.1)])
    r = discover(d, figures=False, seed=seed)
    for f in r.findings:
        if f["effect"] == "run_offset" and f["axis"] == "y":        # kept only with its cause in doubt, said why
            assert f["cause_established"] is False and "wander within runs" in f["explanation"], f
    assert "y" in {u["axis"] for u in r.unexplained}, r.unexplained


@pytest.mark.extended
@pytest.mark.parametrize("seed", [31, 32])
def test_true_run_offsets_stay_named_and_constant_within_runs(seed):
    """The check does not take real per-run steps away: independent run_offset campaigns are named on their channel,
    with the within-run check not rejecting (it needs serial z >= 2 *and* a gain >= 1 % from pieces of runs)."""
    d, p = campaign("run_offset", seed, n=N)
    r = discover(d, figures=False, seed=seed)
    f = [f for f in r.findings if f["effect"] == "run_offset" and f["channel"] == p.channel]
    assert len(f) == 1, r.findings
    w = f[0]["evidence"]["within_run"]
    assert not w["wanders"] and w["gain_pieces"] < MIN_GAIN, w
    assert "cause_established" not in f[0]


# --------------------------------------------------------------------------- 2. a gain that depends on |B|

#: Planted sizes: the |B|-gain's (and the cubic's) contribution at the 98th percentile of |u| is FACTOR_SIM x the
#: reading noise (0.5 uT) on simulate, the bench's factor 3 for calibrated sizes, and FACTOR_IND x the mean channel
#: noise sd on the independent generator, the low end of its U(8, 20) sizing of every other effect.
FACTOR_SIM, FACTOR_IND = 3.0, 10.0


def _sim_magnitude(seed):
    clean = simulate(N, design="campaign", seed=seed, noise_sd=0.5)
    M = np.quantile(np.linalg.norm(clean.b_meas, axis=1), 0.98)
    g = float(np.random.default_rng([seed, 11]).choice([-1, 1])) * FACTOR_SIM * 0.5 / M ** 2
    return simulate(N, design="campaign", seed=seed, noise_sd=0.5, effects=[get_effect("magnitude_gain", g=g)]), g


def _ind_magnitude(seed):
    d, p = campaign("clean", seed, n=N)
    u = np.asarray(d.b_meas)
    m = np.linalg.norm(u, axis=1)
    g = (float(np.random.default_rng([seed, 11]).choice([-1, 1])) * FACTOR_IND
         * float(np.mean(p.params["noise_sd_sensor_units"])) / np.quantile(m, 0.98) ** 2)
    return bayesmag.CalibrationData(u * (1 + g * m)[:, None], d.temperature, d.b_ref, d.time, d.run, "|B| gain"), g


@pytest.mark.extended
@pytest.mark.parametrize("gen,seed", [("simulate", 20), ("simulate", 21), ("independent", 20), ("independent", 21)])
def test_magnitude_dependent_gain_is_named_as_itself(gen, seed):
    """B_cal = (1 + g |B|) S B, planted on both generators: one finding, magnitude_gain on the whole sensor, g within
    3 se of the planted value (the catalogue term inverts the simulate twin exactly). Before: cubic_nonlinearity."""
    d, g = (_sim_magnitude if gen == "simulate" else _ind_magnitude)(seed)
    r = discover(d, figures=False, seed=seed)
    assert [(f["effect"], f["channel"]) for f in r.findings] == [("magnitude_gain", "all")], r.findings
    est = r.findings[0]["parameters"]["g"]
    assert abs(est["value"] - g) <= 3 * est["se"], (est, g)
    assert r.findings[0]["config"]["name"] == "magnitude_gain" and r.findings[0]["config"]["g0"] == pytest.approx(
        est["value"], rel=1e-5)


@pytest.mark.extended
@pytest.mark.parametrize("gen,seed", [("simulate", 20), ("independent", 20)])
def test_a_planted_cubic_is_still_a_cubic(gen, seed):
    """A cubic on one channel (simulate: coeff sized to FACTOR_SIM x the noise at the channel's 98th percentile; the
    independent generator's own cubic kind) is named cubic_nonlinearity on its channel, with no magnitude_gain."""
    if gen == "simulate":
        ax = "xyz"[int(np.random.default_rng([seed, 12]).integers(3))]
        clean = simulate(N, design="campaign", seed=seed, noise_sd=0.5)
        M = np.quantile(np.abs(clean.b_meas[:, "xyz".index(ax)]), 0.98)
        d = simulate(N, design="campaign", seed=seed, noise_sd=0.5,
                     effects=[get_effect("cubic", out=ax, inp=ax, coeff=-FACTOR_SIM * 0.5 / M ** 3)])
    else:
        d, p = campaign("cubic", seed, n=N)
        ax = p.channel
    r = discover(d, figures=False, seed=seed)
    assert ("cubic_nonlinearity", ax) in [(f["effect"], f["channel"]) for f in r.findings], r.findings
    assert "magnitude_gain" not in {f["effect"] for f in r.findings}, r.findings


# --------------------------------------------------------------------------- 3. report wording


def _result(findings=(), closest=None, unexplained=()):
    base = {"rmse": dict.fromkeys("xyz", 0.1), "mae": dict.fromkeys("xyz", 0.1),
            "lag1_autocorrelation": dict.fromkeys("xyz", 0.1), "cv": "5-fold"}
    return DiscoveryResult(list(findings), list(unexplained), [], base, base, [], [], [], DiscoverOptions(), "test",
                           1.0, closest_not_accepted=closest)


def _finding(**ev):
    evidence = {"oos_gain": 0.1, "decided_by": "run contrast z_run", "z_decisive": 3.7, "p_value": 1e-4, "z": 1.78,
                "p_value_block": 0.04, "delta_bic_eff": -50.0, "drop_one_z": 2.01, "drop_one_gain": 0.05,
                "drop_one_decided_by": "run contrast z_run", "drop_one_z_decisive": 3.70, "drop_one_z_run": 3.70,
                "within_run": {"serial_z": 1.2, "serial_p": 0.11, "pieces": 2, "gain_pieces": 0.004, "wanders": False}}
    evidence.update(ev)
    return {"effect": "run_offset", "frame": "sensor", "channel": "y", "axis": "y", "outputs": ["y"],
            "description": "offset steps between runs", "setting": "run_offset(y channel)", "parameters": {},
            "rmse_before": dict.fromkeys("xyz", 0.2), "rmse_after": dict.fromkeys("xyz", 0.1), "evidence": evidence,
            "explanation": C.RunOffset.explanation, "indistinguishable_from": [], "config": {"name": "run_offset"}}


def test_report_shows_the_drop_one_statistic_that_decides():
    """A run offset accepted on z_run: its drop-one line gave the block z 2.0 (which decides nothing); now z_run."""
    md = report_markdown(_result([_finding()]))
    assert f"drop-one given the other findings: run contrast z_run = 3.70 (threshold {Z_RUN:.2f}" in md
    assert "its block z 2.01 does not decide" in md and "drop-one z given the other findings = 2.0" not in md
    md = report_markdown(_result([_finding(drop_one_decided_by="block z", drop_one_z=4.2)]))
    assert f"drop-one given the other findings: block z = 4.20 (threshold {Z_MIN})" in md
    assert "Constant within its runs (what a per-run term claims): not rejected" in md


def test_report_quotes_the_unexplained_share_and_how_far_the_closest_candidate_missed():
    """Nothing found: the report said 'no catalogue extension improves' beside a closest candidate at block z 3.3,
    and quoted 2 % of the residual variance for located structure where the claim uses 5 %."""
    near = {"effect": "cubic_nonlinearity", "where": "cubic(y channel)", "decided_by": "block z", "z_decisive": 3.3,
            "p_value": 5e-4, "z": 3.3, "p_value_block": 5e-4, "oos_gain": 0.03, "delta_bic_eff": -40.0,
            "not_accepted_because": "block z 3.30 < 3.5 (short by 0.20)", "short_by": {"z": 0.2}}
    md = report_markdown(_result(closest=near))
    assert "No catalogue extension improves" not in md
    assert "the closest, cubic_nonlinearity (cubic(y channel)), missed: its block z = 3.30 is 0.20 short of 3.50" in md
    assert ">= 5% of the residual variance" in md and "2%" not in md
    assert "(short by 0.20)" in md
    md = report_markdown(_result())
    assert "No catalogue extension improves the thermo-affine model out of sample" in md


def test_closest_candidate_names_its_miss_per_criterion():
    from bayesmag._src.pipeline.discover.search import Score
    s = Score(("cubic_nonlinearity", "sensor", 1), None, np.zeros(3), 0.004, 0.004, 3.3, -4.0, 3)
    assert s.short_by == pytest.approx({"z": 0.2, "gain": 0.006, "delta_bic_eff": 6.0})
    assert "block z 3.30 < 3.5 (short by 0.20)" in s.shortfall and "(short by 6.0)" in s.shortfall
    assert dataclasses.replace(s, z=3.6, gain=0.02, dbic=-12.0).short_by == {}


@pytest.mark.realdata
def test_the_search_space_docs_discovery_md_states_is_the_codes(belsten):
    """docs/discovery.md states the number of candidate groups and settings on the Belsten recording; it said 389
    settings while the code searched 569 (47 groups). Counted here as `discover` prints it before searching."""
    import re
    from pathlib import Path

    class Stop(Exception):
        pass

    seen = []

    def progress(msg):
        seen.append(msg)
        if msg.startswith("searching"):
            raise Stop

    with pytest.raises(Stop):
        discover(belsten, figures=False, progress=progress)
    groups, settings = map(int, re.match(r"searching (\d+) candidate groups \((\d+) settings\)", seen[-1]).groups())
    doc = " ".join((Path(__file__).resolve().parents[1] / "docs" / "discovery.md").read_text().split())
    assert f"{groups} groups ({settings} settings on the 6-run Belsten recording" in doc, (groups, settings)
