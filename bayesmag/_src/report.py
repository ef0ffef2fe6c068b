"""A fit report a metrologist can read: ``report.md`` from a run folder's metrics.json and params.json."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["write_report", "render_report"]

AXES = ("x", "y", "z")


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def _param_table(ax: str, p: dict, corr_threshold: float) -> list[str]:
    vals, sds, names = p["values"], p["std"], list(p["values"])
    lines = [f"### Axis {ax}", "", "| parameter | value | std. error | relative |", "|---|---|---|---|"]
    for n in names:
        v, s = vals[n], sds[n]
        rel = f"{abs(s / v) * 100:.2g}%" if v != 0 else "-"
        lines.append(f"| {n} | {_fmt(v)} | {_fmt(s)} | {rel} |")
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


def render_report(metrics: dict, params: dict, figures: list[str] = (), corr_threshold: float = 0.9,
                  network_parts: dict | None = None) -> str:
    m = metrics
    lines = ["# Calibration report", "",
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
    u = m["uq"]
    lines += ["## Uncertainty budget (mean standard deviation over test rows, uT)", "",
              "| part | x | y | z |", "|---|---|---|---|"]
    parts = {"aleatoric (input noise through the model)": u["mean_aleatoric"],
             "residual (scatter the model does not explain)": u.get("residual_term", {a: 0.0 for a in AXES}),
             "epistemic (parameter uncertainty)": u["mean_epistemic"]}
    for k, v in parts.items():
        lines.append(f"| {k} | " + " | ".join(f"{v[a]:.4g}" for a in AXES) + " |")
    dom = {a: max(parts, key=lambda k: parts[k][a]).split(" (")[0] for a in AXES}
    if network_parts:
        for k, v in network_parts.items():
            lines.append(f"| {k} | " + " | ".join(f"{v[a]:.4g}" for a in AXES) + " |")
        if m.get("network", {}).get("fusion", "moment_match") == "paper":
            lines += ["", "With the residual network (fusion `paper`), the hybrid's total variance is the paper's "
                      "root-sum-of-squares of physics aleatoric, physics epistemic, network aleatoric and network "
                      "epistemic parts (the input noise is counted twice: intervals tend to over-cover)."]
        else:
            lines += ["", "With the residual network (fusion `moment_match`), the hybrid's total variance is network "
                      "aleatoric + network epistemic + physics epistemic: the network learned its aleatoric part "
                      "from residuals that already contain the propagated input noise and the unexplained scatter, "
                      "so the physics aleatoric and residual parts are not added again."]
    lines += ["", "Dominant physics part per axis: " + ", ".join(f"{a}: {dom[a]}" for a in AXES) + ".",
              f"Input noise sd (Bx, By, Bz in uT, T in C): "
              + ", ".join(f"{k} {v:.3g}" for k, v in u["sigma_in_sd"].items()) + f" ({u['sigma_in_source']}).", ""]
    lines += transfer_section(m)
    d = m.get("domain")
    if d:
        lines += ["## Calibration domain", "",
                  "Training ranges (with margin): " + "; ".join(f"{k} [{lo:.3g}, {hi:.3g}]"
                                                                for k, (lo, hi) in d["training_ranges"].items()) + ".",
                  f"Test rows outside it: {d['n_outside']} of {d['n_rows']}.", ""]
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


def write_report(run_dir: str | Path) -> Path:
    """(Re)write ``report.md`` in a run folder from its metrics.json and params.json."""
    run_dir = Path(run_dir)
    for f in ("metrics.json", "params.json"):
        if not (run_dir / f).exists():
            raise FileNotFoundError(f"{run_dir} has no {f}: give a folder written by `bayesmag run`.")
    metrics = json.loads((run_dir / "metrics.json").read_text())
    params = json.loads((run_dir / "params.json").read_text())
    figs = sorted(p.name for p in run_dir.glob("*.png"))
    out = run_dir / "report.md"
    out.write_text(render_report(metrics, params, figs, network_parts=_network_parts(run_dir / "predictions.csv")))
    return out
