"""Which extra terms ``bayesmag discover`` reports on each training set of ``bench_hybrid_shift.py`` (issue #24 d).

For every seed and left-out session: ``discover`` on the other seven sessions, printed as one JSON line (``extra_terms``
and the findings' settings). ``score_hybrid_sessions.py --pick`` uses it to score the workflow "discover, then
calibrate with what it found": per session the calibration with the term where discover reported it, without where not.

    python benchmarks/discover_hybrid_sessions.py 0 1 2 ... > LOG
"""
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_hybrid_shift as B  # noqa: E402
import bayesmag  # noqa: E402


def main(argv):
    for seed in [int(x) for x in argv] or [0]:
        d = B.sessions(8, 600, seed)
        for run in range(1, 9):
            t = time.perf_counter()
            res = bayesmag.discover(d.subset(np.flatnonzero(d.run != run)))
            print(json.dumps({"seed": seed, "run": run, "extra_terms": [t["name"] for t in res.extra_terms],
                              "findings": [f["setting"] for f in res.findings],
                              "seconds": round(time.perf_counter() - t, 1)}), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
