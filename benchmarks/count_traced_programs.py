"""How many JAX programs a run traces and lowers (each costs that even when the persistent compile cache holds it).

Wraps JAX's uncached-call path, runs ``bayesmag run CONFIG`` (default ``configs/paper_hybrid.toml`` with
``network.max_epochs=3``, figures off) in this process and prints, per program name and bayesmag call site,
how often it was traced, then the total. Run it twice with the same ``BAYESMAG_COMPILE_CACHE`` folder: the
second run is the warm start.

    BAYESMAG_DATA_DIR=../shared/data BAYESMAG_COMPILE_CACHE=/tmp/cc python benchmarks/count_traced_programs.py
"""

from __future__ import annotations

import collections
import sys
import tempfile
import traceback
from pathlib import Path

from jax._src import pjit

ROOT = Path(__file__).resolve().parents[1]
SEEN: collections.Counter = collections.Counter()
_REAL = pjit._pjit_call_impl_python


def _spy(*args, **kwargs):
    frames = [f for f in traceback.extract_stack()[:-1] if "/bayesmag/" in f.filename]
    where = f"{frames[-1].filename.split('bayesmag/')[-1]}:{frames[-1].lineno}" if frames else "?"
    SEEN[(str(kwargs.get("name", "?")), where)] += 1
    return _REAL(*args, **kwargs)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    config = argv[0] if argv else str(ROOT / "configs" / "paper_hybrid.toml")
    pjit._pjit_call_impl_python = _spy
    from bayesmag._src.app.cli import main as cli
    with tempfile.TemporaryDirectory() as tmp:
        rc = cli(["run", config, "--out", str(Path(tmp) / "run"), "--no-progress", "--set", "network.max_epochs=3",
                  "--set", "output.figures=false"])
    for (name, where), n in sorted(SEEN.items(), key=lambda kv: -kv[1]):
        print(n, name, where)
    print("programs traced:", sum(SEEN.values()))
    return rc


if __name__ == "__main__":
    raise SystemExit(main())
