"""Files of a fleet run: one calibration folder per sensor, the fleet table, figures and ``fleet_report.md``."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

__all__ = ["write_fleet_outputs", "write_fleet_report"]


def write_fleet_outputs(folder: Path, cfg, summary: dict, *, stages, sigma_in, ids, feats, feat_names, z, flagged,
                        timings: dict, sources, files=None) -> None:
    """Sensor folders (``sensors/<id>/``: the files of a single ``bayesmag run`` folder,
    :func:`~bayesmag._src.app.fleet_sensors.write_sensor_folder`), ``fleet_table.csv`` and the figures, into
    ``folder``. ``files``: each sensor's ``(recording path, sha256)``, or None (simulated)."""
    from bayesmag._src.app.fleet_sensors import write_sensor_folder

    folder = Path(folder)
    if cfg.sensor_folders:
        n = max(len(ids), 1)
        per = {f"fleet_{k}_per_sensor": round(v / n, 5) for k, v in timings.items()}
        for i, sid in enumerate(ids):
            write_sensor_folder(folder / "sensors" / sid, stages[i], cfg=cfg, verdict=summary["sensors"][i],
                                sigma_in=np.asarray(sigma_in[i]), source=sources[i], timings=per,
                                recording=None if files is None else files[i])
    with open(folder / "fleet_table.csv", "w", newline="") as f:
        w = csv.writer(f)
        lim = list(summary["sensors"][0]["limits_quantities"]) if summary["sensors"] else []
        w.writerow(["id", "verdict", "fails_limits", "outlier", "max_abs_robust_z"] + lim + feat_names)
        for i, s in enumerate(summary["sensors"]):
            zr = s["max_abs_robust_z"]
            w.writerow([s["id"], s["verdict"], ";".join(s["fails_limits"]), "" if zr is None else int(s["outlier"]),
                        "" if zr is None else f"{zr:.4g}"] + [f"{s['limits_quantities'][k]:.6g}" for k in lim]
                       + [f"{v:.8g}" for v in feats[i]])
    if cfg.figures:
        _figures(folder, cfg, summary, z, flagged)


