"""Cold start: whole-process wall time of `bayesmag run CONFIG`, first and second run.

Each repeat uses a fresh, empty compilation-cache folder: run 1 compiles everything and fills
it (cold), run 2 is the same command in a new process reading it (warm). With ``--no-cache``
the cache is off (``BAYESMAG_COMPILE_CACHE=0``) for comparison. Prints per-run wall time and
the process's CPU time (user + sys: less sensitive than wall time to other load on a shared
machine) and the job's own stage timings (metrics.json), then medians.

``--code DIR [DIR ...]`` times the ``bayesmag`` of other checkouts too (e.g. ``git worktree add
/tmp/base 70b89a9``, the code when issue #14 was written), interleaved with this one within every
repeat, so that a machine whose speed drifts compares them fairly (each runs the config of its own
tree); checkouts without the persistent cache compile on every run.

``--exit`` times the end of the process instead: second runs (cache filled) as shipped and with
the command's ``gc.freeze()`` made a no-op, alternating; per run the wall time from ``main()``
returning (every file written) to the process's end, and the whole process's wall and CPU time.

    BAYESMAG_DATA_DIR=../shared/data python benchmarks/bench_coldstart.py --repeats 3
    BAYESMAG_DATA_DIR=../shared/data python benchmarks/bench_coldstart.py --repeats 3 --code /tmp/base
    BAYESMAG_DATA_DIR=../shared/data python benchmarks/bench_coldstart.py --repeats 3 --exit
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("physics_fit", "physics_uq", "network_train", "hybrid_inference", "write", "total")


def one_run(config: str, out: Path, cache_value: str, sets: list[str] = (), code: Path = ROOT) -> dict:
    env = {**os.environ, "BAYESMAG_COMPILE_CACHE": cache_value, "PYTHONPATH": str(code)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "bayesmag._src.app.cli", "run", config, "--out", str(out), "--no-progress",
                        *(a for s in sets for a in ("--set", s))], env=env, capture_output=True, text=True,
                       cwd=out.parent)       # not this repository: its bayesmag/ would shadow PYTHONPATH
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if r.returncode != 0:
        raise SystemExit(f"bayesmag run failed:\n{r.stderr[-3000:]}")
    timings = json.loads((out / "metrics.json").read_text())["timings"]
    shutil.rmtree(out)
    return {"wall": wall, "cpu": cpu, **{k: timings.get(k, float("nan")) for k in STAGES}}


# The command as ``bayesmag`` runs it, printing when main() returned; "nofreeze" disables gc.freeze first.
_EXIT_WRAPPER = """
import gc, sys, time
if sys.argv.pop(1) == "nofreeze":
    gc.freeze = lambda: None
sys.argv[0] = "bayesmag"
from bayesmag._src.app.cli import main
rc = main()
print(f"BENCH_MAIN_RETURNED {time.time():.6f}", file=sys.stderr, flush=True)
sys.exit(rc)
"""


def exit_runs(config: str, repeats: int, sets: list[str]) -> None:
    """Second runs with and without the command's gc.freeze(): the process's end after main() returned."""
    modes = [("as shipped (gc.freeze)", "freeze"), ("gc.freeze disabled (job start and exit)", "nofreeze")]
    rows: dict[str, list[dict]] = {label: [] for label, _ in modes}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        env = {**os.environ, "BAYESMAG_COMPILE_CACHE": str(tmp / "cache"), "PYTHONPATH": str(ROOT)}

        def run(mode: str) -> dict:
            out = tmp / "out"
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t = time.perf_counter()
            r = subprocess.run([sys.executable, "-c", _EXIT_WRAPPER, mode, "run", config, "--out", str(out),
                                "--no-progress", *(a for s in sets for a in ("--set", s))],
                               env=env, capture_output=True, text=True, cwd=tmp)
            end, wall = time.time(), time.perf_counter() - t
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            if r.returncode != 0:
                raise SystemExit(f"bayesmag run failed:\n{r.stderr[-3000:]}")
            returned = float(r.stderr.split("BENCH_MAIN_RETURNED ")[1].split()[0])
            shutil.rmtree(out)
            return {"exit": end - returned, "wall": wall,
                    "cpu": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)}

        run("freeze")                                   # fills the cache (not reported)
        for i in range(repeats):
            for label, mode in (modes if i % 2 == 0 else modes[::-1]):
                rows[label].append(run(mode))
                print(f"repeat {i} {label}: " + ", ".join(f"{k} {v:.2f}" for k, v in rows[label][-1].items()),
                      flush=True)
    print(f"\nmedians of {repeats} (second runs of {Path(config).name}; seconds):")
    print("| exit | main() returned -> process end (wall) | whole process (wall) | whole process (CPU) |")
    print("|---|---|---|---|")
    for label, rs in rows.items():
        med = {k: statistics.median(r[k] for r in rs) for k in rs[0]}
        print(f"| {label} | {med['exit']:.2f} | {med['wall']:.1f} | {med['cpu']:.1f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "paper_hybrid.toml"))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-cache", action="store_true", help="also time runs with the cache off")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override passed to every run (e.g. output.figures=false)")
    ap.add_argument("--code", nargs="*", default=[], metavar="DIR",
                    help="other checkouts to time as well, interleaved with this one")
    ap.add_argument("--exit", action="store_true", help="time the process's end, with and without gc.freeze()")
    args = ap.parse_args(argv)
    if args.exit:
        exit_runs(str(Path(args.config).resolve()), args.repeats, args.set)
        return 0
    codes = [ROOT] + [Path(c).resolve() for c in args.code]
    kinds = ["first run (empty cache)", "second run (cache filled)"] + (["cache off"] if args.no_cache else [])
    name = (lambda c: "" if len(codes) == 1 else f"{'this checkout' if c == ROOT else c}: ")   # noqa: E731
    rows: dict[str, list[dict]] = {name(c) + k: [] for c in codes for k in kinds}
    config = Path(args.config).resolve()

    def config_of(code: Path) -> str:
        """The config inside ``code``'s own tree when it is one of this repository's (settings change)."""
        return str(code / config.relative_to(ROOT)) if config.is_relative_to(ROOT) else str(config)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for i in range(args.repeats):
            for j, code in enumerate(codes):
                cache_dir = tmp / f"cache{i}_{j}"
                for kind, value in zip(kinds, (str(cache_dir), str(cache_dir), "0")):
                    res = one_run(config_of(code), tmp / "out", value, args.set, code)
                    rows[name(code) + kind].append(res)
                    print(f"repeat {i} {name(code)}{kind}: " + ", ".join(f"{k} {v:.2f}" for k, v in res.items()),
                          flush=True)
    print(f"\nmedians of {args.repeats} ({Path(args.config).name}" + "".join(f" --set {s}" for s in args.set)
          + "; seconds):")
    print("| run | whole process (wall) | whole process (CPU, user+sys) | " + " | ".join(STAGES) + " |")
    print("|---|---|---|" + "---|" * len(STAGES))
    for label, rs in rows.items():
        med = {k: statistics.median(r[k] for r in rs) for k in rs[0]}
        print(f"| {label} | {med['wall']:.1f} | {med['cpu']:.1f} | " + " | ".join(f"{med[k]:.2f}" for k in STAGES) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
