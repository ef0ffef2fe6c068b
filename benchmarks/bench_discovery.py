"""Hit rate, false-discovery rate and parameter recovery of `discover` on concealed simulated effects.

Each case hides one catalogue effect (random axis, magnitude a few times the noise after
calibration), a non-catalogue effect (periodic), two effects at once, or nothing, in a
5000-row Helmholtz campaign, then runs discovery blind.

    python benchmarks/bench_discovery.py --seeds 5 [--effects cubic,hysteresis] [--out bench_discovery.json]

Scoring (declared before running):
* hit: the right catalogue effect named on the right output axis (axis-free effects
  thermal_lag / timing_offset: on any axis);
* false discovery: a finding whose effect is not among the concealed ones (secondary-axis
  findings of a concealed effect leak through S's off-diagonal terms and are not false);
* recovery: |estimate - truth| <= 2 reported SE, truth = the parameter fitted with the same
  structure on the noise-free recording (pseudo-true; tau and delta: the simulated value);
* clean: no finding and nothing unexplained.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

import bayesmag  # noqa: F401
from bayesmag._src import discover as D
from bayesmag._src.catalogue import SIMULATOR_NAMES
from bayesmag.simulate import get_effect, simulate

N_ROWS = 5000
NOISE = 0.5
AXES = ("x", "y", "z")
AXIS_FREE = ("thermal_lag", "timing_offset")


def draw_effect(name: str, rng: np.random.Generator, clean) -> tuple:
    """(effect, output axis or None): a magnitude ~3x the reading noise at the 98th percentile."""
    ax = AXES[int(rng.integers(3))]
    k = AXES.index(ax)
    b = np.abs(clean.b_meas)
    peak = 3 * NOISE * rng.uniform(0.8, 1.5)
    if name == "axis_quadratic":
        inp = AXES[int(rng.integers(3))]
        q = np.quantile(b[:, AXES.index(inp)], 0.98)
        return get_effect(name, out=ax, inp=inp, coeff=float(peak / q**2 * rng.choice([-1, 1]))), ax
    if name == "cross_axis_quadratic":
        i, j = [a for a in AXES if a != ax] if rng.random() < 0.5 else (ax, AXES[(k + 1) % 3])
        q = np.quantile(b[:, AXES.index(i)] * b[:, AXES.index(j)], 0.98)
        return get_effect(name, out=ax, inp1=i, inp2=j, coeff=float(peak / q * rng.choice([-1, 1]))), ax
    if name == "cubic":
        q = np.quantile(b[:, k], 0.98)
        return get_effect(name, out=ax, inp=ax, coeff=float(-peak / q**3)), ax
    if name == "temperature_quadratic":
        q = np.quantile((clean.temperature - 24.0) ** 2, 0.98)
        return get_effect(name, axis=ax, coeff=float(peak / q * rng.choice([-1, 1])), t_ref=24.0), ax
    if name == "thermal_lag":
        return get_effect(name, tau=float(rng.uniform(15, 60))), None
    if name == "timing_offset":
        return get_effect(name, delta=float(rng.choice([-1, 1]) * rng.uniform(0.2, 1.0))), None
    if name == "hysteresis":
        return get_effect(name, axis=ax, h=float(peak / 2), threshold=float(rng.uniform(15, 30))), ax
    if name == "offset_drift":
        span = clean.time[-1] - clean.time[0]
        return get_effect(name, axis=ax, rate=float(peak / span * rng.choice([-1, 1]))), ax
    if name == "periodic":
        return get_effect(name, axis=ax, amplitude=float(peak / 2), period=float(rng.uniform(8, 60))), ax
    raise ValueError(name)


def pseudo_truth(finding, data_clean_effects, options):
    """The finding's parameters fitted (same structure) on the noise-free recording."""
    f = finding
    if f["effect"] == "thermal_lag" or f["effect"] == "timing_offset":
        return None
    res = D.discover(data_clean_effects, dataclasses_replace(options, candidates=(f["effect"],)))
    for g in res.findings:
        if g["axis"] == f["axis"] and g["effect"] == f["effect"]:
            return {k: v["value"] for k, v in g["parameters"].items()}
    return None


def dataclasses_replace(o, **kw):
    import dataclasses
    return dataclasses.replace(o, **kw)


