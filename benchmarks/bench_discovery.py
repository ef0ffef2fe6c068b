"""Discovery on concealed effects from two generators: hit rate, clean rate, unexplained rate, extras, time.

* ``simulate``: :mod:`bayesmag.simulate`'s Helmholtz campaign, one catalogue effect sized at
  about 3x the calibrated noise (``draw_effect``), a periodic (out of catalogue), or nothing;
* ``independent``: ``tests/independent_campaigns.py``, written apart from simulate (own run
  designs, effects on one sensor channel sized in sensor units, periodic interference and gain
  drift in time out of catalogue, per-run offsets, hysteresis held across run gaps);
* ``chamber``: ``tests/chamber_campaigns.py`` (issue #25), temperature-chamber programmes
  (0.5-2 C/min ramps and holds, heating and cooling) with a first-order or two-node heat path
  of 30-600 s mean delay, or none (clean). ``tau_in_interval``: the planted mean delay lies in
  the finding's 95 % interval of tau.

    python benchmarks/bench_discovery.py --generator all --seeds 20 [--kinds cubic,clean] [--order seed]
        [--jobs 2] [--out bench_discovery.json] [--md bench_discovery.md] [--resume] [--table]

``--generator`` takes one name, a comma list, or ``all`` (simulate, independent, chamber: the
three tables of docs/discovery.md from one command). The JSON (``--out``) holds the summary and
every campaign's row; ``--md`` also writes the per-kind markdown tables (named rate, tau inside its
interval, false findings on clean campaigns, misses and extras listed).

``--jobs N`` runs campaigns in N worker processes, each single-threaded (XLA and OpenBLAS
threads off, set before jax is imported), with the same results as ``--jobs 1`` (discovery is
deterministic given the campaign and its seed). Every finished campaign is appended to
``OUT.rows.jsonl`` at once; ``--resume`` keeps the rows already there (and in OUT) and runs only
the missing (generator, kind, seed) campaigns, so an interrupted run continues where it stopped
and runs over different seeds merge into one summary. ``--table`` prints the per-kind markdown
tables of docs/discovery.md.

Scoring (declared before running; ``score``):
* hit: the planted catalogue effect named on its sensor channel ('all' for thermal lag and
  timing offset, which act on the whole sensor);
* extra: any finding besides that one (campaigns with extra findings are counted);
* clean: no finding and nothing unexplained;
* out of catalogue: reported as unexplained on the planted channel;
* seconds: wall time of ``discover`` on the 5000-row campaign;
* magnitude (independent generator; thermal_lag and run_offset, where the truth is in the
  units discovery reports): |recovered - true| / se for tau (s) and for each run's offset in
  sensor units on the planted channel (a run offset found in the sensor frame on that
  channel); ``magnitude_ok`` when the largest is <= 3.
"""

from __future__ import annotations

import os

# single-threaded numerics (set before jax and numpy load): small solves gain nothing from
# threads, and worker processes of --jobs must not contend; --jobs 1 runs with the same settings
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")

import argparse
import json
import sys
import time

import jax
import numpy as np

import bayesmag  # noqa: F401
from bayesmag._src.pipeline import discover as D
from bayesmag._src.core.catalogue import SIMULATOR_NAMES
from bayesmag.simulate import TrueParams, get_effect, simulate

sys.path.insert(0, str(__import__('pathlib').Path(__file__).resolve().parents[1] / 'tests'))
import independent_campaigns as IC  # noqa: E402  (the independent generator)
import chamber_campaigns as CC  # noqa: E402  (the chamber generator, issue #25)

N_ROWS = 5000
NOISE = 0.5
#: hidden effects peak (98th percentile) at FACTOR x U(0.8, 1.5) x the calibrated noise sd
FACTOR = 3.0
AXES = ("x", "y", "z")
AXIS_FREE = ("thermal_lag", "timing_offset")


def calibrated_noise_sd(clean, axis: int) -> float:
    """Median sd of the reading noise after calibration on output ``axis``, uT (reference units):
    NOISE * |row ``axis`` of S + Ks T|, from the true parameters."""
    p = TrueParams.paper()
    m = p.S[axis] + p.Ks[axis] * np.asarray(clean.temperature)[:, None]
    return float(np.median(NOISE * np.sqrt((m * m).sum(1))))


