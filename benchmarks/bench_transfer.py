"""Benchmark: new-session coverage of the transfer (between-session) sd over several training draws.

Run:  python benchmarks/bench_transfer.py [--draws 6] [--sessions 200] [--runs 30]

The simulated session shift of ``tests/test_transfer.py`` (each run a session with its own offsets,
sd 0.3 uT, and cross-axis terms, sd 0.003), repeated: for training draws 0..draws-1 fit on ``runs``
simulated sessions (100 rows each), estimate the transfer sd by leave-one-run-out
(:func:`~bayesmag._src.predictor.estimate_transfer`, the job's path), and apply the calibration to
the same ``sessions`` new sessions (200 rows each, seeds 1000...). Prints, per draw, the transfer
sd, the in-domain coverage of the 95 % intervals and the share of rows covered or flagged out of
domain. The test asserts on draw 0 with 40 sessions; this shows how much one draw says.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_transfer import _calibrate, _session  # noqa: E402  (the test's simulated sessions)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=6, help="training draws 0..draws-1")
    ap.add_argument("--sessions", type=int, default=200, help="new sessions each calibration is applied to")
    ap.add_argument("--runs", type=int, default=30, help="training sessions (runs) per draw")
    args = ap.parse_args()
    news = [_session(1000 + s, 1, kind=s) for s in range(args.sessions)]
    print(f"## `python benchmarks/bench_transfer.py --draws {args.draws} --sessions {args.sessions} --runs {args.runs}`\n")
    print("| training draw | transfer sd x / y / z (uT) | in-domain coverage x / y / z (%) | rows covered or flagged "
          "x / y / z (%) | same, first 40 sessions (%) |")
    print("|---|---|---|---|---|")
    below = np.zeros(3, int)
    for draw in range(args.draws):
        pr = _calibrate(_session(draw, args.runs, rows=100))
        cov, dom = [], []
        for new in news:
            p = pr.predict(new)
            lo, hi = p.interval(0.95)
            cov.append((new.b_ref >= lo) & (new.b_ref <= hi))
            dom.append(p.in_domain)
        cov, dom = np.concatenate(cov), np.concatenate(dom)
        ok = (cov | ~dom[:, None]).mean(0)
        first = np.concatenate([np.full(new.n, s < 40) for s, new in enumerate(news)])
        ok40 = (cov[first] | ~dom[first, None]).mean(0)
        below += ok < 0.95
        f = lambda v: " / ".join(f"{100 * x:.1f}" for x in v)   # noqa: E731
        print(f"| {draw} | {' / '.join(f'{v:.3f}' for v in pr.transfer_sd)} | {f(cov[dom].mean(0))} | {f(ok)} | "
              f"{f(ok40)} |")
    print(f"\nDraws with fewer than 95 % of rows covered or flagged, per axis: {' / '.join(map(str, below))} of "
          f"{args.draws}.")


if __name__ == "__main__":
    main()
