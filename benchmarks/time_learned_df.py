"""Cost of the learned Student-t dof (``transfer_df = "learned"``) against a fixed dof and the Gaussian, on the
30-session simulated case of docs/sessions.md (``_session(0, 30, rows=100)``, ``fit_laplace`` on its run stats).

Run: ``python benchmarks/time_learned_df.py [--repeats 3]``: the first fit of each variant (compilation
included), then ``--repeats`` compiled fits of each, interleaved; medians. Also the learned dof's posterior.
``--apply``: instead, the predictive's cost: ``new_session_variance`` of each variant's posterior at 100 000 rows
(``_session(5, 10, rows=10000)``'s Jacobian, three axes), ``--repeats`` interleaved calls, medians.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import bayesmag  # noqa: E402
from bayesmag._src.pipeline.sessions import hierarchical as H  # noqa: E402
from test_transfer import _session  # noqa: E402

VARIANTS = {"gaussian": dict(likelihood="gaussian"), "student_t df 4": dict(likelihood="student_t", df=4.0),
            "student_t learned": dict(likelihood="student_t", df="learned")}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--apply", action="store_true")
    args = ap.parse_args()
    d = _session(0, 30, rows=100)
    model = bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature)))
    fit = bayesmag.fit_physics(d, model)
    st = H.run_stats(d, fit)
    if args.apply:
        posts = {k: H.fit_laplace(st, model.param_names, **kw) for k, kw in VARIANTS.items()}
        J = H._jacobian(fit, _session(5, 10, rows=10000))
        used = (posts["student_t learned"].df_weight >= H.MIN_DF_WEIGHT).sum(1)
        print(f"{J.shape[1]} rows x 3 axes; learned dof: {used.tolist()} dofs in the mixture per axis")
        times = {k: [] for k in posts}
        for _ in range(args.repeats):
            for k, post in posts.items():
                t = time.perf_counter()
                post.new_session_variance(J)
                times[k].append(time.perf_counter() - t)
        for k, v in times.items():
            print(f"{k}: new_session_variance {' '.join(f'{x:.2f}' for x in v)} s, median {np.median(v):.2f} s")
        return
    times = {k: [] for k in VARIANTS}
    for k, kw in VARIANTS.items():
        t = time.perf_counter()
        post = H.fit_laplace(st, model.param_names, **kw)
        print(f"{k}: first fit (compilation included) {time.perf_counter() - t:.2f} s", flush=True)
        if post.df_grid:
            print("  dof posterior x / y / z on", [f"{g:g}" for g in post.df_grid])
            for a in range(3):
                print("   ", " ".join(f"{w:.3f}" for w in post.df_weight[a]))
    for _ in range(args.repeats):
        for k, kw in VARIANTS.items():
            t = time.perf_counter()
            H.fit_laplace(st, model.param_names, **kw)
            times[k].append(time.perf_counter() - t)
    for k, v in times.items():
        print(f"{k}: compiled fits {' '.join(f'{x:.2f}' for x in v)} s, median {np.median(v):.2f} s")


if __name__ == "__main__":
    main()