def calibrated_size(effect, clean, axis: int) -> float:
    """98th percentile of |the effect's contribution to the calibrated RESIDUAL on output ``axis``|, uT.

    The effect is applied to the noise-free reading and both readings are calibrated with the
    TRUE parameters, B_ref = (S + Ks T) B_meas + O + Ko T; the difference on ``axis`` is what
    discovery sees, less the part the thermo-affine fit absorbs (for the y axis, S_yy + Ks_yy T falls from 2.4 to ~0.3
    over the temperature range, so a size in measured units would be misleading)."""
    p = TrueParams.paper()
    b0 = p.measure(clean.b_ref, clean.temperature)
    b1, _ = effect.apply(b0, np.asarray(clean.temperature), np.asarray(clean.time), np.asarray(clean.run),
                         np.asarray(clean.b_ref), jax.random.PRNGKey(0), measure=p.measure)
    d = p.forward(b1, clean.temperature) - p.forward(b0, clean.temperature)
    # what the calibration fit cannot absorb: remove the least-squares projection on the
    # thermo-affine design [B_meas, T B_meas, 1, T] (the baseline model discovery starts from)
    t = np.asarray(clean.temperature)[:, None]
    X = np.concatenate([b0, t * b0, np.ones_like(t), t], axis=1)
    r = d[:, axis] - X @ np.linalg.lstsq(X, d[:, axis], rcond=None)[0]
    return float(np.quantile(np.abs(r), 0.98))


def sized(name: str, clean, k: int, target: float, /, **params):
    """Effect ``name`` with its linear coefficient (the first of ``params``) scaled so that its
    calibrated contribution on output axis ``k`` is ``target`` uT at the 98th percentile."""
    key = next(iter(params))
    unit = get_effect(name, **params)
    scale = target / calibrated_size(unit, clean, k)
    return get_effect(name, **{**params, key: float(params[key] * scale)})


def draw_effect(name: str, rng: np.random.Generator, clean) -> tuple:
    """(effect, output axis or None).

    Linear effects are sized in CALIBRATED (reference) units: their contribution to the
    calibrated output on the concealed axis is FACTOR x U(0.8, 1.5) times the calibrated
    noise sd on that axis at its 98th percentile (hysteresis and periodic: half of that as
    amplitude, so the peak-to-peak swing is the same). thermal_lag: tau 15-60 s;
    timing_offset: |delta| 0.2-1 s (their size follows from the campaign's rates).
    """
    ax = AXES[int(rng.integers(3))]
    k = AXES.index(ax)
    peak = FACTOR * calibrated_noise_sd(clean, k) * rng.uniform(0.8, 1.5)
    sign = float(rng.choice([-1, 1]))
    if name == "axis_quadratic":
        inp = AXES[int(rng.integers(3))]
        return sized(name, clean, k, peak, coeff=sign, out=ax, inp=inp), ax
    if name == "cross_axis_quadratic":
        i, j = [a for a in AXES if a != ax] if rng.random() < 0.5 else (ax, AXES[(k + 1) % 3])
        return sized(name, clean, k, peak, coeff=sign, out=ax, inp1=i, inp2=j), ax
    if name == "cubic":
        return sized(name, clean, k, peak, coeff=-1.0, out=ax, inp=ax), ax
    if name == "temperature_quadratic":
        return sized(name, clean, k, peak, coeff=sign, axis=ax, t_ref=24.0), ax
    if name == "thermal_lag":
        return get_effect(name, tau=float(rng.uniform(15, 60))), None
    if name == "timing_offset":
        return get_effect(name, delta=float(rng.choice([-1, 1]) * rng.uniform(0.2, 1.0))), None
    if name == "hysteresis":
        thr = float(rng.uniform(15, 30))
        return sized(name, clean, k, peak / 2, h=1.0, axis=ax, threshold=thr), ax
    if name == "offset_drift":
        return sized(name, clean, k, peak, rate=sign, axis=ax), ax
    if name == "periodic":
        period = float(rng.uniform(8, 60))
        return sized(name, clean, k, peak / 2, amplitude=1.0, axis=ax, period=period), ax
    raise ValueError(name)


