"""Score the hybrid's new-session transfer variants on cached calibrations (issue #24 d; offline, seconds per session).

Reads the pickles of ``benchmarks/cache_hybrid_sessions.py DIR SEEDS --folds`` (one calibration per left-out session
of ``bench_hybrid_shift.py``, by-run fold networks included) and predicts each left-out session with the same
hybrid predictor carrying one of these transfer parts:

* ``loro`` / ``loro+net``: the leave-one-run-out physics transfer sd, without / with the fold networks' ``tau_n``;
* ``hier`` / ``hier+net``: the physics session model (fitted on the physics residuals), without / with ``tau_n``;
* ``oof``: the session model fitted on the out-of-fold hybrid residuals (what ``transfer_networks = "by_run_folds"``
  saves with the hierarchical transfer);
* ``shared`` / ``shared+net``: the physics session model with the calibrated network's in-sample correction, each
  run's mean taken out, as a column with one coefficient shared by all runs (``fit_sessions(shared=...)``: the
  distortion every session shares is fitted as such, not read as session change), without / with ``tau_n``.

Printed per session: covered-or-flagged share and in-domain mean 95 % width per axis; then per variant the
session-axes under 95 %, and the width / loro's where loro covers or flags >= 95 % (median, largest, count over 1.5x).

``--base DIR2``: also score loro from the pickles of the same sessions in ``DIR2`` (``loro_base``, e.g. the affine
physics model when ``DIR`` was cached with ``--extra``), and take the width ratios over that. ``--pick LOG`` (with
``--base``): per session, the calibration of ``DIR`` only where ``discover_hybrid_sessions.py``'s LOG lists an extra
term for that training set, else ``DIR2``'s (the workflow "discover, then calibrate with what it found").

    python benchmarks/score_hybrid_sessions.py DIR [VARIANT,VARIANT,...] [--base DIR2 [--pick LOG]]
"""
import json
import dataclasses
import pickle
import sys
import time
from pathlib import Path

import numpy as np

from bayesmag._src.core.predictor import estimate_transfer
from bayesmag._src.pipeline.sessions import hierarchical as H

VARIANTS = ("loro", "loro+net", "hier", "hier+net", "oof", "shared", "shared+net")


def run_centred(v: np.ndarray, run: np.ndarray) -> np.ndarray:
    """``v`` less each run's mean of it (rows of ``run``)."""
    out = np.array(v, np.float64)
    for r in np.unique(run):
        m = run == r
        out[m] -= out[m].mean(0)
    return out


def predictors(d: dict, wanted) -> dict:
    train, fit, hyb, nt = d["train"], d["fit"], d["hybrid"], d["network_transfer"]
    base = dataclasses.replace(hyb, network_transfer_sd=None)
    out = {}
    loro = estimate_transfer(train, fit).sd
    if "loro" in wanted or "loro+net" in wanted:
        out["loro"] = dataclasses.replace(base, sessions=None, transfer_sd=loro)
        out["loro+net"] = dataclasses.replace(out["loro"], network_transfer_sd=nt.sd)
    out["hier"] = dataclasses.replace(base, sessions=d["physics_sessions"])
    out["hier+net"] = dataclasses.replace(out["hier"], network_transfer_sd=nt.sd)
    out["oof"] = hyb
    if "shared" in wanted or "shared+net" in wanted:
        post = H.fit_sessions(train, fit, level=0.95, seed=0, shared=run_centred(d["nn"], train.run).T[:, :, None])
        out["shared"] = dataclasses.replace(base, sessions=post)
        out["shared+net"] = dataclasses.replace(out["shared"], network_transfer_sd=nt.sd)
    return {k: v for k, v in out.items() if k in wanted}


def score(pr, test) -> tuple[np.ndarray, np.ndarray]:
    p = pr.predict(test)
    lo, hi = p.interval(0.95)
    cov = (test.b_ref >= lo) & (test.b_ref <= hi)
    ind = np.asarray(p.in_domain, bool)
    return (cov | ~ind[:, None]).mean(0), (hi - lo)[ind].mean(0)


def main(argv) -> int:
    base = pick = None
    if "--base" in argv:
        i = argv.index("--base")
        base, argv = Path(argv[i + 1]), argv[:i] + argv[i + 2:]
    if "--pick" in argv:
        i = argv.index("--pick")
        pick = {(r["seed"], r["run"]): bool(r["extra_terms"] and set(r["extra_terms"]) - {"run_offset"})
                for r in map(json.loads, Path(argv[i + 1]).read_text().splitlines())}
        argv = argv[:i] + argv[i + 2:]
    folder = Path(argv[0])
    wanted = tuple(argv[1].split(",")) if len(argv) > 1 else VARIANTS
    wanted = tuple(dict.fromkeys(("loro",) + wanted))
    files = sorted(folder.glob("seed*_run*.pkl"), key=lambda p: tuple(int(x) for x in p.stem[4:].split("_run")))
    agg = {}
    for f in files:
        t = time.perf_counter()
        key = tuple(int(x) for x in f.stem[4:].split("_run"))
        if pick is not None and key not in pick:
            continue
        d = pickle.load(open(f, "rb"))
        if base is not None:
            b = pickle.load(open(base / f.name, "rb"))
            if pick is not None and not pick[key]:
                d = b
        res = {k: score(pr, d["test"]) for k, pr in predictors(d, wanted).items()}
        if base is not None:
            res = {"loro_base": score(predictors(b, ("loro",))["loro"], b["test"]), **res}
        for k, v in res.items():
            agg.setdefault(k, []).append(v)
        print(f.stem, " | ".join(f"{k}: fc {np.round(100 * v[0], 1)} w {np.round(v[1], 3)}" for k, v in res.items()),
              f"({time.perf_counter() - t:.0f}s)", flush=True)
    ref = "loro_base" if base is not None else "loro"
    covers = np.array([v[0] for v in agg[ref]]) >= 0.95
    wl = np.array([v[1] for v in agg[ref]])
    print(f"\n{len(agg[ref])} sessions; width ratio over {ref}'s on the session-axes it covers or flags >= 95 % "
          f"({covers.sum(0).tolist()} per axis)\n")
    print("| transfer | under 95 % x / y / z | mean covered or flagged (%) | width / loro's, median | largest | over 1.5x |")
    print("|---|---|---|---|---|---|")
    fmt = lambda v, n=2: " / ".join(f"{x:.{n}f}" for x in v)  # noqa: E731
    for k, vs in agg.items():
        fc, w = np.array([v[0] for v in vs]), np.array([v[1] for v in vs])
        r = [(w / wl)[covers[:, a], a] for a in range(3)]
        print(f"| {k} | {' / '.join(str(int(x)) for x in (fc < 0.95).sum(0))} | {fmt(100 * fc.mean(0), 1)} | "
              f"{fmt([np.median(x) for x in r])} | {fmt([x.max() for x in r])} | "
              f"{' / '.join(str(int((x > 1.5).sum())) for x in r)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
