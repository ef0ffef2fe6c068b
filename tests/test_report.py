"""The calibration certificate: units, fit statistics, Type A/B budget with nu_eff, k and U = k u_c."""

import math
import os
import re
import time

import numpy as np
import pytest
from scipy import stats

import bayesmag
from bayesmag._src.app.config import config_from_dict
from bayesmag._src.app.report import (coverage_factor, expanded_uncertainties, parameter_unit, render_report,
                                      welch_satterthwaite)


def test_welch_satterthwaite_hand_computed():
    # u = (0.3, 0.4), nu = (4, 9): u_c^4 = 0.25^2 = 0.0625; sum u^4/nu = 0.0081/4 + 0.0256/9 = 0.00486944...
    assert welch_satterthwaite([0.3, 0.4], [4, 9]) == pytest.approx(12.835139760410724, rel=1e-12)
    # a Type B term (infinite dof) raises nu_eff: only the finite terms count in the denominator
    assert welch_satterthwaite([0.3, 0.4], [4, math.inf]) == pytest.approx(0.0625 / (0.0081 / 4), rel=1e-12)
    assert welch_satterthwaite([0.3, 0.4], [math.inf, math.inf]) == math.inf
    assert welch_satterthwaite([0.5], [7]) == pytest.approx(7.0)                 # one component: its own dof
    assert welch_satterthwaite([0.0, 0.2], [3, 10]) == pytest.approx(10.0)       # a zero term adds nothing


@pytest.mark.parametrize("nu, level", [(9, 0.95), (12.835, 0.95), (3, 0.99), (1000, 0.6827)])
def test_coverage_factor_is_students_t(nu, level):
    assert coverage_factor(nu, level) == pytest.approx(stats.t.ppf(0.5 + level / 2, nu), rel=1e-12)


def test_coverage_factor_textbook_values():
    assert coverage_factor(9, 0.95) == pytest.approx(2.262157, abs=1e-6)     # GUM table G.2
    assert coverage_factor(math.inf, 0.95) == pytest.approx(1.959964, abs=1e-6)


@pytest.mark.parametrize("name, unit", [("S_x", "1"), ("Ks_z", "1/C"), ("O", "uT"), ("Ko", "uT/C"),
                                        ("q_xx", "1/uT"), ("q_xy_T", "(1/uT)/C"), ("Ko2", "uT/C^2"),
                                        ("log_tau", "ln(s)"), ("delta", "s"), ("drift_rate", "uT/s")])
def test_parameter_units(name, unit):
    assert parameter_unit(name) == unit


def _metrics_params(n=1000, p=8):
    names = ["S_x", "S_y", "S_z", "Ks_x", "Ks_y", "Ks_z", "O", "Ko"][:p]
    ax = {"values": {k: 1.0 for k in names}, "std": {k: 0.01 for k in names}, "correlation": np.eye(p).tolist(),
          "condition_number": 1.0, "residual_std": 0.1, "rmse_in_sample": 0.1, "lag1_autocorrelation": 0.0,
          "solver": {"result": "converged", "steps": 4}, "covariance_info": {"method": "white"}}
    per = lambda v: {a: v for a in "xyz"}  # noqa: E731
    m = {"data": {"source": "test", "n_rows": n + 100, "runs": [0]},
         "split": {"description": "d", "n_train": n, "n_test": 100},
         "raw": {"rmse": per(1.0), "mae": per(1.0)},
         "physics": {k: per(0.1) for k in ("rmse", "mae", "nll", "crps", "coverage")},
         "uq": {"level": 0.95, "mean_aleatoric": per(0.06), "residual_term": per(0.08), "mean_epistemic": per(0.01),
                "sigma_in_sd": {"bx": 0.05, "by": 0.05, "bz": 0.05, "T": 0.0}, "sigma_in_source": "auto: x"}}
    params = {"n_rows": n, "model": {"param_names": names}, "axes": {a: ax for a in "xyz"}}
    return m, params


