"""Discovery on simulated ground truth (declared thresholds) and its bad-input handling.

The many-seed sweep is benchmarks/bench_discovery.py (numbers in docs/discovery.md);
these tests run a handful of blind cases that must all pass.
"""

import json
import subprocess
import sys

import numpy as np
import pytest

import bayesmag
from bayesmag._src.discover import DiscoverOptions, discover, main
from bayesmag.simulate import get_effect, simulate

N = 3000
#: The concealed parameter must be recovered within this many reported standard errors of the
#: noise-free (pseudo-true) value; 3 rather than the benchmark's 2 keeps the test failure rate < 1%.
N_SE = 3.0
#: Discovery on these rows must finish within this many seconds on a loaded 2-core CPU.
TIME_LIMIT_S = 60.0


def _run(effects, seed=0, **kw):
    d = simulate(N, design="campaign", seed=seed, effects=effects)
    return d, discover(d, figures=False, seed=seed, **kw)


def test_clean_data_no_missing_physics():
    _, r = _run([])
    assert r.no_missing_physics, (r.findings, r.unexplained)
    assert r.to_json()["no_missing_physics"] is True
    assert r.seconds < TIME_LIMIT_S


def test_hidden_cubic_named_on_its_axis_and_recovered():
    eff = get_effect("cubic", out="z", inp="z", coeff=-2e-5)
    d, r = _run([eff], seed=1)
    main_finding = [f for f in r.findings if f["axis"] == "z"]
    assert main_finding and main_finding[0]["effect"] == "cubic_nonlinearity", r.findings
    assert {f["effect"] for f in r.findings} == {"cubic_nonlinearity"}
    # pseudo-true value: same structure fitted on the noise-free recording
    clean = simulate(N, design="campaign", seed=1, effects=[eff], noise_sd=0.0)
    ref = discover(clean, figures=False, candidates=("cubic_nonlinearity",), max_terms=1)
    p = main_finding[0]["parameters"]["c_z"]
    p0 = next(f for f in ref.findings if f["axis"] == "z")["parameters"]["c_z"]["value"]
    assert abs(p["value"] - p0) <= N_SE * p["se"], (p, p0)
    assert r.final["rmse"]["z"] < 0.95 * r.baseline["rmse"]["z"]


def test_periodic_is_unexplained_not_forced():
    _, r = _run([get_effect("periodic", axis="y", amplitude=1.0, period=25.0)], seed=2)
    assert not r.findings, r.findings
    per = [u for u in r.unexplained if u["variable"] == "periodic"]
    assert per and per[0]["axis"] == "y" and "25" in per[0]["where"], r.unexplained
    assert not r.no_missing_physics


def test_no_time_column_skips_time_domain_candidates():
    d = simulate(N, design="campaign", seed=3, effects=[get_effect("axis_quadratic", out="x", inp="y", coeff=0.004)])
    d = bayesmag.CalibrationData(d.b_meas, d.temperature, d.b_ref, None, d.run, "no time")
    r = discover(d, figures=False)
    assert {s["candidate"] for s in r.skipped} == {"thermal_lag", "timing_offset", "offset_drift"}
    assert any("no time column" in n for n in r.notes)
    assert any(f["effect"] == "axis_quadratic" and f["axis"] == "x" for f in r.findings), r.findings


def test_single_run_by_run_falls_back_and_few_rows_skip():
    d = simulate(400, design="campaign", seed=4, n_runs=1)
    r = discover(d, figures=False, cv="by_run")
    assert any("needs at least two runs" in n for n in r.notes)
    assert r.baseline["cv"].startswith("5-fold")
    small = simulate(120, design="campaign", seed=4, n_runs=2)
    r2 = discover(small, figures=False)
    assert any("training rows" in s["reason"] for s in r2.skipped), r2.skipped


def test_bad_options_name_the_valid_set():
    with pytest.raises(ValueError, match="valid"):
        DiscoverOptions(candidates=("warp_drive",))
    with pytest.raises(ValueError, match="must be one of"):
        DiscoverOptions(cv="random")


def test_cli_writes_folder_atomically(tmp_path):
    d = simulate(N, design="campaign", seed=5, effects=[get_effect("hysteresis", axis="x", h=0.6)])
    csv = tmp_path / "rec.csv"
    bayesmag.write_csv(d, csv)
    out = tmp_path / "disc"
    assert main(["--data", str(csv), "--out", str(out)]) == 0
    j = json.loads((out / "findings.json").read_text())
    for key in ("baseline", "final", "findings", "unexplained", "no_missing_physics"):
        assert key in j
    assert set(j["baseline"]["rmse"]) == {"x", "y", "z"}
    f = j["findings"][0]
    assert f["effect"] == "hysteresis" and f["axis"] == "x"
    for key in ("parameters", "rmse_before", "rmse_after", "evidence", "explanation"):
        assert key in f
    assert (out / "report.md").read_text().startswith("# Discovery")
    assert list(out.glob("*.png"))
    assert not list(tmp_path.glob(".disc.partial*"))
    # the extended model is usable by `bayesmag run`
    extra = bayesmag.PhysicsModel.paper(extra=tuple(
        __import__("bayesmag._src.physics", fromlist=["make_extra"]).make_extra(s) for s in j["extra_terms"]))
    assert "h" in extra.param_names


def test_measured_frame_temperature_curvature_on_y_is_named():
    """An offset curvature added to the y READING reaches the calibrated y output times the
    gain 2.37 - 0.052 T (a cubic in T): the cubic variant of temperature_quadratic names it."""
    eff = get_effect("temperature_quadratic", axis="y", coeff=0.03, t_ref=24.0)
    _, r = _run([eff], seed=6)
    assert any(f["axis"] == "y" and f["effect"] == "temperature_quadratic" for f in r.findings), r.findings
    assert {f["effect"] for f in r.findings} == {"temperature_quadratic"}, r.findings


def test_timing_offset_se_includes_interpolation_term():
    d = simulate(N, design="campaign", seed=7, effects=[get_effect("timing_offset", delta=-0.3)])
    r = discover(d, figures=False, seed=7, candidates=("timing_offset",))
    assert r.findings
    for f in r.findings:
        p = f["parameters"]["delta"]
        assert p["se_interpolation"] == pytest.approx(0.025)          # dt / 10 at 4 Hz
        assert p["se"] == pytest.approx(np.hypot(p["se_statistical"], p["se_interpolation"]))
        assert abs(p["value"] - (-0.3)) <= 2 * p["se"], p
