"""Cold start: whole-process wall time of `bayesmag run CONFIG`, first and second run.

Each repeat uses a fresh, empty compilation-cache folder: run 1 compiles everything and fills
it (cold), run 2 is the same command in a new process reading it (warm). With ``--no-cache``
the cache is off (``BAYESMAG_COMPILE_CACHE=0``) for comparison. Prints per-run wall time and
the process's CPU time (user + sys: less sensitive than wall time to other load on a shared
machine) and the job's own stage timings (metrics.json), then medians.

    BAYESMAG_DATA_DIR=../shared/data python benchmarks/bench_coldstart.py --repeats 3
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


def one_run(config: str, out: Path, cache_value: str, sets: list[str] = ()) -> dict:
    env = {**os.environ, "BAYESMAG_COMPILE_CACHE": cache_value, "PYTHONPATH": str(ROOT)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "bayesmag._src.cli", "run", config, "--out", str(out), "--no-progress",
                        *(a for s in sets for a in ("--set", s))], env=env, capture_output=True, text=True)
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
    args = ap.parse_args(argv)
    rows: dict[str, list[dict]] = {"first run (empty cache)": [], "second run (cache filled)": []}
    if args.no_cache:
        rows["cache off"] = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for i in range(args.repeats):
            cache_dir = tmp / f"cache{i}"
            for label, value in (("first run (empty cache)", str(cache_dir)),
                                 ("second run (cache filled)", str(cache_dir)), ("cache off", "0")):
                if label not in rows:
                    continue
                res = one_run(args.config, tmp / "out", value, args.set)
                rows[label].append(res)
                print(f"repeat {i} {label}: " + ", ".join(f"{k} {v:.2f}" for k, v in res.items()), flush=True)
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
