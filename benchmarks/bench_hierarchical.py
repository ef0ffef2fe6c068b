"""Benchmark: the hierarchical session model (``[uq] transfer = "hierarchical"``) against leave-one-run-out.

Run:
  python benchmarks/bench_hierarchical.py generators [--draws 30] [--sessions 40] [--generator gauss ...]
  python benchmarks/bench_hierarchical.py belsten        # leave one Belsten run out, physics stage
  python benchmarks/bench_hierarchical.py pooling [--draws 3]   # complete / no / partial pooling, LORO elpd

``generators``: bench_transfer.py's five session generators plus three written for issue 24
(``heavy``: offsets Student-t with 2.5 dof scaled to sd 0.3 uT; ``temp_drift``: every session its own
thermal offset slope Ko ~ N(0, 0.01) uT/C besides small offsets, so the shift drifts with temperature;
``correlated``: offsets N(0, 0.3) uT with correlation 0.8 between the axes). For every training draw
(30 sessions of 100 rows, seeds as bench_transfer) one physics fit, then the transfer by
leave-one-run-out (today's ``loro``) and by the hierarchical model (Laplace), both applied to the draw's
own ``sessions`` fresh new sessions: per axis, the share of rows covered or flagged out of domain
(mean over draws, 10th percentile over draws, draws under 95 %) and the mean width of the in-domain 95 %
intervals, and the width ratio hierarchical / loro on the rows loro already covers.

``belsten``: each of the six runs left out; physics fit and transfer on the other five (loro and
hierarchical), the left-out run predicted as a new session: covered or flagged per run and axis.

``pooling``: complete pooling (no random effects), no pooling (free per-session effects, a new session
predicted by the training sessions' effects) and partial pooling (the hierarchical model) by exact
leave-one-run-out log predictive density of each run's rows jointly (AR(1) within the run), fed to
``arviz.compare`` as ELPDData with one observation per run.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_transfer import GENERATORS as BASE  # noqa: E402
from test_transfer import _calibrate, _new_sessions, _session, _shifted_params  # noqa: E402

import bayesmag  # noqa: E402
from bayesmag._src.core.simulate import TrueParams  # noqa: E402
from bayesmag._src.pipeline.sessions import hierarchical as H  # noqa: E402


def _heavy(rng):
    return _shifted_params(rng, lambda g: 0.3 * g.standard_t(2.5, 3) / np.sqrt(2.5 / 0.5))


def _temp_drift(rng):
    p = _shifted_params(rng, lambda g: g.normal(0, 0.05, 3), 0.001)
    return TrueParams(p.S, p.Ks, p.O, p.Ko + rng.normal(0, 0.01, 3))


def _correlated(rng):
    c = 0.8 * np.ones((3, 3)) + 0.2 * np.eye(3)
    return _shifted_params(rng, lambda g: g.multivariate_normal(np.zeros(3), 0.09 * c))


GENERATORS = {**BASE, "heavy": _heavy, "temp_drift": _temp_drift, "correlated": _correlated}


def _scores(pr, news):
    cov, dom, width = [], [], []
    for new in news:
        p = pr.predict(new)
        lo, hi = p.interval(0.95)
        cov.append((new.b_ref >= lo) & (new.b_ref <= hi))
        dom.append(p.in_domain)
        width.append(hi - lo)
    return np.concatenate(cov), np.concatenate(dom), np.concatenate(width)


def generators(args):
    """Per training draw one ``DRAW {json}`` line (covered or flagged, widths, width ratio, importance ESS, fit
    time), then the table; ``summarise`` rebuilds the table from such lines (draws split over processes)."""
    f = lambda v: " / ".join(f"{100 * x:.1f}" for x in v)   # noqa: E731
    recs = []
    for name in args.generator:
        gen = GENERATORS[name]
        for draw in range(args.first_draw, args.first_draw + args.draws):
            train = _session(draw, args.runs, rows=100, session_params=gen)
            pr = _calibrate(train)
            t = time.perf_counter()
            post = H.fit_sessions(train, pr.fit, seed=draw, likelihood=args.likelihood, df=args.df,
                                  importance=args.laplace_draws == "importance")
            secs = time.perf_counter() - t
            ph = dataclasses.replace(pr, transfer_sd=None, sessions=post)
            news = _new_sessions(draw, args.sessions, gen)
            rec = {"generator": name, "draw": draw, "fit_s": round(secs, 2), "ess": [round(e, 1) for e in post.ess]}
            for key, p in (("loro", pr), ("hier", ph)):
                c, d, w = _scores(p, news)
                rec[f"ok_{key}"] = (c | ~d[:, None]).mean(0).tolist()
                rec[f"width_{key}"] = w[d].mean(0).tolist()
                if key == "loro":
                    c_loro, w_loro = c, w
                else:
                    # mean width on the rows loro's intervals cover (in domain or not), hierarchical / loro
                    rec["ratio"] = [float(np.mean(w[c_loro[:, a], a]) / np.mean(w_loro[c_loro[:, a], a]))
                                    for a in range(3)]
            print("DRAW " + json.dumps(rec), flush=True)
            print(f"{name} draw {draw}: covered or flagged loro {f(rec['ok_loro'])}, hierarchical {f(rec['ok_hier'])}; "
                  f"width ratio {' / '.join(f'{v:.2f}' for v in rec['ratio'])}; fit {secs:.2f} s", flush=True)
            recs.append(rec)
    _table(recs, f"{args.draws} training draws x {args.sessions} new sessions")


def _table(recs, title):
    """The generator table of ``DRAW`` records: per generator and transfer, per axis x / y / z."""
    f = lambda v: " / ".join(f"{100 * x:.1f}" for x in v)   # noqa: E731
    print(f"\n### {title} (x / y / z)\n")
    print("| generator | draws | transfer | covered or flagged, mean (%) | sd over draws (%) | 10th percentile over "
          "draws (%) | draws under 95 % | mean in-domain width (uT) | width / loro's where loro covers: rows "
          "| same, draws where loro >= 95 % | importance ESS, min over draws |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name in dict.fromkeys(r["generator"] for r in recs):
        rs = sorted({r["draw"]: r for r in recs if r["generator"] == name}.values(), key=lambda r: r["draw"])
        ratio = np.array([r["ratio"] for r in rs])
        ok_l = np.array([r["ok_loro"] for r in rs])
        wl, wh = np.array([r["width_loro"] for r in rs]), np.array([r["width_hier"] for r in rs])
        good = ok_l >= 0.95
        by_draw = " / ".join(f"{np.mean(wh[good[:, a], a]) / np.mean(wl[good[:, a], a]):.2f}" if good[:, a].any()
                             else "-" for a in range(3))
        ess = np.array([r["ess"] for r in rs if r["ess"]])
        for key in ("loro", "hier"):
            o, w = np.array([r[f"ok_{key}"] for r in rs]), np.array([r[f"width_{key}"] for r in rs])
            hier = key == "hier"
            print(f"| {name} | {len(rs)} | {key} | {f(o.mean(0))} | {f(o.std(0, ddof=1)) if len(rs) > 1 else '-'} | "
                  f"{f(np.percentile(o, 10, axis=0))} | {' / '.join(map(str, (o < 0.95).sum(0)))} | "
                  f"{' / '.join(f'{v:.3f}' for v in w.mean(0))} | "
                  f"{' / '.join(f'{v:.2f}' for v in ratio.mean(0)) if hier else '1'} | {by_draw if hier else '1'} | "
                  f"{' / '.join(f'{v:.0f}' for v in ess.min(0)) if hier and ess.size else '-'} |")


def summarise(args):
    """The generator table rebuilt from the ``DRAW`` lines of benchmark logs (``--logs``)."""
    recs = []
    for path in args.logs:
        recs += [json.loads(line[5:]) for line in Path(path).read_text().splitlines() if line.startswith("DRAW ")]
    if args.generator != list(GENERATORS):
        recs = [r for r in recs if r["generator"] in args.generator]
    order = {g: i for i, g in enumerate(GENERATORS)}
    recs.sort(key=lambda r: (order[r["generator"]], r["draw"]))
    _table(recs, f"from {len(args.logs)} logs, {len(recs)} generator-draws x {args.sessions} new sessions")


def belsten(args):
    from bayesmag._src.core.datasets import load_dataset
    from bayesmag._src.core.domain import Domain
    from bayesmag._src.core.predictor import Predictor, UQOptions, estimate_transfer

    d = load_dataset("belsten2023")
    sigma_in = bayesmag.estimate_input_noise(d) if hasattr(bayesmag, "estimate_input_noise") else None
    f = lambda v: " / ".join(f"{100 * x:.0f}" for x in v)   # noqa: E731
    print("| left-out run | in-domain rows | transfer | covered x / y / z (%) | covered or flagged x / y / z (%) | "
          "mean in-domain 95 % width (uT) | effects |")
    print("|---|---|---|---|---|---|---|")
    for r in np.unique(d.run):
        train, test = d.subset(np.flatnonzero(d.run != r)), d.subset(np.flatnonzero(d.run == r))
        model = bayesmag.PhysicsModel.paper(t0=0.0)
        fit = bayesmag.fit_physics(train, model)
        from bayesmag._src.app.job import _residual_variance

        class _Cfg:
            class uq:
                method, n_params, n_qmc, seed, chunk_size = "analytic", 50, 64, 0, 256
        sin = sigma_in if sigma_in is not None else np.diag([0.02**2] * 3 + [1e-4])
        base = Predictor(fit=fit, sigma_in=sin, residual_sd=np.sqrt(_residual_variance(_Cfg, fit, train, sin)),
                         domain=Domain.from_data(train), uq=UQOptions(method="analytic"))
        post = H.fit_sessions(train, fit)
        for key, pr in (("loro", dataclasses.replace(base, transfer_sd=estimate_transfer(train, fit).sd)),
                        ("hierarchical", dataclasses.replace(base, sessions=post))):
            p = pr.predict(test)
            lo, hi = p.interval(0.95)
            c = (test.b_ref >= lo) & (test.b_ref <= hi)
            dom = p.in_domain
            w = (hi - lo)[dom].mean(0) if dom.any() else np.full(3, np.nan)
            print(f"| {r} | {int(dom.sum())} of {test.n} | {key} | {f(c.mean(0))} | {f((c | ~dom[:, None]).mean(0))} | "
                  f"{' / '.join(f'{v:.3f}' for v in w)} | {', '.join(post.effects) if key != 'loro' else '-'} |",
                  flush=True)


def pooling(args):
    import warnings

    from bayesmag._src.pipeline.nuts.idata import arviz
    az = arviz()
    cases = [("belsten", None)] + [(f"gauss draw {k}", k) for k in range(args.draws)]
    for label, k in cases:
        if k is None:
            from bayesmag._src.core.datasets import load_dataset
            d = load_dataset("belsten2023")
            model = bayesmag.PhysicsModel.paper(t0=0.0)
        else:
            d = _session(k, 12, rows=100)
            model = bayesmag.PhysicsModel.paper(t0=float(np.mean(d.temperature)))
        fit = bayesmag.fit_physics(d, model)
        eff, _ = H.select_effects(d, fit)
        st = H.run_stats(d, fit, eff)
        elpd = {m: H.loro_elpd(st, model.param_names, pooling=m) for m in ("complete", "none", "partial")}
        print(f"\n### {label}: {st.n.size} runs, random effects {list(eff)}\n")
        print("LORO log predictive density per run (x | y | z):\n")
        for m, v in elpd.items():
            print(f"- {m}: " + " | ".join(" ".join(f"{x:.1f}" for x in v[:, a]) for a in range(3)))
        print()
        for a, ax in enumerate("xyz"):
            comp = {}
            import xarray as xr
            for m, v in elpd.items():
                li = xr.DataArray(v[:, a], dims=["run"])
                comp[m] = az.ELPDData(data=[float(li.sum()), float(np.sqrt(li.size * np.var(li.values))), 0.0, 1,
                                            li.size, False, li, xr.zeros_like(li), "log"],
                                      index=["elpd_loo", "se", "p_loo", "n_samples", "n_data_points", "warning",
                                             "loo_i", "pareto_k", "scale"])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                table = az.compare(comp, ic="loo", method="stacking")
            print(f"axis {ax}:\n")
            print(table[["rank", "elpd_loo", "elpd_diff", "weight", "se", "dse"]].round(2).to_string())
            print()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=["generators", "belsten", "pooling", "summarise"])
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--first-draw", type=int, default=0, help="generators: training draws first..first+draws-1")
    ap.add_argument("--logs", nargs="*", default=[], help="summarise: logs holding DRAW lines")
    ap.add_argument("--sessions", type=int, default=40)
    ap.add_argument("--runs", type=int, default=30)
    ap.add_argument("--generator", nargs="+", default=list(GENERATORS), choices=sorted(GENERATORS))
    ap.add_argument("--likelihood", default="gaussian", choices=list(H.LIKELIHOODS), help="hierarchical model's likelihood")
    ap.add_argument("--df", type=float, default=4.0, help="its Student-t dof")
    ap.add_argument("--laplace-draws", default="importance", choices=["importance", "gaussian"],
                    help="Laplace path: draws corrected to the exact posterior (default) or the Gaussian's own")
    args = ap.parse_args()
    print(f"## `python benchmarks/bench_hierarchical.py {' '.join(sys.argv[1:])}`\n")
    {"generators": generators, "belsten": belsten, "pooling": pooling, "summarise": summarise}[args.what](args)


if __name__ == "__main__":
    main()
