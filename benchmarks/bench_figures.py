"""Does the command line's figure process pay? ``run_job`` with the figures drawn in a worker process
(``figure_worker=True``, ``bayesmag run`` with ``BAYESMAG_FIGURE_WORKER=1``) against drawn in-process
(the default of the command line and of library calls).

One Python process runs each config once to compile (not timed), then ``--repeats`` times per mode,
the modes interleaved so that a machine whose speed drifts compares them fairly. Reported per mode:
medians of the job's ``write`` stage (files and figures: what the worker overlaps) and ``total``
(metrics.json timings), and of the whole call's wall time; plus the same with ``output.figures =
false`` as the floor.

    BAYESMAG_DATA_DIR=../shared/data nice python benchmarks/bench_figures.py --repeats 3
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path



def one(cfg_name: str, mode: str, sets: list[str]) -> dict:
    import bayesmag
    from bayesmag._src.app.cli import _resolve_config

    over = list(sets) + (["output.figures=false"] if mode == "none" else [])
    cfg = bayesmag.load_config(_resolve_config(cfg_name), over)
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        res = bayesmag.run_job(cfg, Path(d) / "run", progress=False, figure_worker=(mode == "worker"))
        wall = time.perf_counter() - t
    tm = res["metrics"]["timings"]
    return {"write": tm["write"], "total": tm["total"], "wall": wall}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=["paper_physics", "quickstart"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    modes = ("worker", "inline", "none")
    for name in args.configs:
        one(name, "inline", args.set)                   # compile once, untimed
        rows = {m: [] for m in modes}
        for r in range(args.repeats):
            for m in (modes if r % 2 == 0 else modes[::-1]):
                rows[m].append(one(name, m, args.set))
                x = rows[m][-1]
                print(f"{name} {m:6s} repeat {r}: write {x['write']:.2f} s  total {x['total']:.2f} s  "
                      f"wall {x['wall']:.2f} s", flush=True)
        print(f"\n{name}: medians over {args.repeats} repeats (s)")
        print("| figures | write | total | wall |\n|---|---|---|---|")
        for m, label in zip(modes, ("worker process (CLI)", "in-process (library)", "off")):
            med = {k: statistics.median(x[k] for x in rows[m]) for k in ("write", "total", "wall")}
            print(f"| {label} | {med['write']:.2f} | {med['total']:.2f} | {med['wall']:.2f} |")
        print()


if __name__ == "__main__":
    main()