def _figures(folder: Path, cfg, summary: dict, z, flagged) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sensors = summary["sensors"]
    keys = list(sensors[0]["limits_quantities"])
    fig, axes = plt.subplots(2, (len(keys) + 1) // 2, figsize=(4 * ((len(keys) + 1) // 2), 6.5))
    for ax, k in zip(axes.flat, keys):
        v = np.array([s["limits_quantities"][k] for s in sensors])
        lo, hi = float(min(v.min(), summary["limits"][k])), float(max(v.max(), summary["limits"][k]))
        bins = np.linspace(lo, hi + 1e-12, 40)
        ax.hist([v[~flagged], v[flagged]], bins=bins, stacked=True, color=["tab:blue", "tab:red"],
                label=["pass", "flagged"])
        ax.axvline(summary["limits"][k], color="k", ls="--", lw=1, label="limit")
        ax.set_yscale("log")
        ax.set_title(k, fontsize=9)
    for ax in list(axes.flat)[len(keys):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=8)
    fig.suptitle(f"{summary['name']}: {summary['n_sensors']} sensors, {summary['n_fail']} flagged")
    fig.tight_layout()
    fig.savefig(folder / "fleet_limits.png", dpi=110)
    plt.close(fig)
    if summary["outlier_test"]["computed"]:
        zmax = np.abs(z).max(axis=1)
        fig, ax = plt.subplots(figsize=(8, 3.5))
        idx = np.arange(len(zmax))
        ax.scatter(idx[~flagged], zmax[~flagged], s=6, color="tab:blue", label="pass")
        ax.scatter(idx[flagged], zmax[flagged], s=14, color="tab:red", label="flagged")
        truth = summary.get("ground_truth")
        if truth:
            ids = [s["id"] for s in sensors]
            planted = [ids.index(k) for k in truth["defective"]]
            ax.scatter(planted, zmax[planted], s=60, facecolors="none", edgecolors="k", label="planted defect")
        ax.axhline(cfg.outlier_z, color="k", ls="--", lw=1, label=f"|z| = {cfg.outlier_z:g}")
        ax.set_yscale("log")
        ax.set_xlabel("sensor")
        ax.set_ylabel("max |robust z| over parameters, log RMSE")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(folder / "fleet_outliers.png", dpi=110)
        plt.close(fig)


#: units of the limit quantities and of the parameters (at t0, per output axis; T in C, field in uT)
_LIMIT_UNITS = {"max_offset_ut": "uT", "max_gain_error": "1", "max_cross_axis": "1", "max_rmse_ut": "uT",
                "min_coverage": "fraction", "max_offset_tempco": "uT/C"}
_PARAM_UNITS = {"S": "1", "Ks": "1/C", "O": "uT", "Ko": "uT/C", "log_rmse": "ln uT"}


def _unit(name: str) -> str:
    """The unit of a limit quantity or a parameter column name such as ``Ks_y[x]``; '' where unknown."""
    if name in _LIMIT_UNITS:
        return _LIMIT_UNITS[name]
    base = name.split("[")[0]
    return _PARAM_UNITS.get(base, _PARAM_UNITS.get(base.split("_")[0], ""))


def write_fleet_report(folder: Path, summary: dict) -> Path:
    """``fleet_report.md`` from ``fleet.json``'s content."""
    folder = Path(folder)
    s = summary
    lines = [f"# Fleet report: {s['name']}", "",
             f"{s['n_sensors']} sensor{'s' if s['n_sensors'] != 1 else ''}; **{s['n_pass']} pass, {s['n_fail']} flagged** (a limit failed or an outlier "
             f"against the fleet). Parameters at t0 = {s['t0']:g} C; intervals at level {s['level']:g}.", ""]
    net = s.get("network") or {}
    if net.get("enabled"):
        lines += [f"Residual network per sensor ({net['likelihoods'][0]}, {net['hidden_layers']} x {net['width']}, "
                  f"fusion {net['fusion']}), trained in one batch: the test RMSE and coverage in the verdicts are the "
                  f"hybrid prediction's (physics-only ones in `fleet.json`).", ""]
    ot = s["outlier_test"]
    if ot["computed"]:
        lines.append(f"Outliers: robust z = (x - median) / (1.4826 MAD) of every parameter and of log test RMSE over "
                     f"the fleet; flagged when max |z| > {ot['threshold_abs_z']:g}: {len(s['outliers'])} unit(s).")
    else:
        lines.append(f"Outlier test not computed: {ot['reason']}.")
    gt = s.get("ground_truth")
    if gt:
        lines += ["", f"Ground truth (simulated): {len(gt['defective'])} planted defective unit(s); flagged "
                      f"{len(gt['planted_flagged'])}, missed {gt['planted_missed'] or 'none'}, other units flagged "
                      f"{gt['false_flags'] or 'none'} -> {'exact' if gt['exact'] else 'NOT exact'}."]
    lines += ["", "## Limits", "", "| quantity | unit | limit | fleet median | p05 | p95 | worst | sensors failing |",
              "|---|---|---|---|---|---|---|---|"]
    for k, lim in s["limits"].items():
        d = s["distribution"].get(f"limit:{k}")
        if d is None:
            continue
        n_fail = sum(k in x["fails_limits"] for x in s["sensors"])
        worst = d["min"] if k.startswith("min") else d["max"]
        lines.append(f"| {k} | {_unit(k)} | {lim:g} | {d['median']:.4g} | {d['p05']:.4g} | {d['p95']:.4g} | "
                     f"{worst:.4g} | {n_fail} |")
    lines += ["", "## Flagged sensors", ""]
    flagged = [x for x in s["sensors"] if x["verdict"] == "fail"]
    if flagged:
        lines += ["| id | failed limits | outlier | largest robust z |", "|---|---|---|---|"]
        for x in flagged:
            top = ", ".join(f"{q['quantity']} {q['z']:+.1f}" for q in x["outlying_quantities"]) or "-"
            kind = f" (planted: {gt['defective'][x['id']]})" if gt and x["id"] in gt["defective"] else ""
            lines.append(f"| {x['id']}{kind} | {', '.join(x['fails_limits']) or '-'} | {'not tested' if x.get('max_abs_robust_z') is None else 'yes' if x['outlier'] else 'no'}"
                         f" | {top} |")
    else:
        lines.append("None.")
    notes = [(x["id"], n) for x in s["sensors"] for n in x.get("notes", [])]
    notes += [(x["id"], f"WARNING: {w}") for x in s["sensors"] for w in x.get("warnings", [])]
    if notes:
        lines += [""] + [f"- {sid}: {n}" for sid, n in notes]
    lines += ["", "## Parameter distribution over the fleet", "",
              "| quantity | unit | median | robust sd | p05 | p95 | min | max |", "|---|---|---|---|---|---|---|---|"]
    for k, d in s["distribution"].items():
        if k.startswith("limit:"):
            continue
        lines.append(f"| {k} | {_unit(k)} | {d['median']:.5g} | {d['robust_sd']:.3g} | {d['p05']:.5g} | {d['p95']:.5g} | "
                     f"{d['min']:.5g} | {d['max']:.5g} |")
    figs = [f for f in ("fleet_limits.png", "fleet_outliers.png") if (folder / f).exists()]
    if figs:
        lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figs]
    if "timings" in s:
        lines += ["", "Timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in s["timings"].items())]
    lines += ["", "Per-sensor calibrations: `sensors/<id>/` (apply one with `bayesmag apply --model sensors/<id> ...`); "
                  "every number above: `fleet.json`, `fleet_table.csv`."]
    p = folder / "fleet_report.md"
    p.write_text("\n".join(lines) + "\n")
    return p