def sim_case(kind: str, seed: int):
    """(data, truth) from :mod:`bayesmag.simulate` (its own campaign design; effects sized in calibrated units)."""
    rng = np.random.default_rng([seed, 7])
    clean = simulate(N_ROWS, design="campaign", seed=seed, noise_sd=NOISE)
    if kind == "clean":
        return clean, {"name": None, "channel": None, "out_of_catalogue": False}
    e, ax = draw_effect(kind, rng, clean)
    data = simulate(N_ROWS, design="campaign", seed=seed, noise_sd=NOISE, effects=[e])
    if kind == "periodic":
        return data, {"name": None, "channel": ax, "out_of_catalogue": True}
    return data, {"name": SIMULATOR_NAMES[kind], "channel": ax or "all", "out_of_catalogue": False}


def indep_case(kind: str, seed: int):
    """(data, truth) from the independent generator tests/independent_campaigns.py."""
    data, p = IC.campaign(kind, seed, n=N_ROWS)
    truth = {"name": p.name, "channel": p.channel, "out_of_catalogue": kind in IC.OUT_OF_CATALOGUE}
    if kind == "thermal_lag":
        truth["tau"] = p.params["tau"]
    if kind == "run_offset":
        truth["run_steps"] = {str(r): v for r, v in enumerate(p.params["steps"])}
    return data, truth


def magnitude(res, truth) -> dict | None:
    """Largest |recovered - true| / se over the planted effect's parameters that have a truth in
    the reported units (tau of a thermal lag, s; each run's offset of a sensor-frame run_offset on
    the planted channel, sensor units: the model's d = o_run is the planted d); None otherwise."""
    zs = {}
    for f in res.findings:
        if "tau" in truth and f["effect"] == "thermal_lag":
            p = f["parameters"]["tau"]
            zs["tau"] = abs(p["value"] - truth["tau"]) / p["se"]
        if "run_steps" in truth and f["effect"] == "run_offset" and f["frame"] == "sensor" \
                and f["channel"] == truth["channel"]:
            for name, p in f["parameters"].items():
                zs[name] = abs(p["value"] - truth["run_steps"][name[2:]]) / p["se"]
    if not zs:
        return None
    worst = max(zs, key=zs.get)
    return {"worst_parameter": worst, "worst_abs_z": float(zs[worst]), "magnitude_ok": bool(zs[worst] <= 3.0)}


def chamber_case(kind: str, seed: int):
    """(data, truth) from the chamber generator tests/chamber_campaigns.py (slow heat paths, 30-600 s)."""
    data, p = CC.campaign(kind, seed, n=N_ROWS)
    truth = {"name": p.name, "channel": p.channel, "out_of_catalogue": False}
    if p.name == "thermal_lag":
        truth["tau"] = p.params["tau"]
        truth["nodes"] = p.params["nodes"]
    return data, truth


SIM_KINDS = ("axis_quadratic", "cross_axis_quadratic", "cubic", "temperature_quadratic", "thermal_lag",
             "timing_offset", "hysteresis", "offset_drift", "periodic", "clean")
GENERATORS = {"simulate": (sim_case, SIM_KINDS), "independent": (indep_case, tuple(IC.KINDS)),
              "chamber": (chamber_case, tuple(CC.KINDS))}


def score(res, truth) -> dict:
    """Declared scoring: hit = the planted catalogue effect named on its sensor channel ('all' for
    whole-sensor effects); extra = any other finding; clean = no finding and nothing unexplained;
    unexplained_ok = an out-of-catalogue effect reported as unexplained on its channel."""
    fs = [(f["effect"], f.get("channel", f["axis"])) for f in res.findings]
    hit = None
    if truth["name"] is not None:
        hit = any(fe == truth["name"] and fc == truth["channel"] for fe, fc in fs)
    n_true = 1 if hit else 0
    extra = len(fs) - n_true
    unexpl = [u.get("channel", u["axis"]) for u in res.unexplained]
    tau_in = None
    if "tau" in truth:
        lag = [f for f in res.findings if f["effect"] == "thermal_lag"]
        iv = lag[0]["parameters"]["tau"].get("interval95") if lag else None
        tau_in = bool(iv and iv[0] <= truth["tau"] <= iv[1]) if hit else False
    return {"findings": [f"{fe}@{fc}" for fe, fc in fs], "unexplained": unexpl, "hit": hit,
            "tau_in_interval": tau_in, "rejected": [x["reason"] for x in getattr(res, "rejected", [])],
            "magnitude": magnitude(res, truth) if hit else None,
            "extra_findings": extra,
            "clean_ok": (not fs and not unexpl) if truth["name"] is None and not truth["out_of_catalogue"] else None,
            "unexplained_ok": (truth["channel"] in unexpl) if truth["out_of_catalogue"] else None}


