"""Benchmark: NUTS on the real Belsten (2023) data, the 24-parameter thermo-affine model.

Measures wall-clock seconds (compile, sampling, post-processing, total) and the
diagnostics of :func:`bayesmag.run_nuts` for 4 chains x 1000 draws (1000 warm-up) on all
3378 rows, and prints the per-axis cross-check against the LM fit. Target: under 60 s on a
2-core CPU, R-hat <= 1.01, bulk ESS >= 400, sd ratios in 0.9-1.1, mean differences < 0.2 LM sd.

Run::

    BAYESMAG_DATA_DIR=../shared/data JAX_PLATFORMS=cpu python benchmarks/bench_nuts.py
    python benchmarks/bench_nuts.py --seeds 0 1 2 3 4          # spread of the diagnostics over seeds
    python benchmarks/bench_nuts.py --parametrisation scaled --dense-mass   # the alternative to whitening
    python benchmarks/bench_nuts.py --chain-method sequential --json out.json

The first repetition includes JIT compilation; with several seeds the later ones reuse the
compiled program (same shapes and settings), so their "compile" is ~0.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings

os.environ.setdefault("JAX_PLATFORMS", "cpu")


def main(argv=None) -> int:
    from bayesmag._src.pipeline.nuts import CHAIN_METHODS, PARAMETRISATIONS
    from bayesmag.likelihoods import LIKELIHOODS

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--chains", type=int, default=4)
    p.add_argument("--warmup", type=int, default=1000)
    p.add_argument("--draws", type=int, default=1000)
    p.add_argument("--target-accept", type=float, default=0.8)
    p.add_argument("--chain-method", default="vectorized", choices=list(CHAIN_METHODS))
    p.add_argument("--parametrisation", default="whitened", choices=list(PARAMETRISATIONS))
    p.add_argument("--dense-mass", action="store_true")
    p.add_argument("--likelihood", default="gaussian", choices=sorted(LIKELIHOODS))
    p.add_argument("--t0", default="0", help='reference temperature: a number or "mean"')
    p.add_argument("--train-split", action="store_true",
                   help="the paper's random 90/10 split (seed 0): train rows only")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--json", help="write all results to this file")
    args = p.parse_args(argv)

    import numpy as np

    import bayesmag as bm
    from bayesmag._src.pipeline.nuts import NutsWarning, run_nuts

    data = bm.load_dataset("belsten2023")
    if args.train_split:
        data = data.subset(bm.make_split(data, kind="random", test_fraction=0.1, seed=0).train)
    t0 = float(np.mean(data.temperature)) if args.t0 == "mean" else float(args.t0)
    fit = bm.fit_physics(data, bm.PhysicsModel.paper(t0=t0))
    print(f"# {data.n} rows, {fit.model.n_params} parameters x 3 axes, {args.chains} chains x {args.draws} draws "
          f"(warm-up {args.warmup}), {args.chain_method}, {args.parametrisation}"
          f"{' + dense mass' if args.dense_mass else ''}, {args.likelihood}; t0 = {t0:g}")
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    runs = []
    for seed in args.seeds:
        t = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", NutsWarning)
            res = run_nuts(data, fit, chains=args.chains, warmup=args.warmup, draws=args.draws,
                           target_accept=args.target_accept, chain_method=args.chain_method,
                           likelihood=args.likelihood, parametrisation=args.parametrisation,
                           dense_mass=args.dense_mass, seed=seed)
        wall = time.perf_counter() - t
        st = res.idata.sample_stats
        row = {"seed": seed, "wall_s": wall, "seconds": res.seconds,
               "leapfrog_steps_per_draw": float(st.n_steps.mean()),
               "warnings": [str(w.message) for w in caught], "axes": {}}
        s = res.seconds
        print(f"\nseed {seed}: {wall:.1f} s wall = {s['compile']:.1f} compile + {s['sampling']:.1f} sampling + "
              f"{s['postprocess']:.1f} post-processing; {row['leapfrog_steps_per_draw']:.1f} leapfrog steps/draw")
        print(f"  {'axis':4} {'max R-hat':>9} {'min ESS bulk':>12} {'min ESS tail':>12} {'div':>4} "
              f"{'max|mean diff|/sd_LM':>20} {'sd ratio range':>15}")
        for ax in res.axes:
            c = res.crosscheck[ax]
            row["axes"][ax] = {k: c[k] for k in ("max_rhat", "min_ess_bulk", "min_ess_tail", "divergences",
                                                 "max_abs_mean_diff_lm_sd", "sd_ratio_min", "sd_ratio_max",
                                                 "whitened_eigenvalue_range", "verdict")}
            print(f"  {ax:4} {c['max_rhat']:9.4f} {c['min_ess_bulk']:12.0f} {c['min_ess_tail']:12.0f} "
                  f"{c['divergences']:4d} {c['max_abs_mean_diff_lm_sd']:20.3f} "
                  f"{c['sd_ratio_min']:7.3f}-{c['sd_ratio_max']:.3f}")
        for ax, v in res.verdicts.items():
            print(f"  {ax}: {v}")
        for w in row["warnings"]:
            print(f"  WARNING: {w}")
        runs.append(row)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "n_rows": data.n, "cpus": os.cpu_count(), "runs": runs}, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
