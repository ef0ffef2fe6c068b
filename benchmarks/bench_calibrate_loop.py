"""``bayesmag.calibrate`` called in a loop over recordings, as a script or a simulation study does.

Each recording is a simulated campaign with its own seed, so its training-mean temperature (the
default T0, ``"mean"``) differs from the others'. Prints the seconds of every call and the median of
calls 2..K (call 1 compiles). ``--code DIR`` times another checkout's ``bayesmag`` the same way, in
its own process (e.g. ``git worktree add /tmp/base <commit>``), alternating with this one.

    python benchmarks/bench_calibrate_loop.py --calls 8
    python benchmarks/bench_calibrate_loop.py --calls 8 --code /tmp/base
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_CHILD = r"""
import json, sys, time
import bayesmag
calls, rows, method = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
settings = bayesmag.CalibrationSettings(uq=bayesmag.UQSettings(method=method))
out = []
for seed in range(calls):
    d = bayesmag.simulate.simulate(rows, design="campaign", seed=seed)
    t = time.perf_counter()
    bayesmag.calibrate(d, settings)
    out.append([float(d.temperature.mean()), time.perf_counter() - t])
print(json.dumps(out))
"""


def run(code: Path, calls: int, rows: int, method: str) -> list:
    env = {**os.environ, "PYTHONPATH": str(code), "BAYESMAG_COMPILE_CACHE": "0"}
    res = subprocess.run([sys.executable, "-c", _CHILD, str(calls), str(rows), method], env=env, cwd=code,
                         capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--calls", type=int, default=8)
    ap.add_argument("--rows", type=int, default=2000)
    ap.add_argument("--method", default="analytic", help="[uq] method of the settings")
    ap.add_argument("--repeats", type=int, default=1, help="processes per checkout (alternating)")
    ap.add_argument("--code", nargs="*", default=[], metavar="DIR")
    args = ap.parse_args()
    codes = [ROOT] + [Path(c).resolve() for c in args.code]
    for rep in range(args.repeats):
        for code in codes:
            rec = run(code, args.calls, args.rows, args.method)
            secs = [s for _, s in rec]
            print(f"{code} (repeat {rep}): T0 " + " ".join(f"{t:.2f}" for t, _ in rec) + " C; seconds "
                  + " ".join(f"{s:.2f}" for s in secs) + f"; median of calls 2..{args.calls}: "
                  f"{statistics.median(secs[1:]):.3f} s", flush=True)


if __name__ == "__main__":
    main()
