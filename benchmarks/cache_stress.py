"""Is the persistent compilation cache safe? Every job twice against one fresh cache folder.

The first run of each config compiles and writes the cache, the second reads every entry back.
Prints each run's exit status, wall time and cache entries, and compares the two ``metrics.json``
(timings and the certificate's date aside, as ``compare_metrics.py`` does). Exit status 0 when every
run succeeded and every pair matched.

    BAYESMAG_DATA_DIR=../shared/data python benchmarks/cache_stress.py
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_metrics import differences, strip_time  # noqa: E402

CONFIGS = ["quickstart", "paper_physics", "paper_hybrid", "honest_hybrid", "field_simulated", "scalar_belsten"]


def _metrics(folder: Path) -> dict:
    m = strip_time(json.loads((folder / "metrics.json").read_text()))
    m.get("certificate", {}).pop("date_utc", None)
    return m


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=CONFIGS)
    args = ap.parse_args(argv)
    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        env = {**os.environ, "BAYESMAG_COMPILE_CACHE": str(tmp / "cache")}
        for cfg in args.configs:
            for p in ("cold", "warm"):
                t = time.perf_counter()
                r = subprocess.run([sys.executable, "-m", "bayesmag", "run", cfg, "--out", str(tmp / f"{cfg}.{p}"),
                                    "--no-progress"], env=env, capture_output=True, text=True, cwd=tmp)
                n = sum(1 for f in (tmp / "cache").rglob("*") if f.is_file())
                print(f"{cfg} {p}: exit {r.returncode}, {time.perf_counter() - t:.1f} s, {n} cache entries", flush=True)
                ok &= r.returncode == 0
                if r.returncode != 0:
                    print(r.stderr[-2000:])
            if ok:
                d = differences(_metrics(tmp / f"{cfg}.cold"), _metrics(tmp / f"{cfg}.warm"))
                print(f"  {cfg}: cold vs warm metrics.json {'identical' if not d else d[:5]}")
                ok &= not d
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
