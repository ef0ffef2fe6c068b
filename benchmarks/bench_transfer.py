"""Benchmark: new-session coverage of the transfer (between-session) sd over several training draws.

Run:  python benchmarks/bench_transfer.py [--draws 6] [--sessions 200] [--runs 30] [--generator gauss ...]

The simulated session shift of ``tests/test_transfer.py`` (each run a session with its own offsets,
sd 0.3 uT, and cross-axis terms, sd 0.003), repeated: for training draws 0..draws-1 fit on ``runs``
simulated sessions (100 rows each), estimate the transfer sd by leave-one-run-out
(:func:`~bayesmag._src.core.predictor.estimate_transfer`, the job's path), and apply the calibration to
``sessions`` new sessions (200 rows each) drawn afresh for every training draw (seeds
10000 + 1000 * draw + s; ``--shared`` applies every draw to the same sessions, seeds 1000...,
as the test does). Prints, per draw, the transfer sd, the in-domain coverage of the 95 %
intervals and the share of rows covered or flagged out of domain, then the mean over draws with
its standard error and the sd over draws. The test asserts on draw 0 with 40 sessions; this
shows how much one draw says.

A shared set of new sessions is itself one random sample: its composition (e.g. a few heated
sessions with a large held field on one axis) moves every draw's coverage on that axis the same
way, so means over draws with a shared set carry that set's bias (``--draws 30 --sessions 40``:
in-domain y 94.3 % with the shared sessions 1000-1039, 96.4 % with fresh ones, the same 30
training draws).

``--generator`` picks how sessions differ (several: one table each), so that the estimator is
judged on shifts it was not designed on: ``gauss`` (the test's: offsets N(0, 0.3) uT, cross-axis
N(0, 0.003)), ``t3`` (offsets Student-t, 3 dof, same sd), ``offsets_small`` (offsets N(0, 0.05),
no cross-axis change: the shift near the noise), ``cross_only`` (no offset change, cross-axis
N(0, 0.006): an error that grows with the field) and ``uniform`` (offsets U(-0.5, 0.5), cross-axis
N(0, 0.002): light tails).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_transfer import _calibrate, _new_sessions, _session, _shifted_params  # noqa: E402  (the test's simulated sessions)

GENERATORS = {
    "gauss": lambda rng: _shifted_params(rng),
    "t3": lambda rng: _shifted_params(rng, lambda g: 0.3 / np.sqrt(3.0) * g.standard_t(3, 3)),
    "offsets_small": lambda rng: _shifted_params(rng, lambda g: g.normal(0, 0.05, 3), 0.0),
    "cross_only": lambda rng: _shifted_params(rng, lambda g: np.zeros(3), 0.006),
    "uniform": lambda rng: _shifted_params(rng, lambda g: g.uniform(-0.5, 0.5, 3), 0.002),
}


def run_generator(name: str, args) -> dict:
    """Per-draw table of one generator; returns its summary."""
    gen = GENERATORS[name]
    shared = [_session(1000 + s, 1, kind=s, session_params=gen) for s in range(args.sessions)] if args.shared else None
    print(f"### generator `{name}`\n")
    print("| training draw | transfer sd x / y / z (uT) | in-domain coverage x / y / z (%) | rows covered or flagged "
          "x / y / z (%) | same, first 40 sessions (%) | mean 95 % width x / y / z (uT) |")
    print("|---|---|---|---|---|---|")
    f = lambda v: " / ".join(f"{100 * x:.1f}" for x in v)   # noqa: E731
    oks, covs, widths = [], [], []
    for draw in range(args.draws):
        pr = _calibrate(_session(draw, args.runs, rows=100, session_params=gen))
        cov, dom, width = [], [], []
        news_d = shared if args.shared else _new_sessions(draw, args.sessions, gen)
        for new in news_d:
            p = pr.predict(new)
            lo, hi = p.interval(0.95)
            cov.append((new.b_ref >= lo) & (new.b_ref <= hi))
            dom.append(p.in_domain)
            width.append(hi - lo)
        cov, dom, width = np.concatenate(cov), np.concatenate(dom), np.concatenate(width)
        ok = (cov | ~dom[:, None]).mean(0)
        first = np.concatenate([np.full(new.n, s < 40) for s, new in enumerate(news_d)])
        ok40 = (cov[first] | ~dom[first, None]).mean(0)
        oks.append(ok), covs.append(cov[dom].mean(0)), widths.append(width[dom].mean(0))
        print(f"| {draw} | {' / '.join(f'{v:.3f}' for v in pr.transfer_sd)} | {f(covs[-1])} | {f(ok)} | "
              f"{f(ok40)} | {' / '.join(f'{v:.3f}' for v in widths[-1])} |", flush=True)
    oks, covs, widths = np.array(oks), np.array(covs), np.array(widths)
    below = (oks < 0.95).sum(0)
    print(f"\nDraws with fewer than 95 % of rows covered or flagged, per axis: {' / '.join(map(str, below))} of "
          f"{args.draws}.\n")
    se = lambda v: " / ".join(f"{100 * x:.1f}" for x in v.std(0, ddof=1) / np.sqrt(len(v)))   # noqa: E731
    sd = lambda v: " / ".join(f"{100 * x:.1f}" for x in v.std(0, ddof=1))                     # noqa: E731
    return {"in-domain coverage, mean (%)": f(covs.mean(0)), "its se (%)": se(covs),
            "sd over draws (%)": sd(covs), "covered or flagged, mean (%)": f(oks.mean(0)),
            "covered or flagged, lowest draw (%)": f(oks.min(0)),
            "draws under 95 %": " / ".join(map(str, below)),
            "mean width (uT)": " / ".join(f"{v:.3f}" for v in widths.mean(0))}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=6, help="training draws 0..draws-1")
    ap.add_argument("--sessions", type=int, default=200, help="new sessions each calibration is applied to")
    ap.add_argument("--runs", type=int, default=30, help="training sessions (runs) per draw")
    ap.add_argument("--shared", action="store_true", help="every draw applied to the same new sessions")
    ap.add_argument("--generator", nargs="+", default=["gauss"], choices=sorted(GENERATORS),
                    help="how the sessions differ (one table each)")
    args = ap.parse_args()
    print(f"## `python benchmarks/bench_transfer.py --draws {args.draws} --sessions {args.sessions} --runs {args.runs} "
          f"--generator {' '.join(args.generator)}{' --shared' if args.shared else ''}`\n")
    summary = {name: run_generator(name, args) for name in args.generator}
    keys = list(next(iter(summary.values())))
    print(f"### summary over {args.draws} training draws x {args.sessions} new sessions (x / y / z)\n")
    print("| generator | " + " | ".join(keys) + " |")
    print("|---|" + "---|" * len(keys))
    for name, row in summary.items():
        print(f"| {name} | " + " | ".join(row[k] for k in keys) + " |")


if __name__ == "__main__":
    main()
