r"""A calibration certificate a metrologist can read: ``report.md`` from a run folder's files.

Besides accuracy and coverage it holds, in the manner of the GUM (JCGM 100:2008): units on
every parameter; fit statistics (n, p, chi-square, AIC/BIC, solver iterations); and an
uncertainty budget with Type A / Type B labels, degrees of freedom per component, the
effective degrees of freedom (Welch-Satterthwaite, GUM G.4.1), the coverage factor
:math:`k = t_{(1+p)/2}(\nu_{\mathrm{eff}})` and the expanded uncertainty :math:`U = k\,u_c` per
axis, including the reference magnetometer's own uncertainty (``[uq] reference_sd``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

__all__ = ["write_report", "render_report", "welch_satterthwaite", "coverage_factor", "parameter_unit",
           "uncertainty_budget", "fit_statistics"]

AXES = ("x", "y", "z")

_UNITS = {"S": "1", "Ks": "1/C", "O": "uT", "Ko": "uT/C", "Ko2": "uT/C^2", "Ko3": "uT/C^3", "Ks2": "1/C^2",
          "q": "1/uT", "c": "1/uT^2", "h": "uT", "drift_rate": "uT/s", "run_step": "uT", "log_tau": "ln(s)",
          "delta": "s"}


def parameter_unit(name: str) -> str:
    """Unit of a physics parameter from its name (``S_x`` -> 1, ``Ks_y`` -> 1/C, ``q_xx_T`` -> 1/(uT C), ...)."""
    thermal = name.endswith("_T")
    base = name[:-2] if thermal else name
    unit = _UNITS.get(base, _UNITS.get(base.split("_")[0], "?"))
    if thermal:
        unit = f"({unit})/C" if unit != "1" else "1/C"
    return unit


def welch_satterthwaite(u, nu) -> float:
    """Effective degrees of freedom of ``u_c = sqrt(sum u_i^2)`` (GUM eq. G.2b); ``inf`` terms add nothing."""
    u = np.asarray(u, dtype=np.float64)
    nu = np.asarray(nu, dtype=np.float64)
    uc4 = float(np.sum(u**2)) ** 2
    finite = np.isfinite(nu) & (u > 0)
    den = float(np.sum(u[finite] ** 4 / nu[finite]))
    return math.inf if den == 0 else uc4 / den


def coverage_factor(nu_eff: float, level: float) -> float:
    """``k`` such that ``u_c k`` covers ``level`` (Student t with ``nu_eff`` degrees of freedom; normal if infinite)."""
    from scipy import stats
    q = 0.5 * (1.0 + level)
    return float(stats.norm.ppf(q) if not math.isfinite(nu_eff) else stats.t.ppf(q, nu_eff))


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def _param_table(ax: str, p: dict, corr_threshold: float) -> list[str]:
    vals, sds, names = p["values"], p["std"], list(p["values"])
    lines = [f"### Axis {ax}", "", "| parameter | value | std. uncertainty | unit | relative |", "|---|---|---|---|---|"]
    for n in names:
        v, s = vals[n], sds[n]
        rel = f"{abs(s / v) * 100:.2g}%" if v != 0 else "-"
        lines.append(f"| {n} | {_fmt(v)} | {_fmt(s)} | {parameter_unit(n)} | {rel} |")
    corr = np.asarray(p["correlation"])
    pairs = [(names[i], names[j], corr[i, j]) for i in range(len(names)) for j in range(i + 1, len(names))
             if abs(corr[i, j]) > corr_threshold]
    lines.append("")
    if pairs:
        lines.append(f"Correlations with |rho| > {corr_threshold}: " +
                     ", ".join(f"{a}-{b} {c:+.3f}" for a, b, c in sorted(pairs, key=lambda t: -abs(t[2]))))
    cond = p["condition_number"]
    advice = ("well conditioned" if cond < 1e3 else
              "moderately ill-conditioned: some parameters trade off against each other" if cond < 1e6 else
              "ill-conditioned: individual parameters are poorly determined even though the predictions are fine; "
              "see the design notes, and consider [physics] t0 = \"mean\"")
    lines += ["", f"Condition number (correlation-scaled): {cond:.3g} - {advice}.",
              f"Residual sd {p['residual_std']:.4g} uT; residual lag-1 autocorrelation "
              f"{p['lag1_autocorrelation']:.2f}" + (" (the white covariance understates the standard errors; use "
                                                    "[physics] covariance = \"newey_west\")"
                                                    if p["lag1_autocorrelation"] > 0.3 and
                                                    p["covariance_info"].get("method") == "white" else "") + ".", ""]
    return lines


def _per_axis_sd(reference_sd) -> dict:
    r = reference_sd if isinstance(reference_sd, (list, tuple)) else [reference_sd] * 3
    return {a: float(v) for a, v in zip(AXES, r)}


def uncertainty_budget(m: dict, params: dict, network_parts: dict | None = None, reference_sd=0.0) -> list[str]:
    """The uncertainty-budget section: components with Type A/B and dof, u_c, nu_eff, k and U per axis."""
    u = m["uq"]
    level = u["level"]
    n = int(params.get("n_rows") or m["split"]["n_train"])
    p = len(params["model"]["param_names"])
    auto = str(u.get("sigma_in_source", "")).startswith("auto")
    ref = _per_axis_sd(reference_sd)
    # (label, values per axis, type, degrees of freedom, how it was evaluated)
    comps = [
        ("aleatoric (input noise through the model)", u["mean_aleatoric"], "A" if auto else "B",
         n - 1 if auto else math.inf, "noise sd estimated from the training rows" if auto else "noise sd from the config"),
        ("residual (scatter the model does not explain)", u.get("residual_term", {a: 0.0 for a in AXES}), "A", n - p,
         "residual variance of the fit"),
        ("epistemic (parameter uncertainty)", u["mean_epistemic"], "A", n - p, "parameter covariance of the fit"),
        ("reference magnetometer (`[uq] reference_sd`)", ref, "B", math.inf,
         "stated by the user (certificate of the reference)" if any(ref.values()) else "not given (0)"),
    ]
    lines = ["## Uncertainty budget (standard uncertainties, mean over test rows, uT)", "",
             "| component | type | dof | x | y | z | evaluation |", "|---|---|---|---|---|---|---|"]
    dof = lambda v: "inf" if not math.isfinite(v) else f"{v:.0f}"  # noqa: E731
    for label, vals, typ, nu, how in comps:
        lines.append(f"| {label} | {typ} | {dof(nu)} | " + " | ".join(f"{vals[a]:.4g}" for a in AXES) + f" | {how} |")
    combined = {}
    for a in AXES:
        us = [c[1][a] for c in comps]
        nus = [c[3] for c in comps]
        uc = math.sqrt(sum(x * x for x in us))
        nu_eff = welch_satterthwaite(us, nus)
        k = coverage_factor(nu_eff, level)
        combined[a] = (uc, nu_eff, k, k * uc)
    lines.append("| **combined u_c (physics)** | | | " + " | ".join(f"{combined[a][0]:.4g}" for a in AXES) + " | "
                 "root sum of squares |")
    lines.append("| effective dof nu_eff | | | " + " | ".join(dof(combined[a][1]) for a in AXES)
                 + " | Welch-Satterthwaite |")
    lines.append(f"| coverage factor k ({level:.0%}) | | | " + " | ".join(f"{combined[a][2]:.4f}" for a in AXES)
                 + " | Student t(nu_eff) |")
    lines.append("| **expanded uncertainty U = k u_c** | | | " + " | ".join(f"{combined[a][3]:.4g}" for a in AXES)
                 + " | |")
    dom = {a: max(comps, key=lambda c: c[1][a])[0].split(" (")[0] for a in AXES}
    if network_parts:
        lines += ["", "Hybrid stage (residual network), for comparison:", "",
                  "| component | type | x | y | z |", "|---|---|---|---|---|"]
        for k_, v in network_parts.items():
            lines.append(f"| {k_} | A | " + " | ".join(f"{v[a]:.4g}" for a in AXES) + " |")
        if m.get("network", {}).get("fusion", "moment_match") == "paper":
            lines += ["", "With the residual network (fusion `paper`), the hybrid's total variance is the paper's "
                      "root-sum-of-squares of physics aleatoric, physics epistemic, network aleatoric and network "
                      "epistemic parts (the input noise is counted twice: intervals tend to over-cover)."]
        else:
            lines += ["", "With the residual network (fusion `moment_match`), the hybrid's total variance is network "
                      "aleatoric + network epistemic + physics epistemic: the network learned its aleatoric part "
                      "from residuals that already contain the propagated input noise and the unexplained scatter, "
                      "so the physics aleatoric and residual parts are not added again."]
    lines += ["", "Type A: evaluated statistically from the calibration data; Type B: from other information "
              "(JCGM 100:2008, 4.2-4.3). The reference's uncertainty enters the budget only: the job's intervals "
              "and coverage figures do not include it.",
              "Dominant physics part per axis: " + ", ".join(f"{a}: {dom[a]}" for a in AXES) + ".",
              "Input noise sd (Bx, By, Bz in uT, T in C): "
              + ", ".join(f"{k_} {v:.3g}" for k_, v in u["sigma_in_sd"].items()) + f" ({u['sigma_in_source']}).", ""]
    return lines


def fit_statistics(m: dict, params: dict, reference_sd=0.0) -> list[str]:
    """Fit statistics per axis: n, p, dof, RSS, chi-square against the known noise, AIC, BIC, LM iterations."""
    n = int(params.get("n_rows") or m["split"]["n_train"])
    p = len(params["model"]["param_names"])
    ref = _per_axis_sd(reference_sd)
    lines = ["## Fit statistics (training rows)", "",
             "| axis | n | p | dof | RSS (uT^2) | sigma (uT) | chi^2 | chi^2/dof | AIC | BIC | LM iterations | result |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for a in AXES:
        ax = params["axes"][a]
        rss = n * ax["rmse_in_sample"] ** 2
        sigma = math.sqrt(m["uq"]["mean_aleatoric"][a] ** 2 + ref[a] ** 2)
        chi2 = rss / sigma**2 if sigma > 0 else math.inf
        ll = n * math.log(rss / n) if rss > 0 else -math.inf
        aic, bic = ll + 2 * (p + 1), ll + (p + 1) * math.log(n)
        sol = ax.get("solver", {})
        lines.append(f"| {a} | {n} | {p} | {n - p} | {rss:.5g} | {sigma:.4g} | {chi2:.5g} | {chi2 / (n - p):.4g} | "
                     f"{aic:.2f} | {bic:.2f} | {sol.get('steps', '-')} | {sol.get('result', '-')} |")
    lines += ["", "chi^2 = RSS / sigma^2 with sigma^2 the propagated input-noise variance (+ reference variance): "
              "chi^2/dof near 1 means the model explains the data down to the known noise. AIC = n ln(RSS/n) + 2(p+1), "
              "BIC = n ln(RSS/n) + (p+1) ln n (Gaussian likelihood, noise variance counted as a parameter).", ""]
    return lines


def _nuts_section(m: dict, nuts_rows: list[dict] | None) -> list[str]:
    nuts = m.get("nuts")
    if not nuts:
        return []
    lines = ["## NUTS cross-check", "",
             "| axis | verdict | max R-hat | min ESS bulk | min ESS tail | divergences |", "|---|---|---|---|---|---|"]
    for ax, b in nuts.get("axes", {}).items():
        lines.append(f"| {ax} | {b.get('verdict', '-')} | {b.get('max_rhat', float('nan')):.4f} | "
                     f"{b.get('min_ess_bulk', float('nan')):.0f} | {b.get('min_ess_tail', float('nan')):.0f} | "
                     f"{b.get('divergences', '-')} |")
    if nuts_rows:
        lines += ["", "| axis | parameter | mean | sd | R-hat | ESS bulk | ESS tail |", "|---|---|---|---|---|---|---|"]
        for r in nuts_rows:
            f = lambda k, spec: format(float(r[k]), spec) if r.get(k) not in (None, "") else "-"  # noqa: E731
            lines.append(f"| {r.get('axis', '')} | {r.get('parameter', '')} | {f('mean', '.6g')} | {f('sd', '.3g')} | "
                         f"{f('r_hat', '.4f')} | {f('ess_bulk', '.0f')} | {f('ess_tail', '.0f')} |")
    th = nuts.get("thresholds", {})
    if th:
        lines += ["", f"Thresholds: R-hat <= {th.get('rhat_max')}, ESS >= {th.get('ess_min')}."]
    return lines + [""]


def _hybrid_section(m: dict) -> list[str]:
    tests = m.get("hybrid_vs_physics")
    train = m.get("network", {}).get("training")
    if not tests and not train:
        return []
    lines = ["## Hybrid stage: paired test and training", ""]
    if tests:
        lines += ["Paired t-test (one-sided) of the per-row squared error, physics minus hybrid, on the test rows "
                  "(positive: the hybrid is better):", "",
                  "| likelihood | axis | mean difference (uT^2) | t | p | Cohen's d |", "|---|---|---|---|---|---|"]
        for lik, axes in tests.items():
            for a in AXES:
                if a in axes:
                    t = axes[a]
                    lines.append(f"| {lik} | {a} | {t['mean_diff']:.4g} | {t['t']:.3f} | {t['p']:.3g} | "
                                 f"{t['cohens_d']:.3f} |")
        lines.append("")
    if train:
        scaled = any("interval_scale" in axes.get(a, {}) for axes in train.values() for a in AXES)
        lines += ["| likelihood | axis | epochs run | best epoch | best validation loss |"
                  + (" interval scale k |" if scaled else ""), "|---|---|---|---|---|" + ("---|" if scaled else "")]
        for lik, axes in train.items():
            for a in AXES:
                if a in axes:
                    t = axes[a]
                    k = t.get("interval_scale")
                    lines.append(f"| {lik} | {a} | {t.get('epochs_run', '-')} | {t.get('best_epoch', '-')} | "
                                 f"{t.get('best_val_loss', float('nan')):.5g} |"
                                 + ((f" {k:.3f} |" if k is not None else " - |") if scaled else ""))
        lines.append("")
        for lik, axes in train.items():
            c = axes.get("conformal")
            if c:
                lines += [f"Interval scale k ({lik}): cross-conformal over {c['folds']} time-block folds, each one block "
                          f"of {c.get('block_fraction', float('nan')):.3g} of every run's training rows (the network's "
                          f"validation fraction, or as long as the job's test blocks if longer), {c['rows']} rows "
                          f"scored, each by the fold network that did not see it; k multiplies the sd of the hybrid's intervals (floored at 1), and the "
                          f"{c['folds']} fold networks predict together as an ensemble "
                          f"({' / '.join(map(str, c.get('ensemble_passes', [])))} MC passes).", ""]
    return lines


def render_report(metrics: dict, params: dict, figures: list[str] = (), corr_threshold: float = 0.9,
                  network_parts: dict | None = None, reference_sd=0.0, nuts_rows: list[dict] | None = None) -> str:
    m = metrics
    lines = ["# Calibration report (certificate)", "",
             f"Data: {m['data']['source']} ({m['data']['n_rows']} rows, runs {m['data']['runs']}). "
             f"Split: {m['split']['description']} ({m['split']['n_train']} train / {m['split']['n_test']} test rows).",
             f"Covariance: {params.get('covariance_method', '')}. Physics model parameters: "
             f"{', '.join(params['model']['param_names'])}.", ""]
    for w in m.get("warnings", []):
        lines += [f"> **Warning.** {w}", ""]
    for note in params.get("design_notes", []):
        lines += [f"> **Design note.** {note}", ""]
    lines += ["## Accuracy and coverage (test rows)", "",
              "| stage | metric | x | y | z |", "|---|---|---|---|---|"]

    def row(stage, key, block, pct=False):
        vals = [block[key][a] * (100 if pct else 1) for a in AXES]
        f = (lambda v: f"{v:.1f}%") if pct else (lambda v: f"{v:.4g}")
        lines.append(f"| {stage} | {key} | " + " | ".join(f(v) for v in vals) + " |")

    row("raw", "rmse", m["raw"]); row("raw", "mae", m["raw"])
    for k in ("rmse", "mae", "nll", "crps"):
        row("physics", k, m["physics"])
    row("physics", "coverage", m["physics"], pct=True)
    for name, block in m.get("hybrid", {}).items():
        for k in ("rmse", "mae", "nll", "crps"):
            if k in block:
                row(f"hybrid ({name})", k, block)
        if "coverage" in block:
            row(f"hybrid ({name})", "coverage", block, pct=True)
    level = m["uq"]["level"]
    lines += ["", f"Coverage is of central {level:.0%} intervals; a trustworthy model is close to {level:.0%}.", ""]
    lines += uncertainty_budget(m, params, network_parts, reference_sd)
    lines += fit_statistics(m, params, reference_sd)
    lines += transfer_section(m)
    d = m.get("domain")
    if d:
        lines += ["## Calibration domain", "",
                  "Training ranges (with margin): " + "; ".join(f"{k} [{lo:.3g}, {hi:.3g}]"
                                                                for k, (lo, hi) in d["training_ranges"].items()) + ".",
                  f"Test rows outside it: {d['n_outside']} of {d['n_rows']}.", ""]
    lines += _hybrid_section(m) + _nuts_section(m, nuts_rows)
    lines += ["## Physics parameters", ""]
    for ax in AXES:
        lines += _param_table(ax, params["axes"][ax], corr_threshold)
    if figures:
        lines += ["## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    t = m.get("timings", {})
    if t:
        lines += ["Timings (s): " + ", ".join(f"{k} {v:.3g}" for k, v in t.items()) + "."]
    return "\n".join(lines) + "\n"


def transfer_section(m: dict) -> list[str]:
    """report.md lines on the transfer (between-session) part of the budget and the dynamic domain."""
    tr = m.get("transfer")
    if not tr:
        return []
    sd, z = tr["sd"], 1.959963984540054
    lines = ["## Transfer to a new session", ""]
    if tr["method"] == "off":
        return lines + ["Transfer uncertainty is off (`[uq] transfer = \"off\"`): intervals for new recordings "
                        "hold within-session parts only and will be too narrow if the sensor changes between "
                        "sessions.", ""]
    lines.append(f"This calibration transfers to a new session with +/- {z * sd['x']:.3g} / {z * sd['y']:.3g} / "
                 f"{z * sd['z']:.3g} uT (x / y / z; 1.96 x the between-session sd {sd['x']:.3g} / {sd['y']:.3g} / "
                 f"{sd['z']:.3g} uT), added in quadrature to every prediction of a new recording (`bayesmag apply`; "
                 f"column `transfer`).")
    if tr["method"] == "leave_one_run_out":
        rows = [(r, v) for r, v in tr["per_run"].items()]
        lines += ["Estimated by leaving each training run out (rows inside the other runs' value domain):", "",
                  "| left-out run | in-domain rows | RMSE x / y / z (uT) |", "|---|---|---|"]
        for r, v in rows:
            rm = " / ".join(f"{v['rmse'][a]:.3g}" for a in AXES) if v["rmse"] else "not refitted"
            lines.append(f"| {r} | {v['n_in_domain']} | {rm} |")
    else:
        lines.append(f"> **Warning.** {tr['warning']}")
    n_new = tr.get("n_test_rows_new_session", 0)
    lines += ["", f"Test rows from runs not in the training data (they include the transfer part): {n_new}."
              + (" The test rows share sessions with the training rows, so their scores above do not include it."
                 if n_new == 0 else ""), ""]
    d = m.get("domain", {})
    if d.get("by_reason"):
        lines += ["Test rows out of domain by reason: " + ", ".join(f"{k} {v}" for k, v in d["by_reason"].items())
                  + ".", ""]
    return lines


def _network_parts(path: Path) -> dict | None:
    """Mean network aleatoric / epistemic sd per axis from predictions.csv, if the hybrid stage ran."""
    import csv
    if not path.exists():
        return None
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or "x_aleatoric_nn" not in rows[0]:
        return None
    out = {}
    for label, col in (("network aleatoric (learned from the residuals)", "aleatoric_nn"),
                       ("network epistemic (MC DropConnect)", "epistemic_nn")):
        out[label] = {a: float(np.mean([float(r[f"{a}_{col}"]) for r in rows])) for a in AXES}
    return out


def _axes_null_as_nan(d):
    """Per-axis values written as ``null`` (strict JSON for NaN, jsonio) read back as NaN for the tables."""
    if isinstance(d, dict):
        return {k: (float("nan") if v is None and k in AXES else _axes_null_as_nan(v)) for k, v in d.items()}
    if isinstance(d, list):
        return [_axes_null_as_nan(v) for v in d]
    return d


def write_report(run_dir: str | Path) -> Path:
    """(Re)write ``report.md`` in a run folder from its metrics.json and params.json."""
    run_dir = Path(run_dir)
    for f in ("metrics.json", "params.json"):
        if not (run_dir / f).exists():
            raise FileNotFoundError(f"{run_dir} has no {f}: give a folder written by `bayesmag run`.")
    metrics = _axes_null_as_nan(json.loads((run_dir / "metrics.json").read_text()))
    params = _axes_null_as_nan(json.loads((run_dir / "params.json").read_text()))
    figs = sorted(p.name for p in run_dir.glob("*.png"))
    out = run_dir / "report.md"
    reference_sd = 0.0
    if (run_dir / "calibration.json").exists():
        cfg = json.loads((run_dir / "calibration.json").read_text()).get("config", {})
        reference_sd = cfg.get("uq", {}).get("reference_sd", 0.0)
    nuts_rows = None
    if (run_dir / "nuts_summary.csv").exists():
        import csv
        with open(run_dir / "nuts_summary.csv", newline="") as f:
            nuts_rows = list(csv.DictReader(f))
    out.write_text(render_report(metrics, params, figs, network_parts=_network_parts(run_dir / "predictions.csv"),
                                 reference_sd=reference_sd, nuts_rows=nuts_rows))
    return out
