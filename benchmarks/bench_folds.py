"""Cross-conformal fold networks: trained at once (the job's way) against one fold after the other.

On the honest_hybrid training rows (Belsten, time-block split, seed 0) and its network settings,
the K = ``network.conformal_folds`` networks are trained by
:func:`~bayesmag._src.pipeline.hybrid.train_fold_networks` (all folds' axes on one shared pool of threads)
and by :func:`~bayesmag._src.pipeline.hybrid.train_network` fold by fold (each fold's axes on its own
threads). One warm-up of each, then ``--repeats`` alternating timings (wall, in-process, compiled);
prints each and the medians, and checks that both give the same epochs per network and axis.

    BAYESMAG_DATA_DIR=../shared/data python benchmarks/bench_folds.py --repeats 3
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

import bayesmag
from bayesmag._src.app.config import load_config
from bayesmag._src.core.data import make_split
from bayesmag._src.pipeline.hybrid import check_network_config, conformal_folds, train_fold_networks, train_network
from bayesmag._src.app.job import build_model, load_data
from bayesmag._src.core.physics import inputs_from_data
from bayesmag._src.core.predictor import network_inputs

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "honest_hybrid.toml"))
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    cfg = load_config(args.config)
    data = load_data(cfg)
    split = make_split(data, kind=cfg.split.kind, test_fraction=cfg.split.test_fraction, seed=cfg.split.seed)
    train = data.subset(split.train)
    fit = bayesmag.fit_physics(train, build_model(cfg, train))
    x, r = network_inputs(train), train.b_ref - fit.predict(inputs_from_data(train))
    spec, net = check_network_config(cfg)[0], cfg.network
    k_folds = net.conformal_folds
    folds = conformal_folds(train.run, fraction=net.validation_fraction, folds=k_folds, seed=net.seed + 1)

    def one_after_the_other():
        return [train_network(x[folds != k], r[folds != k], spec, net, groups=train.run[folds != k])
                for k in range(k_folds)]

    def together():
        return train_fold_networks(x, r, spec, net, train.run, folds, k_folds)

    ways = {"one fold after the other": one_after_the_other, "all folds at once": together}
    epochs = {name: [int(e) for n in f() for e in np.asarray(n.info.epochs_run)] for name, f in ways.items()}
    assert len({tuple(v) for v in epochs.values()}) == 1, epochs
    print(f"{k_folds} fold networks x 3 axes, epochs run: {epochs['all folds at once']} (sum {sum(epochs['all folds at once'])})")
    times: dict[str, list[float]] = {name: [] for name in ways}
    for rep in range(args.repeats):
        for name, f in ways.items():
            t = time.perf_counter()
            f()
            times[name].append(time.perf_counter() - t)
            print(f"repeat {rep} {name}: {times[name][-1]:.2f} s", flush=True)
    med = {name: statistics.median(v) for name, v in times.items()}
    print(f"\nmedians of {args.repeats}: " + ", ".join(f"{n} {v:.2f} s" for n, v in med.items())
          + f"; ratio {med['one fold after the other'] / med['all folds at once']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