def _row(text, label):
    line = next(ln for ln in text.splitlines() if ln.startswith(f"| {label}"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_budget_combines_with_reference_and_reports_k_and_U():
    m, params = _metrics_params()
    text = render_report(m, params, reference_sd=0.05)
    ref = _row(text, "reference magnetometer")
    assert ref[1:6] == ["B", "inf", "0.050", "0.050", "0.050"]                 # two significant figures
    # the noise sd's dof: a MAD (37 % efficient) of n - 2R overlapping second differences (0.514 of them independent)
    nu_noise = 0.37 / (1 + 2 * (4 / 9 + 1 / 36)) * (1000 - 2)
    assert _row(text, "aleatoric")[1:3] == ["A", f"{nu_noise:.0f}"] == ["A", "190"]
    assert _row(text, "epistemic")[1:3] == ["A", "992"]                  # independent residuals: n - p
    uc = math.sqrt(0.06**2 + 0.08**2 + 0.01**2 + 0.05**2)
    nu = welch_satterthwaite([0.06, 0.08, 0.01, 0.05], [nu_noise, 992, 992, math.inf])
    k = stats.t.ppf(0.975, nu)
    ex = expanded_uncertainties(m, params, reference_sd=0.05)["same_session"]["x"]
    assert ex["u_c"] == pytest.approx(uc, rel=1e-12) and ex["U"] == pytest.approx(k * uc, rel=1e-12)
    assert _row(text, "**combined u_c, same session")[3] == f"{uc:.2g}" == "0.11"
    assert float(_row(text, "coverage factor k (95%), same session")[3]) == pytest.approx(k, abs=1e-3)
    assert _row(text, "**expanded uncertainty U = k u_c, same session")[3] == f"{k * uc:.2g}" == "0.22"
    # without the reference the combined uncertainty is smaller
    assert expanded_uncertainties(m, params)["same_session"]["x"]["u_c"] == pytest.approx(
        math.sqrt(uc**2 - 0.05**2), rel=1e-12)


def test_autocorrelated_residuals_count_their_effective_rows():
    """With lag-1 autocorrelation rho the residual and parameter parts have n (1 - rho) / (1 + rho) - p dof (AR(1)
    effective sample size), per axis, and the budget prints them x / y / z."""
    m, params = _metrics_params()
    params["axes"] = {a: {**params["axes"][a], "lag1_autocorrelation": r} for a, r in zip("xyz", (0.0, 0.5, 0.8))}
    want = [1000 * (1 - r) / (1 + r) - 8 for r in (0.0, 0.5, 0.8)]
    assert _row(render_report(m, params), "epistemic")[2] == " / ".join(f"{v:.0f}" for v in want) == "992 / 325 / 103"
    ex = expanded_uncertainties(m, params)["same_session"]
    nu_noise = 0.37 / (1 + 2 * (4 / 9 + 1 / 36)) * 998
    for a, v in zip("xyz", want):
        assert ex[a]["nu_eff"] == pytest.approx(welch_satterthwaite([0.06, 0.08, 0.01, 0.0], [nu_noise, v, v, math.inf]))


def test_a_non_gaussian_hybrid_states_the_U_of_its_own_interval():
    """A Laplace hybrid's 95 % interval is +-2.12 sd (b ln 20, b = sd / sqrt 2): the certificate's k is that family's
    factor (recorded per axis by the job as budget.interval_factor) times the t(nu_eff) / z correction, so U is the
    half-width of the predictor's own interval (with k = 1.96 it was 8 % below it)."""
    from bayesmag._src.app.report import hybrid_new_session
    m, params = _metrics_params()
    factor = np.log(20) / np.sqrt(2)
    m["network"] = {"primary": "laplace", "training": {"laplace": {"budget": {
        "parts": {"aleatoric_nn": {a: 0.03 for a in "xyz"}, "epistemic_nn": {a: 0.01 for a in "xyz"},
                  "epistemic_physics": {a: 0.005 for a in "xyz"}}, "interval_scale": {a: 1.0 for a in "xyz"},
        "transfer_sd": {a: 0.0 for a in "xyz"}, "family": "laplace", "average": "rms",
        "interval_factor": {a: factor for a in "xyz"}}}}}
    assert hybrid_new_session(m) is not None
    ex = expanded_uncertainties(m, params)
    uc = math.sqrt(0.03**2 + 0.01**2 + 0.005**2)
    nu = ex["same_session"]["x"]["nu_eff"]
    assert ex["same_session"]["x"]["U"] == pytest.approx(factor * stats.t.ppf(0.975, nu) / stats.norm.ppf(0.975) * uc,
                                                         rel=1e-12)
    assert factor == pytest.approx(2.1183, abs=1e-4) and ex["family"] == "laplace"
    text = render_report(m, params)
    assert "the laplace family's interval half-width in sd" in text


def test_fit_statistics_block():
    m, params = _metrics_params(n=1000, p=8)
    row = _row(render_report(m, params), "x | 1000")
    rss = 1000 * 0.1**2
    assert float(row[4]) == pytest.approx(rss)
    assert float(row[6]) == pytest.approx(rss / 0.06**2, rel=1e-4)                   # chi^2 vs the input noise
    assert float(row[8]) == pytest.approx(1000 * math.log(rss / 1000) + 2 * 9, abs=0.01)            # AIC
    assert float(row[9]) == pytest.approx(1000 * math.log(rss / 1000) + 9 * math.log(1000), abs=0.01)  # BIC
    assert row[10:] == ["4", "converged"]


def test_units_on_every_parameter_and_nuts_and_hybrid_sections():
    m, params = _metrics_params()
    m["nuts"] = {"axes": {"x": {"verdict": "agrees with LM", "max_rhat": 1.001, "min_ess_bulk": 2100.0,
                                "min_ess_tail": 1800.0, "divergences": 0}}, "thresholds": {"rhat_max": 1.01, "ess_min": 400}}
    rows = [{"axis": "x", "parameter": "S_x", "mean": "1.0", "sd": "0.01", "r_hat": "1.0004", "ess_bulk": "2500",
             "ess_tail": "2000"}]
    m["hybrid_vs_physics"] = {"gaussian": {"x": {"mean_diff": 0.01, "t": 5.0, "p": 1e-6, "cohens_d": 0.2}}}
    m["network"] = {"training": {"gaussian": {"x": {"epochs_run": 120, "best_epoch": 70, "best_val_loss": -1.5}}}}
    text = render_report(m, params, nuts_rows=rows)
    table = [ln for ln in text.splitlines() if re.match(r"\| (S|Ks|O|Ko)", ln)]
    assert len(table) == 24 and all(ln.split("|")[4].strip() in ("1", "1/C", "uT", "uT/C") for ln in table)
    assert "| x | agrees with LM | 1.0010 | 2100 | 1800 | 0 |" in text
    assert "| x | S_x | 1.000 | 0.010 | 1.0004 | 2500 | 2000 |" in text          # mean and sd GUM-rounded
    assert "| gaussian | x | 0.01 | 5.000 | 1e-06 | 0.200 |" in text
    assert "| gaussian | x | 120 | 70 | -1.5 |" in text
    assert "interval scale" not in text and "conformal scale" not in text     # no conformal scale, no column


def test_hybrid_section_reports_the_conformal_scale_and_its_folds():
    m, params = _metrics_params()
    m["network"] = {"training": {"gaussian": {
        "x": {"epochs_run": 120, "best_epoch": 70, "best_val_loss": -1.5, "interval_scale": 1.234},
        "y": {"epochs_run": 90, "best_epoch": 40, "best_val_loss": -1.0, "interval_scale": 1.0},
        "conformal": {"folds": 3, "block_fraction": 0.25, "rows": 2880, "ensemble_passes": [17, 17, 16]}}}}
    text = render_report(m, params)
    assert "| gaussian | x | 120 | 70 | -1.5 | 1.234 |" in text and "| gaussian | y | 90 | 40 | -1 | 1.000 |" in text
    assert "cross-conformal over 3 time-block folds, each one block of 0.25 of every run's training rows" in text
    assert "| conformal scale c |" in text and "interval scale k" not in text   # not confused with coverage k
    assert "2880 rows scored" in text and "(17 / 17 / 16 MC passes)" in text


def test_report_of_a_run_uses_reference_sd_from_the_config(tmp_path):
    raw = {"data": {"source": "simulated", "simulate": {"design": "campaign", "n": 800, "seed": 3, "noise_sd": 0.05}},
           "split": {"kind": "time_blocks", "test_fraction": 0.2}, "uq": {"method": "analytic", "reference_sd": 0.02},
           "physics": {"t0": "mean"}, "output": {"figures": False, "progress": False}}
    bayesmag.run_job(config_from_dict(raw), tmp_path / "run")
    text = (tmp_path / "run" / "report.md").read_text()
    assert _row(text, "reference magnetometer")[1:6] == ["B", "inf", "0.020", "0.020", "0.020"]
    assert "## Fit statistics" in text and "expanded uncertainty U = k u_c, new session" in text


def test_reference_sd_is_validated():
    with pytest.raises(bayesmag.ConfigError, match="reference_sd"):
        config_from_dict({"data": {"source": "simulated"}, "uq": {"reference_sd": -1.0}})


def test_residual_figures_label_axes_and_count_rows_inside_the_band(tmp_path):
    from bayesmag._src.app import plots
    rng = np.random.default_rng(1)
    n = 4000
    sd = np.tile([0.1, 0.2, 0.05], (n, 1))
    ref = rng.uniform(-50, 50, (n, 3))
    d = bayesmag.CalibrationData(ref, rng.uniform(10, 40, n), ref, np.arange(n) * 0.25, np.repeat([1, 2], n // 2))
    pred = ref - sd * rng.standard_normal((n, 3))          # residuals exactly N(0, sd^2)
    fig = plots.residuals_vs(d.b_ref, d.b_ref - pred, sd, xlabels=["a", "b", "c"], title="t")
    share = [float(re.search(r"([\d.]+)% inside", ax.get_title()).group(1)) for ax in fig.axes]
    assert len(share) == 9 and all(abs(s - 95.45) < 1.5 for s in share)     # P(|Z| <= 2) = 95.45%
    assert fig.axes[1].get_xlabel() == "b" and fig.axes[3].get_ylabel() == "residual By (uT)"
    files = plots.residual_figures(tmp_path, d, pred, sd)
    assert all((tmp_path / f).stat().st_size > 10_000 for f in files)
    tfig = plots.residuals_vs_time(d.time, d.run, d.b_ref - pred, sd)
    assert len(tfig.axes) == 6 and tfig.axes[0].get_xlabel() == "time since run start (s)"


def test_histogram_and_pit_panels_are_labelled(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt
    from bayesmag._src.app import hybrid_plots, plots
    from bayesmag.likelihoods import Gaussian
    saved = []
    monkeypatch.setattr(plt.Figure, "savefig", lambda self, *a, **k: saved.append(self))
    monkeypatch.setattr(plt, "close", lambda fig=None: None)
    r = np.random.default_rng(0).standard_normal((200, 3))
    plots.residual_histograms(tmp_path / "h.png", {"physics": r})
    hybrid_plots.pit_histograms(tmp_path / "p.png", {"gaussian": Gaussian(np.zeros((200, 3)), np.ones((200, 3)))}, r)
    for fig in saved:
        for ax in fig.axes:
            assert ax.get_xlabel() and ax.get_ylabel()


def _draw_named(folder, name):
    (folder / name).write_text(f"{name} {os.getpid()}")


def _draw_slowly(folder, name):
    time.sleep(0.2)
    _draw_named(folder, name)


def _draw_broken(folder):
    raise RuntimeError("bad figure")


def test_figure_worker_draws_in_background_and_surfaces_errors(tmp_path):
    """FigureWorker: queued figures land in the output folder at finish(), drawn in one other process;
    a drawing error is raised by finish() (never a silently missing figure); close() removes its folder."""
    from bayesmag._src.app.plots import FigureWorker

    with FigureWorker() as figs:
        figs.submit(_draw_named, "a.png")
        figs.submit(_draw_named, "b.png")
        private = figs._tmp
        assert figs.finish(tmp_path, share=False) == ["a.png", "b.png"]
    pids = {(tmp_path / n).read_text().split()[1] for n in ("a.png", "b.png")}
    assert not private.exists() and len(pids) == 1 and pids != {str(os.getpid())}

    shared = tmp_path / "shared"                    # share=True (the job): this process draws what the worker
    shared.mkdir()                                  # has not taken; every file once, from one of the two
    names = [f"{i}.png" for i in range(8)]
    with FigureWorker() as figs:
        for n in names:
            figs.submit(_draw_slowly, n)
        assert figs.finish(shared) == sorted(names)
    pids = [(shared / n).read_text().split()[1] for n in names]
    assert sorted(p.name for p in shared.iterdir()) == sorted(names)
    assert str(os.getpid()) in pids and len(set(pids)) == 2       # both processes drew

    for share in (False, True):                     # drawn by the worker, or by whichever process takes it
        with FigureWorker() as figs:
            figs.submit(_draw_broken)
            with pytest.raises(RuntimeError, match="bad figure"):
                figs.finish(tmp_path, share=share)
    with FigureWorker(enabled=False) as figs:       # [output] figures = false: nothing drawn, nothing moved
        figs.submit(_draw_named, "c.png")
        assert figs.finish(tmp_path) == [] and not (tmp_path / "c.png").exists()


def test_budget_names_the_networks_new_session_part_when_estimated():
    """[uq] transfer_networks: the hybrid adds the network's own new-session sd; the budget must say so."""
    m, params = _metrics_params()
    m["transfer"] = {"method": "leave_one_run_out", "sd": {"x": 0.1, "y": 0.2, "z": 0.1}, "per_run": {}}
    parts = {"network aleatoric": {a: 0.05 for a in "xyz"}}
    assert "network's own new-session error" not in render_report(m, params, network_parts=parts)
    m["network"] = {"training": {"gaussian": {"transfer_network": {"method": "by_run_folds",
                                                                   "sd": {"x": 0.034, "y": 0.102, "z": 0.035}}}}}
    row = _row(render_report(m, params, network_parts=parts), "network's own new-session error")
    assert row[1:] == ["A", "0.034", "0.10", "0.035"]
