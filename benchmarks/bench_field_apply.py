"""A field calibration applied to recordings it did not see: `bayesmag apply` on a new flight of the same sensor.

Simulated (``--generator simulate``): for each seed s, a field run (``[measurement] kind``: constant 50 uT or a
scalar column) on a campaign of sensor s, then ``apply`` to a second campaign of the same sensor
(``simulate_field(sensor_seed=s, seed=1000 + s)``: new motion and noise, the same temperature range). Scored
against the simulation's truth: |B| RMSE, coverage of the magnitude interval (all rows; in domain), rows flagged,
and the calibrated vector's error after the best rotation (the gauge; orthogonal Procrustes).

Real (``--generator belsten``): the scalar calibration of ``configs/scalar_belsten.toml`` fitted with one Belsten
run left out (``split.kind = "by_run"``), applied to that run's rows; the reference magnitude is |B_ref| of the vector
reference (the scalar the field fit saw on the other runs).

  python benchmarks/bench_field_apply.py --generator simulate --seeds 20
  python benchmarks/bench_field_apply.py --generator belsten
  python benchmarks/bench_field_apply.py --generator speed        # seconds per 100k rows
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def _write(path, data, f_ref=None):
    head = ["time", "run", "bx_meas", "by_meas", "bz_meas", "temperature", "bx_ref", "by_ref", "bz_ref"]
    head += [] if f_ref is None else ["F_ovh"]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        for i in range(data.n):
            row = [data.time[i], data.run[i], *data.b_meas[i], data.temperature[i], *data.b_ref[i]]
            w.writerow([repr(float(v)) for v in row + ([] if f_ref is None else [f_ref[i]])])


def _score(out_csv, truth_b):
    with open(out_csv) as fh:
        r = list(csv.reader(fh))
    head, a = r[0], np.array(r[1:], float)
    col = {h: a[:, j] for j, h in enumerate(head)}
    dom = col["in_domain"].astype(bool)
    mag = np.linalg.norm(truth_b, axis=1)
    inside = (mag >= col["magnitude_lower"]) & (mag <= col["magnitude_upper"])
    B = np.column_stack([col[f"{x}_calibrated"] for x in "xyz"])
    U, _, Vt = np.linalg.svd(B[dom].T @ truth_b[dom]) if dom.any() else np.linalg.svd(B.T @ truth_b)
    R = U @ Vt
    return {"n": int(a.shape[0]), "n_outside": int((~dom).sum()),
            "rmse_magnitude": float(np.sqrt(np.mean((col["magnitude"] - mag) ** 2))),
            "coverage": float(inside.mean()),
            "coverage_in_domain": float(inside[dom].mean()) if dom.any() else None,
            "covered_or_flagged": float(np.mean(inside | ~dom)),
            "mean_width": float(np.mean(col["magnitude_upper"] - col["magnitude_lower"])),
            "vector_rmse_after_rotation": float(np.sqrt(np.mean((B[dom] @ R - truth_b[dom]) ** 2))) if dom.any() else None}


def simulate(seeds, kind, measurement, n):
    import bayesmag
    from bayesmag._src.app.apply import apply_calibration
    from bayesmag._src.app.config import config_from_dict
    from bayesmag.simulate import simulate_field

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for s in seeds:
            t = time.perf_counter()
            kw = dict(n=n, temperature=(15.0, 35.0), field=50.0)
            a = simulate_field(kind, seed=s, sensor_seed=s, **kw)
            b = simulate_field(kind, seed=1000 + s, sensor_seed=s, **kw)
            _write(tmp / "a.csv", a.data, a.f_ref)
            _write(tmp / "b.csv", b.data, b.f_ref)
            meas = ({"kind": "constant", "field": 50.0} if measurement == "constant"
                    else {"kind": "scalar", "scalar_column": "F_ovh"})
            cfg = config_from_dict({"name": "field_apply", "data": {"path": str(tmp / "a.csv")},
                                    "measurement": {**meas, "exports": ["json"], "compare_vector": False},
                                    "split": {"kind": "time_blocks", "test_fraction": 0.2, "n_blocks": 2, "seed": s},
                                    "physics": {"t0": "mean"}, "output": {"figures": False, "progress": False}})
            run = tmp / f"run{s}"
            bayesmag.run_job(cfg, run)
            apply_calibration(run, tmp / "b.csv", tmp / f"out{s}.csv")
            sc = _score(tmp / f"out{s}.csv", b.data.b_ref)
            sc.update(seed=s, seconds=time.perf_counter() - t)
            rows.append(sc)
            print(json.dumps(sc), flush=True)
    return rows


def belsten():
    import bayesmag
    from bayesmag._src.app.apply import apply_calibration
    from bayesmag._src.app.config import load_config
    from bayesmag._src.core.data import write_csv

    cfg_path = Path(__file__).resolve().parents[1] / "configs" / "scalar_belsten.toml"
    data = bayesmag.load_dataset("belsten2023")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        strong = np.linalg.norm(data.b_ref, axis=1) >= 5.0       # the config's min_magnitude: runs 1-2 drop out
        for k in np.unique(data.run[strong]):
            t = time.perf_counter()
            cfg = load_config(cfg_path, ['split.kind="by_run"', f"split.test_runs=[{int(k)}]", "output.figures=false",
                                         "output.progress=false", "measurement.compare_vector=false"])
            run = tmp / f"run{k}"
            bayesmag.run_job(cfg, run)
            part = data.subset(np.flatnonzero(data.run == k))
            part = part.subset(np.flatnonzero(np.linalg.norm(part.b_ref, axis=1) >= cfg.measurement.min_magnitude))
            write_csv(part, tmp / f"run{k}.csv")
            apply_calibration(run, tmp / f"run{k}.csv", tmp / f"out{k}.csv")
            sc = _score(tmp / f"out{k}.csv", part.b_ref)
            sc.update(run=int(k), seconds=time.perf_counter() - t)
            rows.append(sc)
            print(json.dumps(sc), flush=True)
    return rows


def speed(n: int, repeats: int = 3):
    """Seconds of ``apply_calibration`` (load, predict, write) on an n-row new flight; the median of ``repeats``
    after one warm-up, on the built-in ``field_simulated`` calibration."""
    import bayesmag
    from bayesmag._src.app.apply import apply_calibration
    from bayesmag._src.app.config import load_config
    from bayesmag._src.core.data import write_csv
    from bayesmag.simulate import simulate_field

    cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "field_simulated.toml",
                      ["output.figures=false", "output.progress=false"])
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        bayesmag.run_job(cfg, tmp / "run")
        c = simulate_field("two_temperature", n=n, seed=5, sensor_seed=0, field=50.0, inclination=60.0,
                           noise_sd=0.05, temperatures=(15.0, 40.0))
        write_csv(c.data, tmp / "big.csv")
        apply_calibration(tmp / "run", tmp / "big.csv", tmp / "out.csv")
        times, s = [], None
        for _ in range(repeats):
            t = time.perf_counter()
            s = apply_calibration(tmp / "run", tmp / "big.csv", tmp / "out.csv")
            times.append(time.perf_counter() - t)
    print(f"apply of a field calibration, {n} rows: median {np.median(times):.3f} s over {repeats} "
          f"({n / np.median(times):,.0f} rows/s); |B| RMSE {s['magnitude_metrics']['rmse']:.4f} uT, coverage "
          f"{s['magnitude_metrics']['coverage']:.3f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--generator", choices=["simulate", "belsten", "speed"], default="simulate")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--kind", default="dance")
    ap.add_argument("--measurement", choices=["constant", "scalar"], default="constant")
    ap.add_argument("--n", type=int, default=2000)
    ap.add_argument("--out", default=None, help="write the rows as JSON here")
    a = ap.parse_args()
    if a.generator == "speed":
        return speed(a.n if a.n != 2000 else 100_000)
    if a.generator == "belsten":
        rows = belsten()
    else:
        rows = simulate(range(a.first_seed, a.first_seed + a.seeds), a.kind, a.measurement, a.n)
    keys = ["rmse_magnitude", "coverage", "coverage_in_domain", "covered_or_flagged", "mean_width",
            "vector_rmse_after_rotation"]
    print("\nmedian over", len(rows), "|", "  ".join(
        f"{k} {np.median([r[k] for r in rows if r[k] is not None]):.4g}" for k in keys))
    cif = [r["covered_or_flagged"] for r in rows]
    print(f"covered or flagged: min {min(cif):.3f}, 10th pct {np.percentile(cif, 10):.3f}, "
          f"under 0.95: {sum(c < 0.95 for c in cif)} of {len(cif)}")
    if a.out:
        Path(a.out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