def run_one(generator: str, kind: str, seed: int) -> dict:
    make, _ = GENERATORS[generator]
    data, truth = make(kind, seed)
    t = time.perf_counter()
    res = D.discover(data, D.DiscoverOptions(figures=False, seed=seed))
    secs = time.perf_counter() - t
    return {"generator": generator, "kind": kind, "seed": seed, "truth": truth, "seconds": secs,
            **score(res, truth)}


def summarise(rows: list) -> dict:
    out = {}
    for g in dict.fromkeys(r["generator"] for r in rows):
        rg = [r for r in rows if r["generator"] == g]
        hits = [r["hit"] for r in rg if r["hit"] is not None]
        clean = [r["clean_ok"] for r in rg if r["clean_ok"] is not None]
        unex = [r["unexplained_ok"] for r in rg if r["unexplained_ok"] is not None]
        out[g] = {"campaigns": len(rg),
                  "right_effect_and_channel": float(np.mean(hits)) if hits else None, "n_planted": len(hits),
                  "clean_no_finding": float(np.mean(clean)) if clean else None, "n_clean": len(clean),
                  "out_of_catalogue_unexplained_on_channel": float(np.mean(unex)) if unex else None,
                  "n_out_of_catalogue": len(unex),
                  "campaigns_with_extra_findings": float(np.mean([r["extra_findings"] > 0 for r in rg])),
                  "median_seconds": float(np.median([r["seconds"] for r in rg])),
                  "max_seconds": float(np.max([r["seconds"] for r in rg])),
                  "per_kind": {k: {"hit": float(np.mean([r["hit"] for r in rg if r["kind"] == k]))
                                   if rg and [r for r in rg if r["kind"] == k][0]["hit"] is not None else None,
                                   "extra": float(np.mean([r["extra_findings"] > 0 for r in rg if r["kind"] == k]))}
                               for k in dict.fromkeys(r["kind"] for r in rg)}}
    return out


def _key(r) -> tuple:
    return (r["generator"], r["kind"], int(r["seed"]))


def _load_rows(out: str) -> dict:
    """Rows already stored for ``out`` (its JSON and its .rows.jsonl; later lines win), by key."""
    rows = {}
    if os.path.exists(out):
        with open(out) as f:
            for r in json.load(f).get("rows", []):
                rows[_key(r)] = r
    if os.path.exists(out + ".rows.jsonl"):
        with open(out + ".rows.jsonl") as f:
            for line in f:
                line = line.strip()
                if line:
                    try:
                        r = json.loads(line)
                    except json.JSONDecodeError:        # a line cut by an interrupt
                        continue
                    rows[_key(r)] = r
    return rows


def _run_key(key):
    return run_one(*key)


