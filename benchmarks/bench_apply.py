"""Benchmark: apply a saved calibration to a large recording (issue #7 targets).

Run:  python benchmarks/bench_apply.py [--rows 1000000]
Trains the quickstart physics calibration (simulated sensor, network off), writes a recording of --rows
rows without reference columns, and times `bayesmag apply` end to end (read CSV, calibrate
in chunks, write CSV) with the analytic physics uncertainty and with PS-QMC at Np=100,
Nq=256, reporting seconds and peak resident memory of each run (separate processes).
"""

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", type=int, default=1_000_000)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_apply_"))
    run = tmp / "run"
    subprocess.run([sys.executable, "-m", "bayesmag._src.app.cli", "run", str(ROOT / "configs/quickstart.toml"), "--out",
                    str(run), "--set", "output.figures=false", "--set", "network.enabled=false", "--no-progress"],
                   check=True, capture_output=True)
    import bayesmag as bm
    from bayesmag import CalibrationData
    d = bm.simulate.simulate(args.rows, design="iid", seed=11, noise_sd=0.05, field_range=40.0,
                             temp_range=(5.0, 40.0))
    rec = tmp / "rec.csv"
    bm.write_csv(CalibrationData(d.b_meas, d.temperature, None, d.time, d.run), rec)
    results = {}
    for label, extra in (("analytic", ["--uq", "analytic"]),
                         ("psqmc Np=100 Nq=256", ["--uq", "psqmc", "--n-params", "100", "--n-qmc", "256"])):
        t = time.perf_counter()
        r = subprocess.run(["/usr/bin/time", "-f", "%M", sys.executable, "-m", "bayesmag._src.app.cli", "apply",
                            "--model", str(run), "--data", str(rec), "--out", str(tmp / "out.csv"), "--no-progress",
                            *extra], capture_output=True, text=True)
        wall = time.perf_counter() - t
        if r.returncode != 0:
            raise SystemExit(r.stderr)
        peak_kb = int(r.stderr.strip().splitlines()[-1])
        results[label] = {"seconds": round(wall, 2), "peak_rss_gb": round(peak_kb / 1024**2, 2)}
    print(f"| rows | physics UQ | seconds (whole command) | peak memory GB |")
    print("|---|---|---|---|")
    for label, r in results.items():
        print(f"| {args.rows:,} | {label} | {r['seconds']} | {r['peak_rss_gb']} |")
    print(json.dumps(results))


if __name__ == "__main__":
    main()
