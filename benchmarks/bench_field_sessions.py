"""A field calibration's between-session term on new sessions of a vehicle whose hard and soft iron change.

For each generator and training draw d: ``simulate_field_sessions`` gives R training sessions and 20 new sessions of
one sensor on one vehicle (sensor seed d); ``run_field_stage`` fits the R sessions (the job's settings: conformal
scale from time-block folds, the magnitude transfer by leave-one-run-out) and predicts the new sessions' |B| with
the term and without it (``[uq] transfer = "off"``: the same fit, the term taken out). Scored against the true |B|:
pooled 95 % coverage of the new sessions, the share of new sessions covered under 95 %, the mean width ratio
(with / without), and |B| RMSE. One line per draw (``DRAW {json}``), then a table per generator:

  python benchmarks/bench_field_sessions.py --draws 30                  # every generator
  python benchmarks/bench_field_sessions.py --draws 5 --generator heavy
  python benchmarks/bench_field_sessions.py --summarise LOG             # the table from a log's DRAW lines

Generators (hard iron sd per axis, soft iron sd per element; dance at 15 -> 35 C, 300 rows a session, 0.05 uT
reading noise, constant 50 uT field unless said): ``hard_iron`` (0.3 uT, 6 sessions), ``hard_iron_12`` (12
sessions), ``heavy`` (Student-t changes, 3 dof), ``soft_iron`` (0.1 uT and 0.01), ``temperatures`` (0.3 uT, every
session's temperatures shifted by up to +-8 C), ``scalar`` (a scalar reference with 0.01 uT noise instead of the
constant field), ``none`` (nothing changes: the term's cost) and ``large`` (1 uT, 6 sessions). ``heavy``,
``soft_iron``, ``temperatures`` and ``large`` were written after the method and its tests, and not tuned on.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

import numpy as np

GENERATORS = {
    "hard_iron": dict(sessions=6, hard_iron_sd=0.3),
    "hard_iron_12": dict(sessions=12, hard_iron_sd=0.3),
    "heavy": dict(sessions=6, hard_iron_sd=0.3, shift_df=3.0),
    "soft_iron": dict(sessions=6, hard_iron_sd=0.1, soft_iron_sd=0.01),
    "temperatures": dict(sessions=6, hard_iron_sd=0.3, temperature_spread=8.0),
    "scalar": dict(sessions=6, hard_iron_sd=0.3, measurement="scalar"),
    "none": dict(sessions=6, hard_iron_sd=0.0),
    "large": dict(sessions=6, hard_iron_sd=1.0),
    "small": dict(sessions=6, hard_iron_sd=0.05),
    "small_12": dict(sessions=12, hard_iron_sd=0.05),
}
NEW_SESSIONS = 20


def _cat(campaigns):
    from bayesmag._src.core.data import CalibrationData
    d = [c.data for c in campaigns]
    data = CalibrationData(np.concatenate([x.b_meas for x in d]), np.concatenate([x.temperature for x in d]),
                           np.concatenate([x.b_ref for x in d]),
                           np.concatenate([x.time + 1e5 * i for i, x in enumerate(d)]), np.concatenate([x.run for x in d]))
    return data, np.concatenate([c.f_ref for c in campaigns])


def one_draw(name: str, draw: int, n: int = 300) -> dict:
    from bayesmag._src.core.measurement import Constant, Scalar
    from bayesmag._src.pipeline.field_stage import run_field_stage
    from bayesmag.simulate import simulate_field_sessions

    g = dict(GENERATORS[name])
    meas = Scalar() if g.pop("measurement", "constant") == "scalar" else Constant(50.0)
    r = g.pop("sessions")
    seed = 100 + draw
    ss = simulate_field_sessions("dance", sessions=r + NEW_SESSIONS, n=n, seed=seed, sensor_seed=seed,
                                 temperature=(15.0, 35.0), **g)
    (train, f_tr), (new, f_new) = _cat(ss[:r]), _cat(ss[r:])
    t = time.perf_counter()
    fs = run_field_stage(train, new, meas, f_ref_train=f_tr, f_ref_test=f_new, conformal=(0.1, 5), transfer="loro",
                         compare_vector=False)
    seconds = time.perf_counter() - t
    p = fs.prediction
    truth = np.linalg.norm(new.b_ref, axis=1)
    err = truth - p["mean"]
    with_t = p["total"]
    without = np.sqrt(np.maximum(with_t**2 - p["transfer"] ** 2, 0.0))
    rec = {"generator": name, "draw": draw, "sessions": r, "tau": fs.transfer["sd"], "method": fs.transfer["method"],
           "rmse": float(np.sqrt(np.mean(err**2))), "seconds": round(seconds, 2)}
    for key, sd in (("loro", with_t), ("off", without)):
        cov = np.abs(err) <= 1.96 * sd
        per = np.array([cov[new.run == k].mean() for k in np.unique(new.run)])
        rec[key] = {"coverage": float(cov.mean()), "sessions_under_95": int(np.sum(per < 0.95)),
                    "worst_session": float(per.min()), "mean_width": float(np.mean(2 * 1.96 * sd))}
    rec["width_ratio"] = rec["loro"]["mean_width"] / rec["off"]["mean_width"]
    return rec


def table(records: list[dict]) -> str:
    out = ["| generator | draws | sessions | method | coverage of new sessions, mean (10th pct): with / without | "
           "new sessions under 95 %: with / without | worst session: with / without | width with / without (median; "
           "max) | |B| RMSE (uT) | tau (uT, median) |", "|---|---|---|---|---|---|---|---|---|---|"]
    by = {}
    for r in records:
        by.setdefault(r["generator"], []).append(r)
    for name in [g for g in GENERATORS if g in by] + sorted(set(by) - set(GENERATORS)):
        rs = by[name]
        c = {k: np.array([r[k]["coverage"] for r in rs]) for k in ("loro", "off")}
        under = {k: sum(r[k]["sessions_under_95"] for r in rs) for k in c}
        worst = {k: min(r[k]["worst_session"] for r in rs) for k in c}
        w = np.array([r["width_ratio"] for r in rs])
        methods = sorted({r["method"] for r in rs})
        out.append(f"| {name} | {len(rs)} | {rs[0]['sessions']} | {', '.join(methods)} | "
                   f"{100 * c['loro'].mean():.1f} % ({100 * np.percentile(c['loro'], 10):.1f}) / "
                   f"{100 * c['off'].mean():.1f} % ({100 * np.percentile(c['off'], 10):.1f}) | "
                   f"{under['loro']} / {under['off']} of {NEW_SESSIONS * len(rs)} | "
                   f"{100 * worst['loro']:.0f} / {100 * worst['off']:.0f} % | {np.median(w):.2f}; {w.max():.2f} | "
                   f"{np.median([r['rmse'] for r in rs]):.3f} | {np.median([r['tau'] for r in rs]):.3f} |")
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--first-draw", type=int, default=0)
    ap.add_argument("--generator", nargs="*", default=list(GENERATORS), choices=list(GENERATORS))
    ap.add_argument("--summarise", nargs="*", default=None, help="logs whose DRAW lines to tabulate")
    a = ap.parse_args()
    if a.summarise is not None:
        recs = [json.loads(m.group(1)) for f in a.summarise for m in re.finditer(r"^DRAW (.*)$", Path(f).read_text(),
                                                                               re.M)]
        print(table(recs))
        return
    import warnings
    warnings.simplefilter("ignore")          # the CalibrationWarnings of hundreds of fits
    recs = []
    t0 = time.perf_counter()
    for name in a.generator:
        for d in range(a.first_draw, a.first_draw + a.draws):
            rec = one_draw(name, d)
            recs.append(rec)
            print("DRAW " + json.dumps(rec), flush=True)
    print(f"\n{len(recs)} draws in {time.perf_counter() - t0:.0f} s\n", file=sys.stderr)
    print(table(recs))


if __name__ == "__main__":
    main()
