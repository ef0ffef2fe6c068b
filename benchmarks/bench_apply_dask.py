"""Benchmark: `bayesmag apply` on a partitioned Parquet archive through Dask (issue #27).

Run:  python benchmarks/bench_apply_dask.py [--rows 10000000] [--workers 1 2] [--file-rows 1000000]
                                            [--row-group 250000] [--keep]

Writes an archive of --rows rows (files of --file-rows rows, row groups of --row-group rows; smooth field rotations
and temperature drift inside the calibration's domain), fits a physics calibration on a simulated campaign, then
times `bayesmag apply --data ARCHIVE --out OUT --workers W` (a local cluster of W single-threaded worker processes)
for every W as a separate process. Peak memory: the largest sum of resident set sizes of that process and all its
children (scheduler in the client process, nannies, workers), sampled every 0.2 s (shared pages are counted in every
process, so this overstates the true total); CPU: user + system seconds of the command and its reaped children
(the rate per CPU-second does not depend on what else the machine runs). Prints a markdown table (docs/benchmarks.md).
"""

import argparse
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def write_archive(root: Path, rows: int, file_rows: int, row_group: int) -> None:
    import pandas as pd
    root.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for k, lo in enumerate(range(0, rows, file_rows)):
        n = min(file_rows, rows - lo)
        t = (lo + np.arange(n)) / 4.0
        ph = rng.uniform(0, 2 * np.pi, 3)
        b = 35 * np.sin(2 * np.pi * t[:, None] / np.array([60.0, 83.0, 97.0]) + ph) + rng.normal(0, 0.05, (n, 3))
        df = pd.DataFrame({"time": t, "run": np.full(n, k + 1), "bx_meas": b[:, 0], "by_meas": b[:, 1],
                           "bz_meas": b[:, 2], "temperature": 30 + 5 * np.sin(2 * np.pi * t / 3600.0)})
        df.to_parquet(root / f"part{k:04d}.parquet", row_group_size=row_group, index=False)


def write_calibration(path: Path) -> None:
    from bayesmag._src.app.artifact import save_calibration
    from bayesmag._src.core.domain import Domain
    from bayesmag._src.core.fit import fit_physics
    from bayesmag._src.core.physics import PhysicsModel
    from bayesmag._src.core.physics_uq import estimate_input_noise
    from bayesmag._src.core.predictor import Predictor, UQOptions
    from bayesmag._src.core.simulate import simulate
    d = simulate(5000, design="campaign", seed=0, noise_sd=0.05)
    fit = fit_physics(d, PhysicsModel.paper(t0=25.0))
    path.mkdir(parents=True)
    save_calibration(path, Predictor(fit=fit, sigma_in=estimate_input_noise(d), residual_sd=np.full(3, 0.01),
                                     domain=Domain.from_data(d), uq=UQOptions(method="analytic")), config={})


def tree_rss(pid: int) -> int:
    import psutil
    try:
        p = psutil.Process(pid)
        procs = [p] + p.children(recursive=True)
    except psutil.Error:
        return 0
    total = 0
    for q in procs:
        try:
            total += q.memory_info().rss
        except psutil.Error:
            pass
    return total


def timed(cmd: list[str]) -> tuple[float, float, float, str]:
    """Wall seconds, peak summed RSS (GB), CPU seconds of the command and every process it started (reaped
    children's user + system time, from /usr/bin/time), and its stdout."""
    t = time.perf_counter()
    proc = subprocess.Popen(["/usr/bin/time", "-f", "CPU %U %S"] + cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    peak = [0]

    def sample():
        while proc.poll() is None:
            peak[0] = max(peak[0], tree_rss(proc.pid))
            time.sleep(0.2)
    th = threading.Thread(target=sample, daemon=True)
    th.start()
    out, err = proc.communicate()
    wall = time.perf_counter() - t
    th.join()
    if proc.returncode:
        raise SystemExit(f"{cmd} failed ({proc.returncode}): {err[-2000:]}")
    cpu = [ln for ln in err.splitlines() if ln.startswith("CPU ")][-1].split()
    return wall, peak[0] / 2**30, float(cpu[1]) + float(cpu[2]), out.strip()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", type=int, default=10_000_000)
    ap.add_argument("--workers", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--file-rows", type=int, default=1_000_000)
    ap.add_argument("--row-group", type=int, default=250_000)
    ap.add_argument("--memory-limit", default="900MB")
    ap.add_argument("--keep", action="store_true", help="keep the archive and outputs")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_apply_dask_"))
    t = time.perf_counter()
    write_archive(tmp / "archive", args.rows, args.file_rows, args.row_group)
    write_calibration(tmp / "cal")
    print(f"archive: {args.rows:,} rows in {tmp / 'archive'} ({time.perf_counter() - t:.0f} s to write)", file=sys.stderr)
    print("| rows | workers x threads | wall (s) | rows/s (wall) | CPU (s) | rows per CPU-second | "
          "peak RSS, all processes (GB) |")
    print("|---|---|---|---|---|---|---|")
    try:
        for w in args.workers:
            out = tmp / f"out{w}"
            cmd = [sys.executable, "-m", "bayesmag._src.app.cli", "apply", "--model", str(tmp / "cal"), "--data",
                   str(tmp / "archive"), "--out", str(out), "--workers", str(w), "--threads-per-worker", "1",
                   "--memory-limit", args.memory_limit, "--no-progress"]
            wall, peak, cpu, msg = timed(cmd)
            print(f"| {args.rows:,} | {w} x 1 | {wall:.1f} | {args.rows / wall:,.0f} | {cpu:.1f} | {args.rows / cpu:,.0f} | "
                  f"{peak:.2f} |", flush=True)
            print(f"  {msg}", file=sys.stderr)
            if not args.keep:
                shutil.rmtree(out, ignore_errors=True)
    finally:
        if not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