def table(rows: list) -> str:
    """Per-kind markdown tables (the ones in docs/discovery.md) and the list of misses and extras."""
    out = []
    for g in dict.fromkeys(r["generator"] for r in rows):
        rg = [r for r in rows if r["generator"] == g]
        seeds = sorted({r["seed"] for r in rg})
        out.append(f"**{g}** ({len(rg)} campaigns, seeds {seeds[0]}-{seeds[-1]})\n")
        out.append("| planted | campaigns | right effect and channel | campaigns with extra findings | "
                   "clean (no finding) / unexplained on its channel | magnitude within 3 se | tau inside its 95 % "
                   "interval | median s | max s |")
        out.append("|---|---|---|---|---|---|---|---|---|")
        for k in dict.fromkeys(r["kind"] for r in rg):
            rk = [r for r in rg if r["kind"] == k]
            hits = [r["hit"] for r in rk if r["hit"] is not None]
            cl = [r["clean_ok"] for r in rk if r["clean_ok"] is not None]
            un = [r["unexplained_ok"] for r in rk if r["unexplained_ok"] is not None]
            mg = [r["magnitude"]["magnitude_ok"] for r in rk if r.get("magnitude")]
            ti = [r["tau_in_interval"] for r in rk if r.get("tau_in_interval") is not None]
            frac = lambda v: f"{sum(v)}/{len(v)}" if v else "–"      # noqa: E731
            ce = frac(cl) if cl else frac(un)
            out.append(f"| {k} | {len(rk)} | {frac(hits)} | {sum(r['extra_findings'] > 0 for r in rk)}/{len(rk)} | "
                       f"{ce} | {frac(mg)} | {frac(ti)} | {np.median([r['seconds'] for r in rk]):.0f} | "
                       f"{np.max([r['seconds'] for r in rk]):.0f} |")
        out.append("")
        for r in rg:
            if r["hit"] is False or r["extra_findings"] > 0 or r["clean_ok"] is False or r["unexplained_ok"] is False:
                out.append(f"- {r['kind']} seed {r['seed']}: findings {r['findings']}, unexplained {r['unexplained']}")
        out.append("")
    return "\n".join(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--generator", default="all", help="simulate, independent, chamber (comma list), or all")
    p.add_argument("--kinds", default=None, help="comma list (default: all kinds of each generator)")
    p.add_argument("--out", default="bench_discovery.json")
    p.add_argument("--jobs", type=int, default=1, help="worker processes, each single-threaded")
    p.add_argument("--resume", action="store_true", help="keep stored rows of OUT and run only missing campaigns")
    p.add_argument("--table", action="store_true", help="print the per-kind markdown tables at the end")
    p.add_argument("--md", default=None, help="also write the per-kind markdown tables to this file")
    p.add_argument("--order", choices=("kind", "seed"), default="kind",
                   help="run order: every seed of a kind in turn (kind), or seed 0 of every kind first (seed: an "
                        "interrupted run then has the same seeds for every kind)")
    a = p.parse_args(argv)
    if a.jobs < 1:
        p.error(f"--jobs is {a.jobs}; it must be >= 1.")
    todo = []
    gens = ["chamber", "independent", "simulate"] if a.generator == "all" else a.generator.split(",")
    for g in gens:
        if g not in GENERATORS:
            p.error(f"--generator {g!r} is not one of {sorted(GENERATORS)}.")
        kinds = [k for k in a.kinds.split(",") if k in GENERATORS[g][1]] if a.kinds else GENERATORS[g][1]
        for kind in kinds:
            todo += [(g, kind, seed) for seed in range(a.first_seed, a.first_seed + a.seeds)]
    if a.kinds:
        unknown = [k for k in a.kinds.split(",") if not any(k in GENERATORS[g][1] for g in gens)]
        if unknown:
            p.error(f"--kinds {','.join(unknown)}: no such kind in {', '.join(gens)}.")
    stored = _load_rows(a.out) if a.resume else {}
    if not a.resume and os.path.exists(a.out + ".rows.jsonl"):
        os.remove(a.out + ".rows.jsonl")
    todo = [k for k in todo if k not in stored]
    if a.order == "seed":
        todo.sort(key=lambda k: k[2])        # stable: generator and kind order kept within a seed
    if stored:
        print(f"resuming: {len(stored)} campaigns stored, {len(todo)} to run", file=sys.stderr)
    rows = dict(stored)
    keys = ("generator", "kind", "seed", "findings", "unexplained", "hit", "extra_findings", "magnitude", "tau_in_interval",
            "seconds")
    with open(a.out + ".rows.jsonl", "a") as sink:
        def done(r):
            rows[_key(r)] = r
            sink.write(json.dumps(r, default=str) + "\n")
            sink.flush()
            print(json.dumps({k: r[k] for k in keys}), flush=True)
        if a.jobs == 1:
            for key in todo:
                done(run_one(*key))
        else:
            import concurrent.futures as cf
            import multiprocessing as mp
            # spawn: fresh interpreters import this module, so the thread settings above apply before jax loads
            with cf.ProcessPoolExecutor(a.jobs, mp_context=mp.get_context("spawn")) as ex:
                for fut in cf.as_completed([ex.submit(_run_key, k) for k in todo]):
                    done(fut.result())
    order = sorted(rows.values(), key=lambda r: (r["generator"], list(GENERATORS[r["generator"]][1]).index(r["kind"])
                                                 if r["kind"] in GENERATORS[r["generator"]][1] else 99, r["seed"]))
    summary = summarise(order)
    print(json.dumps(summary, indent=1))
    if a.table:
        print(table(order))
    if a.md:
        with open(a.md + ".tmp", "w") as f:
            f.write(table(order) + "\n")
        os.replace(a.md + ".tmp", a.md)
    tmp = a.out + ".tmp"
    with open(tmp, "w") as f:
        json.dump({"summary": summary, "rows": order}, f, indent=1, default=str)
    os.replace(tmp, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
