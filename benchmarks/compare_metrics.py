"""Do two checkouts compute the same numbers? ``metrics.json`` of the same configs, timings aside.

Runs ``bayesmag run CONFIG`` with the code of this checkout and of ``--base`` (another checkout,
e.g. ``git worktree add /tmp/base d806e3b``), each on the config file of its own tree, and compares
the two ``metrics.json`` exactly (every number, every string) after dropping what measures time:
the ``timings`` block and the per-likelihood ``train_seconds`` / NUTS ``seconds``. Figures are off
(they do not enter metrics.json). Exit status 0 when every config matches, 1 otherwise (the
differing keys are printed).

    git worktree add /tmp/base d806e3b
    BAYESMAG_DATA_DIR=../shared/data python benchmarks/compare_metrics.py --base /tmp/base
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TIME_KEYS = ("timings", "train_seconds", "seconds")


def strip_time(x):
    """``x`` without the keys that measure time (at any depth)."""
    if isinstance(x, dict):
        return {k: strip_time(v) for k, v in x.items() if k not in TIME_KEYS}
    if isinstance(x, list):
        return [strip_time(v) for v in x]
    return x


def differences(a, b, path: str = "") -> list[str]:
    """Every path where ``a`` and ``b`` differ (exact comparison)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{path}.{k}: only in {'base' if k in a else 'this'}" for k in sorted(set(a) ^ set(b))]
        for k in a.keys() & b.keys():
            out += differences(a[k], b[k], f"{path}.{k}")
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (u, v) in enumerate(zip(a, b)) for d in differences(u, v, f"{path}[{i}]")]
    return [] if a == b else [f"{path}: base {a!r} != this {b!r}"]


def largest_relative(a, b, path: str = ""):
    """``(|a - b| / max(|a|, |b|), path)`` of the number that differs most between ``a`` and ``b``
    relative to its size (numbers present in both only), or None when no number differs."""
    if isinstance(a, dict) and isinstance(b, dict):
        found = [largest_relative(a[k], b[k], f"{path}.{k}") for k in a.keys() & b.keys()]
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        found = [largest_relative(u, v, f"{path}[{i}]") for i, (u, v) in enumerate(zip(a, b))]
    elif (isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool)
          and not isinstance(b, bool) and a != b):
        return (abs(a - b) / max(abs(a), abs(b)), path)
    else:
        return None
    found = [f for f in found if f is not None]
    return max(found) if found else None


def run(code: Path, config: str, out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(code)}
    cmd = [sys.executable, "-m", "bayesmag._src.app.cli", "run", str(code / config), "--out", str(out),
           "--no-progress", "--set", "output.figures=false"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=out.parent)   # not a repo: no shadowing
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{r.stderr[-3000:]}")
    return json.loads((out / "metrics.json").read_text())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="the other checkout (its bayesmag/ and configs/)")
    ap.add_argument("--configs", nargs="+", default=["configs/paper_physics.toml", "configs/paper_hybrid.toml"])
    ap.add_argument("--show", type=int, default=40, help="differences printed per config")
    args = ap.parse_args(argv)
    base = Path(args.base).resolve()
    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        for config in args.configs:
            m_base = strip_time(run(base, config, Path(tmp) / "base"))
            m_this = strip_time(run(ROOT, config, Path(tmp) / "this"))
            diff = differences(m_base, m_this)
            print(f"{config}: {'identical' if not diff else f'{len(diff)} differences'} "
                  f"({len(json.dumps(m_this))} characters of metrics.json compared, timings aside)")
            rel = largest_relative(m_base, m_this)
            if rel is not None:
                print(f"  largest relative difference of a number present in both: {rel[0]:.2g} at {rel[1]}")
            for d in diff[:args.show]:
                print("  " + d)
            ok &= not diff
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
