"""Network training cost per epoch, and what each part of the step costs (issue #14 item 8).

Times the compiled training loop of :func:`bayesmag.network.fit_residual_network` at the paper's
settings (4 x 64 ReLU, batch 16, DropConnect 0.01, Adam) on 3040 synthetic rows for a fixed
number of epochs (early stopping off), after one warm-up call: CPU time (``time.process_time``,
less sensitive to other load) and wall time, minimum over ``--repeats``. Variants: 3 axes vmapped
(the job's case), 1 axis (what the last axis training alone costs), and 3 axes without DropConnect
(the mask's share).

    python benchmarks/bench_training.py --epochs 30 --repeats 3
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import dataclasses
import time

import numpy as np

import bayesmag  # noqa: F401  (float64 for the rest; the network casts to float32)
from bayesmag._src.core import network as N


def time_fit(x, r, spec, repeats):
    N.fit_residual_network(x, r, spec)                                   # compile
    cpu, wall = [], []
    for _ in range(repeats):
        c, w = time.process_time(), time.perf_counter()
        N.fit_residual_network(x, r, spec)
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - w)
    return min(cpu) / spec.max_epochs, min(wall) / spec.max_epochs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3040, 4))
    r = 0.1 * np.sin(x[:, :3]) + 0.05 * rng.normal(size=(3040, 3))
    spec = N.NetworkSpec(max_epochs=a.epochs, patience=10**9, validation="random")   # paper settings otherwise
    steps = -(-int(3040 * (1 - spec.validation_fraction)) // spec.batch_size)
    print(f"| variant | CPU ms / epoch | wall ms / epoch | CPU us / step ({steps} steps of {spec.batch_size} rows) |")
    print("|---|---|---|---|")
    for label, s, rr in (("3 axes (vmapped)", spec, r), ("1 axis", spec, r[:, :1]),
                         ("3 axes, DropConnect off", dataclasses.replace(spec, dropconnect=0.0), r)):
        c, w = time_fit(x, rr, s, a.repeats)
        print(f"| {label} | {c * 1e3:.1f} | {w * 1e3:.1f} | {c / steps * 1e6:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
