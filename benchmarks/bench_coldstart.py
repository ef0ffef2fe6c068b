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

    BAYESMAG_DATA_DIR=../shared/data python benchmarks/bench_coldstart.py --repeats 3
    BAYESMAG_DATA_DIR=../shared/data python benchmarks/bench_coldstart.py --repeats 3 --code /tmp/base
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
STAGES = ("physics_fit", "physics_uq", "network_train", "hybrid_inference", "total")


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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "paper_hybrid.toml"))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-cache", action="store_true", help="also time runs with the cache off")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override passed to every run (e.g. output.figures=false)")
    ap.add_argument("--code", nargs="*", default=[], metavar="DIR",
                    help="other checkouts to time as well, interleaved with this one")
    args = ap.parse_args(argv)
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
