"""Does the command line's figure process pay? ``run_job`` with the figures shared between a worker
process and this one (``figure_worker=True``, the default of ``bayesmag run``) against drawn here only
(``BAYESMAG_FIGURE_WORKER=0``, and every library call).

One Python process runs each config once to compile (not timed), then ``--repeats`` times per mode,
the modes interleaved so that a machine whose speed drifts compares them fairly. Reported per mode:
medians of the job's ``write`` stage (files and figures: what the worker shares) and ``total``
(metrics.json timings), of the whole call's wall time and of its CPU time (this process and the
worker, user + sys); plus the same with ``output.figures = false`` as the floor.

``--tasks`` instead times every figure task of ``paper_hybrid`` alone, drawn in this process
(CPU seconds, median of ``--repeats``): the weights of ``plots._COST``.

    BAYESMAG_DATA_DIR=../shared/data nice python benchmarks/bench_figures.py --repeats 3
    BAYESMAG_DATA_DIR=../shared/data nice python benchmarks/bench_figures.py --tasks
"""

from __future__ import annotations

import argparse
import resource
import statistics
import tempfile
import time
from pathlib import Path


def _cpu() -> float:
    """CPU seconds of this process and its finished children (the figure worker), user + sys."""
    r, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime + c.ru_utime + c.ru_stime



def one(cfg_name: str, mode: str, sets: list[str]) -> dict:
    import bayesmag
    from bayesmag._src.app.cli import _resolve_config

    over = list(sets) + (["output.figures=false"] if mode == "none" else [])
    cfg = bayesmag.load_config(_resolve_config(cfg_name), over)
    with tempfile.TemporaryDirectory() as d:
        t, c = time.perf_counter(), _cpu()
        res = bayesmag.run_job(cfg, Path(d) / "run", progress=False, figure_worker=(mode == "worker"))
        wall, cpu = time.perf_counter() - t, _cpu() - c
    tm = res["metrics"]["timings"]
    return {"write": tm["write"], "total": tm["total"], "wall": wall, "cpu": cpu}


def time_tasks(cfg_name: str, repeats: int) -> None:
    """CPU seconds of every figure task of one job, drawn here alone (median of ``repeats``)."""
    import bayesmag
    from bayesmag._src.app import job as job_module
    from bayesmag._src.app.cli import _resolve_config

    captured = []

    class Capture:                                   # a figure drawer that keeps the tasks
        def __init__(self, *a, **k):
            pass

        def warm(self):
            pass

        def submit(self, draw, *args, **kwargs):
            captured.append((draw, args, kwargs))

        def finish(self, out, **k):
            return []

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            pass

    from bayesmag._src.app import figure_worker
    real = figure_worker.figures
    figure_worker.figures = lambda *a, **k: Capture()
    try:
        cfg = bayesmag.load_config(_resolve_config(cfg_name), [])
        with tempfile.TemporaryDirectory() as d:
            job_module.run_job(cfg, Path(d) / "run", progress=False)
    finally:
        figure_worker.figures = real
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for draw, args, kwargs in captured:
            ts = []
            for _ in range(repeats):
                c = time.process_time()
                draw(Path(d), *args, **kwargs)
                ts.append(time.process_time() - c)
            rows.append((args[0], statistics.median(ts)))
    print("| figure | CPU s |\n|---|---|")
    for name, t in rows:
        print(f"| {name} | {t:.3f} |")
    print(f"| all | {sum(t for _, t in rows):.3f} |")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=["paper_physics", "quickstart"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--tasks", action="store_true", help="time each figure task of paper_hybrid alone instead")
    args = ap.parse_args(argv)
    if args.tasks:
        return time_tasks("paper_hybrid", args.repeats)
    modes = ("worker", "inline", "none")
    for name in args.configs:
        one(name, "inline", args.set)                   # compile once, untimed
        rows = {m: [] for m in modes}
        for r in range(args.repeats):
            for m in (modes if r % 2 == 0 else modes[::-1]):
                rows[m].append(one(name, m, args.set))
                x = rows[m][-1]
                print(f"{name} {m:6s} repeat {r}: write {x['write']:.2f} s  total {x['total']:.2f} s  "
                      f"wall {x['wall']:.2f} s  cpu {x['cpu']:.2f} s", flush=True)
        print(f"\n{name}: medians over {args.repeats} repeats (s)")
        print("| figures | write | total | wall | CPU |\n|---|---|---|---|---|")
        for m, label in zip(modes, ("shared with the worker (CLI)", "in-process (library)", "off")):
            med = {k: statistics.median(x[k] for x in rows[m]) for k in ("write", "total", "wall", "cpu")}
            print(f"| {label} | {med['write']:.2f} | {med['total']:.2f} | {med['wall']:.2f} | {med['cpu']:.2f} |")
        print()


if __name__ == "__main__":
    main()
