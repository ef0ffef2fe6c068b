"""Benchmark: physics fit and physics UQ on the paper's protocol (real data, random 90/10 split, seed 0).

Run:  BAYESMAG_DATA_DIR=../shared/data python benchmarks/bench_physics.py [--repeats 7]
Prints a markdown table of median seconds (after one warm-up/compile call) and ratios to the
paper's Table 11 (physics fit 0.165 s; whole inference for 338 rows x 3 axes 39.47 s).
"""

import argparse
import json
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import bayesmag as bm
from bayesmag._src.core.physics_uq import _General, _gen_jit, sobol_normal

PAPER_FIT_S = 0.165
PAPER_INFER_S = 39.47


def timed(fn, repeats):
    fn()                                   # compile / warm up
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts), min(ts), max(ts)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--json", help="also write the numbers here")
    args = ap.parse_args()
    d = bm.load_dataset("belsten2023")
    sp = bm.make_split(d, kind="random", test_fraction=0.1, seed=0)
    train, test = d.subset(sp.train), d.subset(sp.test)
    inp = bm.inputs_from_data(test)
    fit = bm.fit_physics(train)
    S = bm.estimate_input_noise(train)
    rows = {}
    rows["physics fit (LM, 3 axes, 3040 rows, with covariance)"] = timed(lambda: bm.fit_physics(train), args.repeats)
    rows["physics UQ psqmc Np=500 Nq=1000 (338 rows x 3 axes)"] = timed(
        lambda: bm.physics_uncertainty(fit, inp, sigma_in=S, method="psqmc", n_params=500, n_qmc=1000, seed=0), args.repeats)
    rows["physics UQ psqmc Np=100 Nq=500 (paper 'reduced')"] = timed(
        lambda: bm.physics_uncertainty(fit, inp, sigma_in=S, method="psqmc", n_params=100, n_qmc=500, seed=0), args.repeats)
    rows["physics UQ analytic (exact moments)"] = timed(
        lambda: bm.physics_uncertainty(fit, inp, sigma_in=S, method="analytic"), args.repeats)

    eps = jnp.asarray(sobol_normal(1000, S, seed=0))

    def brute():
        key = jax.random.PRNGKey(0)
        for a in range(3):
            key, sub = jax.random.split(key)
            dr = jax.random.multivariate_normal(sub, jnp.asarray(fit.theta[a]), jnp.asarray(fit.cov[a]),
                                                shape=(500,), method="svd")
            jax.block_until_ready(_gen_jit(_General(fit.model), inp, 0, inp.b.shape[0], eps, dr,
                                           jnp.asarray(fit.theta[a]), jnp.asarray(fit.cov[a])))
    rows["same nested estimator, brute force (Np x Nq model evaluations)"] = timed(brute, max(1, args.repeats // 3))

    print(f"| step | median s | min s | max s | paper s | paper / ours |")
    print("|---|---|---|---|---|---|")
    out = {}
    for name, (med, lo, hi) in rows.items():
        paper = PAPER_FIT_S if name.startswith("physics fit") else (PAPER_INFER_S if "Np=500" in name else None)
        ratio = f"{paper / med:,.0f}x" if paper else ""
        print(f"| {name} | {med:.4f} | {lo:.4f} | {hi:.4f} | {paper or ''} | {ratio} |")
        out[name] = {"median_s": med, "min_s": lo, "max_s": hi}
    print(f"\njax {jax.__version__}, {jax.devices()[0].platform}, repeats {args.repeats}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)


if __name__ == "__main__":
    main()
