"""Calibrate once per left-out session of ``bench_hybrid_shift.py`` and pickle the pieces (issue #24 d diagnostics).

Saved per session (``DIR/seed{S}_run{R}.pkl``): the training and test rows, the physics fit, the calibrated hybrid
predictor (its session model fitted as the job fits it) and the network's in-sample correction on the training rows,
so that other session models can be scored against loro offline (``benchmarks/score_hybrid_sessions.py DIR``).
With ``--folds`` the job runs with ``[uq] transfer_networks = "by_run_folds"`` and the pickle also holds the
physics stage's session model and the by-run fold networks' per-row pieces (``NetworkTransfer``); with ``--extra
NAME`` the physics model carries that catalogue term (``[physics] extra_terms = [{name = NAME}]``, e.g.
``axis_quadratic``, the distortion the simulated sessions share, as ``bayesmag discover`` reports it).

    python benchmarks/cache_hybrid_sessions.py DIR 0 1 2 [--folds] [--extra axis_quadratic]     # the seeds
"""
import pickle
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import bench_hybrid_shift as B  # noqa: E402
from bayesmag._src.app.config import config_from_dict  # noqa: E402
from bayesmag._src.pipeline.calibrate import calibrate  # noqa: E402

RAW = {"name": "x", "data": {"path": "unused.csv"}, "physics": {"t0": "mean"},
       "uq": {"method": "psqmc", "n_params": 100, "n_qmc": 128, "seed": 0, "transfer": "hierarchical"},
       "network": {"enabled": True, "learning_rate": 1e-3, "batch_size": 64, "max_epochs": 200, "patience": 20,
                   "mc_passes": 50, "seed": 0}, "output": {"figures": False, "progress": False}}


def main(argv):
    folds = "--folds" in argv
    argv = [a for a in argv if a != "--folds"]
    extra = None
    if "--extra" in argv:
        i = argv.index("--extra")
        extra, argv = argv[i + 1], argv[:i] + argv[i + 2:]
    out, seeds = Path(argv[0]), [int(x) for x in argv[1:]] or [0]
    raw = {**RAW, "uq": {**RAW["uq"], **({"transfer_networks": "by_run_folds"} if folds else {})},
           "physics": {**RAW["physics"], **({"extra_terms": [{"name": extra}]} if extra else {})}}
    out.mkdir(parents=True, exist_ok=True)
    for seed in seeds:
        d = B.sessions(8, 600, seed)
        for run in range(1, 9):
            path = out / f"seed{seed}_run{run}.pkl"
            if path.exists():
                continue
            t = time.perf_counter()
            train, test = d.subset(np.flatnonzero(d.run != run)), d.subset(np.flatnonzero(d.run == run))
            s = config_from_dict({**raw, "split": {"kind": "by_run", "test_runs": [run]}}).settings()
            cr = calibrate(train, s, test=test)
            nn = np.asarray(cr.predictor.network_part(train).mean, np.float64)
            tmp = path.with_suffix(".tmp")
            with open(tmp, "wb") as f:
                nt = next(iter(cr.hybrid.network_transfer.values()), None) if folds else None
                pickle.dump({"train": train, "test": test, "fit": cr.fit, "hybrid": cr.predictor, "nn": nn,
                             "physics_sessions": cr.physics.predictor.sessions, "network_transfer": nt}, f)
            tmp.rename(path)
            print(seed, run, f"{time.perf_counter() - t:.0f}s", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