def run_case(kind: str, seed: int) -> dict:
    rng = np.random.default_rng([seed, 7])
    clean = simulate(N_ROWS, design="campaign", seed=seed, noise_sd=NOISE)
    truth = []
    if kind == "clean":
        effects = []
    elif kind == "two":
        names = rng.choice(["axis_quadratic", "cubic", "thermal_lag", "hysteresis", "offset_drift",
                            "cross_axis_quadratic"], size=2, replace=False)
        effects = []
        for n in names:
            e, ax = draw_effect(str(n), rng, clean)
            effects.append(e)
            truth.append((SIMULATOR_NAMES[str(n)], ax, e))
        effects.sort(key=lambda e: e.name not in AXIS_FREE)     # re-measuring effects first
    else:
        e, ax = draw_effect(kind, rng, clean)
        effects = [e]
        truth.append((SIMULATOR_NAMES.get(kind, kind), ax, e))
    data = simulate(N_ROWS, design="campaign", seed=seed, noise_sd=NOISE, effects=effects)
    t = time.perf_counter()
    opts = D.DiscoverOptions(figures=False, seed=seed)
    res = D.discover(data, opts)
    secs = time.perf_counter() - t
    named = {(f["effect"], f["axis"]) for f in res.findings}
    true_names = {n for n, _, _ in truth}
    hits, recov = [], []
    for n, ax, e in truth:
        if n == "periodic":
            continue
        ok = any(fe == n and (ax is None or fa == ax) for fe, fa in named)
        hits.append(ok)
        # recovery on the main axis
        for f in res.findings:
            if f["effect"] != n or (ax is not None and f["axis"] != ax):
                continue
            if n == "thermal_lag":
                p = f["parameters"]["tau"]
                recov.append(abs(p["value"] - e.tau) <= 2 * p["se"])
            elif n == "timing_offset":
                p = f["parameters"]["delta"]
                recov.append(abs(p["value"] - e.delta) <= 2 * p["se"])
            else:
                noiseless = simulate(N_ROWS, design="campaign", seed=seed, noise_sd=0.0, effects=effects)
                ref = D.discover(noiseless, dataclasses_replace(opts, candidates=(n,), max_terms=1))
                g = next((g for g in ref.findings if g["axis"] == f["axis"] and g["effect"] == n
                          and g["setting"] == f["setting"]), None)
                if g is not None:
                    big = max(f["parameters"], key=lambda k: abs(f["parameters"][k]["value"]) / max(f["parameters"][k]["se"], 1e-300))
                    recov.append(abs(f["parameters"][big]["value"] - g["parameters"][big]["value"])
                                 <= 2 * f["parameters"][big]["se"])
            break
    false = [f"{fe}@{fa}" for fe, fa in named if fe not in true_names]
    periodic_reported = any("periodic" in u["where"] for u in res.unexplained)
    return {"kind": kind, "seed": seed, "truth": [(n, ax, e.describe()) for n, ax, e in truth],
            "findings": sorted(f"{fe}@{fa}" for fe, fa in named), "hits": hits, "recovered": recov,
            "false": false, "unexplained": [f"{u['axis']}: {u['where']}" for u in res.unexplained],
            "periodic_reported": periodic_reported, "no_missing_physics": res.no_missing_physics,
            "seconds": secs}


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--effects", default="axis_quadratic,cross_axis_quadratic,cubic,temperature_quadratic,"
                                        "thermal_lag,timing_offset,hysteresis,offset_drift,periodic,two,clean")
    p.add_argument("--out", default="bench_discovery.json")
    a = p.parse_args(argv)
    rows = []
    for kind in a.effects.split(","):
        for seed in range(a.first_seed, a.first_seed + a.seeds):
            r = run_case(kind, seed)
            rows.append(r)
            print(json.dumps({k: r[k] for k in ("kind", "seed", "findings", "hits", "recovered", "false",
                                                "unexplained", "seconds")}), flush=True)
    summary = {}
    for kind in dict.fromkeys(r["kind"] for r in rows):
        rs = [r for r in rows if r["kind"] == kind]
        hits = [h for r in rs for h in r["hits"]]
        rec = [x for r in rs for x in r["recovered"]]
        summary[kind] = {
            "seeds": len(rs),
            "hit_rate": float(np.mean(hits)) if hits else None,
            "recovered_within_2se": float(np.mean(rec)) if rec else None,
            "cases_with_false_discovery": float(np.mean([bool(r["false"]) for r in rs])),
            "clean_no_missing_physics": float(np.mean([r["no_missing_physics"] for r in rs])),
            "periodic_reported_unexplained": float(np.mean([r["periodic_reported"] for r in rs])),
            "median_seconds": float(np.median([r["seconds"] for r in rs])),
        }
    print(json.dumps(summary, indent=1))
    with open(a.out, "w") as f:
        json.dump({"summary": summary, "rows": rows}, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
