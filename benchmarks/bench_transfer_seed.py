"""How much the hierarchical session model's new-session sd moves with ``uq.seed`` (sixth outside pass).

Belsten, one run left out (default run 1), ``paper_physics`` with ``[uq] transfer = "hierarchical"``: the
root-mean-square transfer sd over the left-out rows for seeds 0..N-1, and its spread (max - min) / mean per axis.
The seed enters only the importance sample of the between-session posterior (docs/sessions.md).

    python benchmarks/bench_transfer_seed.py [--seeds 5] [--run 1]
"""

import argparse
import dataclasses
import time

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--run", type=int, default=1)
    args = ap.parse_args(argv)
    from bayesmag._src.app.config import load_config
    from bayesmag._src.app.job import load_data
    from bayesmag._src.core.data import make_split
    from bayesmag._src.pipeline.calibrate import calibrate

    cfg = load_config("paper_physics", ['uq.n_params=64', 'uq.n_qmc=64', 'split.kind="by_run"',
                                        f'split.test_runs=[{args.run}]', 'uq.transfer="hierarchical"'])
    data = load_data(cfg)
    sp = make_split(data, kind="by_run", test_runs=[args.run])
    train, test = data.subset(sp.train), data.subset(sp.test)
    rows = []
    print(f"Belsten, run {args.run} left out: RMS new-session transfer sd (uT) by uq.seed")
    for seed in range(args.seeds):
        st = cfg.settings()
        st = dataclasses.replace(st, uq=dataclasses.replace(st.uq, seed=seed))
        t = time.perf_counter()
        run = calibrate(train, st, test=test)
        sd = np.sqrt(np.mean(np.asarray(run.physics.prediction.transfer) ** 2, axis=0))
        rows.append(sd)
        print(f"  seed {seed}: x {sd[0]:.4f}  y {sd[1]:.4f}  z {sd[2]:.4f}   ({time.perf_counter() - t:.1f} s)")
    r = np.array(rows)
    spread = (r.max(0) - r.min(0)) / r.mean(0)
    print("spread (max - min) / mean: " + "  ".join(f"{a} {v:.1%}" for a, v in zip("xyz", spread)))


if __name__ == "__main__":
    main()
