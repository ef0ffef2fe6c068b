"""How many JAX programs a run traces and lowers (each costs that even when the persistent compile cache holds it).

Wraps JAX's uncached-call path, runs ``bayesmag run CONFIG`` in this process and prints, per program name and
bayesmag call site, how often it was traced; the total goes to stderr last. Run it twice with the same
``BAYESMAG_COMPILE_CACHE`` folder: the second run is the warm start.

    BAYESMAG_DATA_DIR=../shared/data BAYESMAG_COMPILE_CACHE=/tmp/cc python benchmarks/count_traced_programs.py
"""
import collections, traceback, sys
from jax._src import pjit
orig = pjit._pjit_call_impl_python
seen = collections.Counter()
def spy(*args, **kw):
    nm = str(kw.get("name", "?"))
    st = [f for f in traceback.extract_stack()[:-1] if "/bayesmag/" in f.filename]
    where = f"{st[-1].filename.split('bayesmag/')[-1]}:{st[-1].lineno}" if st else "?"
    seen[(nm, where)] += 1
    return orig(*args, **kw)
pjit._pjit_call_impl_python = spy
from bayesmag._src.app.cli import main
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
config = sys.argv[1] if len(sys.argv) > 1 else str(ROOT / "configs" / "paper_hybrid.toml")
with tempfile.TemporaryDirectory() as tmp:
    main(["run", config, "--out", str(Path(tmp) / "run"), "--no-progress", "--set", "network.max_epochs=3",
          "--set", "output.figures=false"])
for (n, w), c in sorted(seen.items(), key=lambda kv: -kv[1]):
    print(c, n, w, file=sys.stderr)
print("programs traced:", sum(seen.values()), file=sys.stderr)
