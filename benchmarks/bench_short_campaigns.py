"""Short clean campaigns: the hierarchical transfer sd against leave-one-run-out's, with and without the runs'
weak directions (issue 24; docs/sessions.md, Limits).

Run:  python benchmarks/bench_short_campaigns.py [--seeds 0 1 2 3 4 5 6 7] [--runs 8] [--rows 100] [--noise 0.05]

Per seed, ``tests/test_transfer.py::_session(seed, runs, rows, noise_sd=NOISE)`` (no distortion: every
session's offsets N(0, 0.3) uT and cross-axis terms N(0, 0.003) around the paper's parameters), one physics fit,
then per axis the root-mean-square transfer sd over the training rows of ``hierarchical_transfer`` with
``weak=None`` (the model before the weak directions) and the default, over leave-one-run-out's sd, the number of
weak directions and whether the job warns that the model is far wider than loro (``MISFIT_RATIO``; the
few-runs warning below 6 runs is not counted). No new sessions: the generator benchmark
(``bench_hierarchical.py generators --runs 8``) scores coverage.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_transfer import _session  # noqa: E402

import bayesmag  # noqa: E402
from bayesmag._src.core.predictor import estimate_transfer  # noqa: E402
from bayesmag._src.pipeline.sessions import hierarchical as H  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(8)))
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--rows", type=int, default=100)
    ap.add_argument("--noise", type=float, default=0.05, help="the DUT's reading noise sd, uT")
    args = ap.parse_args()
    f = lambda v: " / ".join(f"{x:.2f}" for x in v)   # noqa: E731
    print(f"## `python benchmarks/bench_short_campaigns.py {' '.join(sys.argv[1:])}`\n")
    print("| seed | loro sd x / y / z (uT) | weak off: sd / loro's | default: sd / loro's | weak directions | misfit warning (off, default) |")
    print("|---|---|---|---|---|---|")
    worst = {"off": [], "default": []}
    for seed in args.seeds:
        d = _session(seed, args.runs, rows=args.rows, noise_sd=args.noise)
        fit = bayesmag.fit_physics(d, bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature))))
        loro = estimate_transfer(d, fit).sd
        off = H.fit_sessions(d, fit, weak=None)
        sd_off = np.sqrt(np.mean(off.transfer_sd_for(fit, d) ** 2, axis=0))
        warn_off = bool(H.misfit_axes(sd_off, loro, fit.s2).any())
        tr, _ = H.hierarchical_transfer(d, fit)
        misfit = "The hierarchical transfer sd is" in (tr.warning or "")      # not the few-runs warning
        eff = H.select_effects(d, fit)[0]
        n_weak = sum(W.shape[1] for W in H.weak_directions(d, fit, eff, 0).values())
        worst["off"].append((sd_off / loro).max())
        worst["default"].append((tr.sd / loro).max())
        print(f"| {seed} | {f(loro)} | {f(sd_off / loro)} | {f(tr.sd / loro)} | {n_weak} | "
              f"{'yes' if warn_off else 'no'}, {'yes' if misfit else 'no'} |", flush=True)
    for k, v in worst.items():
        v = np.array(v)
        print(f"\n{k}: largest axis ratio per seed {f(v)}; seeds over 2x: {int((v > 2).sum())} of {v.size}")


if __name__ == "__main__":
    main()
