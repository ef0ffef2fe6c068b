"""Which simulated training draws have a second mode of the collapsed hyperparameter posterior (issue 24).

Run:  python benchmarks/scan_modes.py [--draws 30] [--generator gauss ...] [--weak 5|off] [--runs 30] [--only 3 7]

For every generator of ``bench_hierarchical.py`` and training draw (30 sessions of 100 rows, the benchmark's
seeds), the physics fit and, per axis, BFGS from the two starts of ``_modes`` (between-session sds at a fifth
of the prior scale, and at the prior scale). Prints one line per draw-axis with two distinct modes: both
modes' between-session sds (uT at an RMS input), noise sd and log posterior, and which is higher. No transfer,
no new sessions. ``--weak``: the runs' weak directions decoupled as in ``fit_sessions`` (default ``off``: the
stats the scan of the fifth round used); ``--runs``: training sessions per draw.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_hierarchical import GENERATORS  # noqa: E402
from test_transfer import _session  # noqa: E402

import bayesmag  # noqa: E402
from bayesmag._src.pipeline.sessions import hierarchical as H  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--generator", nargs="+", default=list(GENERATORS), choices=sorted(GENERATORS))
    ap.add_argument("--weak", type=lambda v: None if v == "off" else float(v), default=None)
    ap.add_argument("--runs", type=int, default=30)
    ap.add_argument("--only", type=int, nargs="*", default=None, help="these draws only (instead of 0..draws-1)")
    args = ap.parse_args()
    print(f"## `python benchmarks/scan_modes.py {' '.join(sys.argv[1:])}`\n")
    total = found2 = higher2 = 0
    for name in args.generator:
        for draw in (range(args.draws) if args.only is None else args.only):
            train = _session(draw, args.runs, rows=100, session_params=GENERATORS[name])
            fit = bayesmag.fit_physics(train, bayesmag.PhysicsModel.paper(t0=float(np.mean(train.temperature))))
            eff, _ = H.select_effects(train, fit)
            q = len(eff)
            for a in range(3):
                st = H.run_stats(train, fit, eff, directions=None if args.weak is None else
                                 H.weak_directions(train, fit, eff, a, args.weak))
                args_ = (jnp.asarray(st.m0[a]), jnp.asarray(st.m1[a]), jnp.asarray(st.m2[a]), jnp.asarray(st.first[a]),
                         jnp.asarray(st.n), jnp.asarray(st.effects), H.TAU_PRIOR_SCALE, H.SIGMA_PRIOR_SCALE, H.REML)

                def fg(h, args_=args_):
                    v, g = H._neg_lp_and_grad(jnp.asarray(h), *args_)
                    v, g = float(v), np.asarray(g, np.float64)
                    return (v, g) if np.isfinite(v) else (1e300, np.zeros_like(g))

                h0 = H._init_h(st, a, H.TAU_PRIOR_SCALE)
                modes = H._modes(fg, h0, q, H.TAU_PRIOR_SCALE, search=True)
                total += 1
                if len(modes) > 1:
                    found2 += 1
                    first = H._modes(fg, h0, q, H.TAU_PRIOR_SCALE, search=False)[0][0]
                    higher2 += not np.allclose(modes[0][0], first)
                    desc = "; ".join(
                        f"{'first start' if np.allclose(h, first) else 'second start'}: tau "
                        f"{' / '.join(f'{t:.3f}' for t in np.exp(h[:q]))}, sigma {np.exp(h[q]):.4f}, lp {-fg(h)[0]:.1f}"
                        for h, _ in modes)
                    print(f"- {name} draw {draw} axis {'xyz'[a]} ({', '.join(eff)}): {desc}", flush=True)
    print(f"\n{found2} of {total} generator-draw-axes have a second mode; on {higher2} the second start's is higher.")


if __name__ == "__main__":
    jax.config.update("jax_enable_x64", True)
    main()
