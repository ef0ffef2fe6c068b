"""Benchmark: the hierarchical session model (``[uq] transfer = "hierarchical"``) against leave-one-run-out.

Run:
  python benchmarks/bench_hierarchical.py generators [--draws 30] [--sessions 40] [--generator gauss ...]
  python benchmarks/bench_hierarchical.py belsten        # leave one Belsten run out, physics stage
  python benchmarks/bench_hierarchical.py pooling [--draws 3]   # complete / no / partial pooling, LORO elpd
  python benchmarks/bench_hierarchical.py belsten_tau [--run 3 --axis y]   # the offset sd's posterior, by grid
  python benchmarks/bench_hierarchical.py summarise --logs LOG ...        # generator table from DRAW lines

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
``--within-uninformed shared`` (generators, belsten, belsten_tau): the model before the uninformed candidates'
within-run variation was decoupled (``fit_sessions(within_uninformed=False)``); ``--weak off`` (generators, belsten):
the model before the runs' noise-only directions were decoupled (``fit_sessions(weak=None)``).

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
from helpers import tau_grid_log_marginal  # noqa: E402

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
                                  importance=args.laplace_draws == "importance", mode_search=args.mode_search,
                                  within_uninformed=args.within_uninformed == "free", weak=args.weak)
            secs = time.perf_counter() - t
            ph = dataclasses.replace(pr, transfer_sd=None, sessions=post)
            news = _new_sessions(draw, args.sessions, gen)
            rec = {"generator": name, "draw": draw, "fit_s": round(secs, 2), "ess": [round(e, 1) for e in post.ess]}
            if post.df_grid:       # learned dof: its posterior per axis on the grid
                rec["df_grid"] = [g if np.isfinite(g) else None for g in post.df_grid]
                rec["df_weight"] = np.round(post.df_weight, 6).tolist()
            # the job's transfer_check = "loro": an axis whose rms transfer sd over the training rows is > 2x loro's
            # and the residual sd takes loro's constant sd; scored only where it engages (else the hier figures)
            rms = np.sqrt(np.mean(post.transfer_sd_for(pr.fit, train) ** 2, axis=0))
            warned = H.misfit_axes(rms, pr.transfer_sd, pr.fit.s2)
            rec["checked"] = [bool(v) for v in warned]
            pairs = [("loro", pr), ("hier", ph)]
            if warned.any():
                fb = tuple(float(v) for v in np.where(warned, pr.transfer_sd, np.nan))
                pairs.append(("chk", dataclasses.replace(ph, sessions=dataclasses.replace(post, fallback_sd=fb))))
            for key, p in pairs:
                c, d, w = _scores(p, news)
                rec[f"ok_{key}"] = (c | ~d[:, None]).mean(0).tolist()
                rec[f"width_{key}"] = w[d].mean(0).tolist()
                if key == "loro":
                    c_loro, w_loro = c, w
                else:
                    # mean width on the rows loro's intervals cover (in domain or not), hierarchical / loro
                    rec["ratio" if key == "hier" else "ratio_chk"] = [
                        float(np.mean(w[c_loro[:, a], a]) / np.mean(w_loro[c_loro[:, a], a])) for a in range(3)]
            if not warned.any():
                rec.update(ok_chk=rec["ok_hier"], width_chk=rec["width_hier"], ratio_chk=rec["ratio"])
            print("DRAW " + json.dumps(rec), flush=True)
            print(f"{name} draw {draw}: covered or flagged loro {f(rec['ok_loro'])}, hierarchical {f(rec['ok_hier'])}; "
                  f"width ratio {' / '.join(f'{v:.2f}' for v in rec['ratio'])}; fit {secs:.2f} s", flush=True)
            recs.append(rec)
    _table(recs, f"{args.draws} training draws x {args.sessions} new sessions")
    _df_table(recs)


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
        keys = ("loro", "hier") + (("chk",) if all("ok_chk" in r for r in rs) else ())
        for key in keys:
            o, w = np.array([r[f"ok_{key}"] for r in rs]), np.array([r[f"width_{key}"] for r in rs])
            hier = key != "loro"
            if key == "chk":       # hierarchical with the job's check against loro (transfer_check = "loro")
                ratio = np.array([r["ratio_chk"] for r in rs])
                by_draw = " / ".join(f"{np.mean(w[good[:, a], a]) / np.mean(wl[good[:, a], a]):.2f}"
                                     if good[:, a].any() else "-" for a in range(3))
                key = f"hier, checked ({' / '.join(str(int(v)) for v in np.sum([r['checked'] for r in rs], 0))} draws)"
            print(f"| {name} | {len(rs)} | {key} | {f(o.mean(0))} | {f(o.std(0, ddof=1)) if len(rs) > 1 else '-'} | "
                  f"{f(np.percentile(o, 10, axis=0))} | {' / '.join(map(str, (o < 0.95).sum(0)))} | "
                  f"{' / '.join(f'{v:.3f}' for v in w.mean(0))} | "
                  f"{' / '.join(f'{v:.2f}' for v in ratio.mean(0)) if hier else '1'} | {by_draw if hier else '1'} | "
                  f"{' / '.join(f'{v:.0f}' for v in ess.min(0)) if hier and ess.size else '-'} |")


def _df_table(recs):
    """Learned dof (records with ``df_weight``): per generator, the posterior mass on df <= 6 and the posterior
    mean of log df (the Gaussian limit counted as df 1000), per axis, mean over draws."""
    recs = [r for r in recs if "df_weight" in r]
    if not recs:
        return
    print("\n| generator | draws | posterior mass on df <= 6, mean (min-max) over draws x / y / z | posterior median "
          "dof, median over draws x / y / z |")
    print("|---|---|---|---|")
    for name in dict.fromkeys(r["generator"] for r in recs):
        rs = [r for r in recs if r["generator"] == name]
        g = np.array([1000.0 if v is None else v for v in rs[0]["df_grid"]])
        w = np.array([r["df_weight"] for r in rs])                       # (draws, 3, K)
        small = w[:, :, g <= 6].sum(-1)
        med = g[np.argmax(np.cumsum(w, -1) >= 0.5, axis=-1)]              # (draws, 3)
        lab = lambda v: "inf" if v >= 1000 else f"{v:g}"   # noqa: E731
        print(f"| {name} | {len(rs)} | " + " / ".join(f"{small[:, a].mean():.2f} ({small[:, a].min():.2f}-"
                                                     f"{small[:, a].max():.2f})" for a in range(3))
              + " | " + " / ".join(lab(np.median(med[:, a])) for a in range(3)) + " |")


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
    _df_table(recs)


def belsten(args):
    from bayesmag._src.core.datasets import load_dataset
    from bayesmag._src.core.domain import Domain
    from bayesmag._src.core.predictor import Predictor, UQOptions, estimate_transfer

    d = load_dataset("belsten2023")
    sigma_in = bayesmag.estimate_input_noise(d) if hasattr(bayesmag, "estimate_input_noise") else None
    f = lambda v: " / ".join(f"{100 * x:.0f}" for x in v)   # noqa: E731
    print("| left-out run | in-domain rows | transfer | covered x / y / z (%) | in-domain rows covered x / y / z (%) | "
          "covered or flagged x / y / z (%) | mean in-domain 95 % width (uT) | effects | "
          "job's check: axes failed (new-session sd with the residual / loro's) |")
    print("|---|---|---|---|---|---|---|---|---|")
    from bayesmag._src.core.catalogue import make_extra
    extra = tuple(make_extra(name, t0=0.0) for name in args.extra)
    widths = {}
    for r in np.unique(d.run):
        train, test = d.subset(np.flatnonzero(d.run != r)), d.subset(np.flatnonzero(d.run == r))
        model = bayesmag.PhysicsModel.paper(t0=0.0, extra=extra)
        fit = bayesmag.fit_physics(train, model)
        from bayesmag._src.app.job import _residual_variance

        class _Cfg:
            class uq:
                method, n_params, n_qmc, seed, chunk_size = "analytic", 50, 64, 0, 256
        sin = sigma_in if sigma_in is not None else np.diag([0.02**2] * 3 + [1e-4])
        base = Predictor(fit=fit, sigma_in=sin, residual_sd=np.sqrt(_residual_variance(_Cfg, fit, train, sin)),
                         domain=Domain.from_data(train), uq=UQOptions(method="analytic"))
        post = H.fit_sessions(train, fit, mode_search=args.mode_search, likelihood=args.likelihood,
                              within_uninformed=args.within_uninformed == "free", weak=args.weak,
                              **({} if args.likelihood == "gaussian" else {"df": args.df}))
        loro_sd = estimate_transfer(train, fit).sd
        rms = np.sqrt(np.mean(post.transfer_sd_for(fit, train) ** 2, axis=0))
        warned = H.misfit_axes(rms, loro_sd, fit.s2)          # the job's rule (hierarchical_transfer)
        tot = lambda v: np.sqrt(v**2 + fit.s2)     # noqa: E731  the check's new-session sd (misfit_axes)
        said = ", ".join(f"{'xyz'[a]} {tot(rms)[a] / tot(loro_sd)[a]:.1f}x" for a in np.flatnonzero(warned)) or "none"
        fb = np.where(warned, loro_sd, np.nan)             # the job's default transfer_check = "loro"
        checked = dataclasses.replace(post, fallback_sd=tuple(map(float, fb))) if warned.any() else post
        for key, pr in (("loro", dataclasses.replace(base, transfer_sd=loro_sd)),
                        ("hierarchical", dataclasses.replace(base, sessions=post)),
                        ("hierarchical, checked", dataclasses.replace(base, sessions=checked))):
            p = pr.predict(test)
            lo, hi = p.interval(0.95)
            c = (test.b_ref >= lo) & (test.b_ref <= hi)
            dom = p.in_domain
            w = (hi - lo)[dom].mean(0) if dom.any() else np.full(3, np.nan)
            cin = c[dom].mean(0) if dom.any() else np.full(3, np.nan)
            widths.setdefault(key, []).append(w)
            print(f"| {r} | {int(dom.sum())} of {test.n} | {key} | {f(c.mean(0))} | {f(cin)} | "
                  f"{f((c | ~dom[:, None]).mean(0))} | "
                  f"{' / '.join(f'{v:.3f}' for v in w)} | {', '.join(post.effects) if key != 'loro' else '-'} | "
                  f"{said if key != 'loro' else '-'} |",
                  flush=True)
    ref = np.array(widths["loro"])
    for key in ("hierarchical", "hierarchical, checked"):
        ratio = np.array(widths[key]) / ref
        ok = np.isfinite(ratio)
        print(f"\n{key}: in-domain width / loro's over the {int(ok.sum())} run-axes with rows in domain: "
              f"median {np.median(ratio[ok]):.2f}, max {ratio[ok].max():.2f}, over 1.5x: {int((ratio[ok] > 1.5).sum())}")


def belsten_tau(args):
    """Belsten, run ``--run`` left out, axis ``--axis``: the posterior of the offset's between-session sd.

    Prints the modes BFGS finds from the two starts (log posterior, tau, the model's effective y-from-x
    cross-axis term at 24 C), the grid-integrated E tau^2 and P(tau > 0.3 uT) against ``fit_laplace`` (three
    seeds, importance ESS), the restricted against the profiled likelihood at the modes, the log posterior
    difference of the modes with each training run dropped, and what the left-out run says: the slope of its
    error on B_x with the five-run fit, and the all-run fit's cross-axis term.
    """
    import jax
    import jax.numpy as jnp
    import scipy.optimize
    from bayesmag._src.core.datasets import load_dataset
    from bayesmag._src.core.physics import inputs_from_data
    jax.config.update("jax_enable_x64", True)

    d = load_dataset("belsten2023")
    r, a = args.run, "xyz".index(args.axis)
    train, test = d.subset(np.flatnonzero(d.run != r)), d.subset(np.flatnonzero(d.run == r))
    model = bayesmag.PhysicsModel.paper(t0=0.0)
    fit = bayesmag.fit_physics(train, model)
    eff, dropped = H.select_effects(train, fit)
    within = H.uninformed_within(train, fit, list(dropped), a) if args.within_uninformed == "free" else None
    st = H.run_stats(train, fit, eff, within=within)
    names = list(model.param_names)
    print(f"run {r} left out, axis {args.axis}: learned effects {list(eff)}, uninformed {dropped}; within-run "
          f"nuisance columns {st.nuisance} ({args.within_uninformed})\n")
    if eff != ("O",):
        print("(the grid integration below is written for one learned effect)")
        return

    lp_of = lambda stats, reml: _lp_of(stats, a, reml)    # noqa: E731
    lp = lp_of(st, H.REML)

    def fg(h):
        v, g = jax.value_and_grad(lambda x: -lp(x)[0])(jnp.asarray(h))
        return float(v), np.asarray(g, np.float64)

    found = H._modes(fg, H._init_h(st, a, H.TAU_PRIOR_SCALE), 1, H.TAU_PRIOR_SCALE, search=True)
    ix, iks = names.index("S_x"), names.index("Ks_x")
    cross = lambda th: th[ix] + 24.0 * th[iks]    # noqa: E731  (y-from-x term at 24 C, the paper model: S + Ks T)
    print("| mode | tau (uT) | log posterior (REML) | log posterior (profiled mu) | B_x cross-axis term at 24 C |")
    print("|---|---|---|---|---|")
    for k, (h, _) in enumerate(found):
        val, mu, _ = lp(jnp.asarray(h))
        prof = float(lp_of(st, 0.0)(jnp.asarray(h))[0])
        c = cross(np.asarray(mu) / st.scale[a])
        print(f"| {k} | {np.exp(h[0]):.3f} | {float(val):.2f} | {prof:.2f} | {c:+.4f} |")
    full = bayesmag.fit_physics(d, model)
    e = test.b_ref[:, a] - np.asarray(fit.predict(inputs_from_data(test)))[:, a]
    slope = np.linalg.lstsq(np.c_[np.ones(test.n), test.b_meas[:, 0]], e, rcond=None)[0][1]
    print(f"\nfive-run LM fit: cross-axis term at 24 C {cross(np.asarray(fit.theta[a])):+.4f}; all six runs: "
          f"{cross(np.asarray(full.theta[a])):+.4f}; run {r}'s error against B_x with the five-run fit: slope "
          f"{slope:+.4f}, mean {e.mean():+.3f} uT, sd {e.std():.3f} uT")
    lt = np.arange(-6.0, 2.5, 0.15)
    logm = tau_grid_log_marginal(lambda h: lp(h)[0], found[0][0][1:], lt, np.linspace(-6.0, 6.0, 15))
    bad = ~np.isfinite(logm)
    if bad.any():    # the conditional Newton failed there: say where, and the lowest finite value, for scale
        print(f"grid: {bad.sum()} non-finite points at log tau {lt[bad].round(2).tolist()}, left out (the finite "
              f"points span {np.nanmax(logm) - np.nanmin(logm):.1f} nats below the top)")
        logm = np.where(bad, -np.inf, logm)
    w = np.exp(logm - logm.max())
    w /= w.sum()
    tau = np.exp(lt)
    print(f"\ngrid integration: E tau^2 = {w @ tau**2:.3f} uT^2 (rms {np.sqrt(w @ tau**2):.3f} uT), "
          f"P(tau > 0.3 uT) = {w[tau > 0.3].sum():.3f}, median tau {tau[np.searchsorted(np.cumsum(w), 0.5)]:.3f} uT")
    print("prior HalfNormal(0.5): E tau^2 = 0.25, P(tau > 0.3) = "
          f"{2 * (1 - __import__('scipy').stats.norm.cdf(0.3 / H.TAU_PRIOR_SCALE)):.3f}")
    for seed in range(3):
        post = H.fit_laplace(st, names, seed=seed, mode_search=True)
        print(f"fit_laplace(mode_search=True) seed {seed}: E tau^2 = {post.w_mean[a, 0]:.3f}, importance ESS "
              f"{post.ess[a]:.0f} of {H.N_PROPOSALS}")
    if len(found) > 1 and not st.nuisance:
        print("\nlog posterior maximised over (log sigma, atanh rho) at the large-tau mode's tau minus the same at the "
              "small-tau mode's, with one training run dropped:")
        big, small = sorted((h for h, _ in found), key=lambda h: h[0])[::-1]

        for k, run in enumerate(st.runs):
            sub = lp_of(st.select(np.arange(st.runs.size) != k), H.REML)
            f = lambda h, sub=sub: sub(h)[0]      # noqa: E731
            print(f"- without run {run}: {_cond_max(f, big[0], big[1:])[0] - _cond_max(f, small[0], small[1:])[0]:+.2f}")
    if len(found) == 1 and np.exp(found[0][0][0]) > SMALL_TAU:
        one_mode_profile(train, fit, eff, a, found[0][0])


def _lp_of(stats, a, reml):
    """Axis ``a``'s collapsed log posterior of ``h`` on ``stats`` (the value, ``mu`` and its covariance)."""
    import jax.numpy as jnp

    args_ = tuple(jnp.asarray(x) for x in (stats.m0[a], stats.m1[a], stats.m2[a], stats.first[a], stats.n,
                                            stats.effects))
    return lambda h: H._collapsed(h, *args_, H.TAU_PRIOR_SCALE, H.SIGMA_PRIOR_SCALE, reml)


def _cond_max(f, log_tau, start):
    """``f`` (log posterior of ``h``) maximised over ``(log sigma, atanh rho)`` at ``log_tau`` by BFGS from ``start``:
    ``(value, sigma, rho)``."""
    import jax
    import jax.numpy as jnp
    import scipy.optimize

    vg = jax.jit(jax.value_and_grad(lambda sr: -f(jnp.r_[log_tau, sr])))
    fn = lambda x: tuple(np.asarray(v, np.float64) for v in vg(jnp.asarray(x)))  # noqa: E731
    res = scipy.optimize.minimize(fn, np.asarray(start), jac=True, method="BFGS")
    return -float(res.fun), np.exp(res.x[0]), np.tanh(res.x[1])


#: ``belsten_tau``'s reference between-session sd for a one-mode posterior far above it (uT): a stable sensor's.
SMALL_TAU = 0.03


def one_mode_profile(train, fit, eff, a, mode):
    """One mode at a large ``tau``: how much the data prefer it to ``SMALL_TAU``, which run makes it, and what
    the left-out axis's reading does inside the training runs.

    The log posterior maximised over ``(log sigma, atanh rho)`` at the mode's ``tau`` minus the same at
    ``SMALL_TAU``, with all training runs and with each one dropped (stats without the within-run nuisance
    columns, which belong to single runs), and per run the within-run sd of the DUT's reading and of the
    reference on this axis, their lag-0 correlation and what the reading follows.
    """
    st = H.run_stats(train, fit, eff)

    def prof(stats, log_tau, start):
        lp = _lp_of(stats, a, H.REML)
        return _cond_max(lambda h: lp(h)[0], log_tau, start)

    print(f"\none mode, tau {np.exp(mode[0]):.3f} uT. Log posterior (maximised over sigma, rho) at it minus at tau "
          f"{SMALL_TAU} uT; sigma / rho at each:\n")
    print("| training runs | difference (nats) | sigma / rho at tau " f"{SMALL_TAU} | sigma / rho at the mode |")
    print("|---|---|---|---|")
    for k in [None] + list(range(st.runs.size)):
        s = st if k is None else st.select(np.arange(st.runs.size) != k)
        lo, hi = prof(s, np.log(SMALL_TAU), mode[1:]), prof(s, mode[0], mode[1:])
        label = "all" if k is None else f"without run {st.runs[k]}"
        print(f"| {label} | {hi[0] - lo[0]:+.1f} | {lo[1]:.4f} / {lo[2]:.3f} | {hi[1]:.4f} / {hi[2]:.3f} |")
    print(f"\nwithin each training run, axis {'xyz'[a]}: sd of the DUT's reading and of the reference (uT), their "
          "lag-0 correlation, and the input the reading follows most (|correlation|):\n")
    print("| run | reading sd | reference sd | correlation | follows |")
    print("|---|---|---|---|---|")
    cols = {"B_x": 0, "B_y": 1, "B_z": 2}
    for run in np.unique(train.run):
        m = train.run == run
        bm, br, temp = train.b_meas[m], train.b_ref[m], train.temperature[m]
        x = bm[:, a]
        others = {n: bm[:, j] for n, j in cols.items() if j != a} | {"temperature": temp}
        cc = {n: abs(np.corrcoef(x, v)[0, 1]) if v.std() > 0 and x.std() > 0 else 0.0 for n, v in others.items()}
        n_best = max(cc, key=cc.get)
        corr = np.corrcoef(x, br[:, a])[0, 1] if x.std() > 0 and br[:, a].std() > 0 else float("nan")
        print(f"| {run} | {x.std():.3f} | {br[:, a].std():.3f} | {corr:.3f} | {n_best} ({cc[n_best]:.3f}) |")


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
    ap.add_argument("what", choices=["generators", "belsten", "belsten_tau", "pooling", "summarise"])
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--first-draw", type=int, default=0, help="generators: training draws first..first+draws-1")
    ap.add_argument("--mode-search", action="store_true", help="generators, belsten: fit_laplace(mode_search=True)")
    ap.add_argument("--run", type=int, default=3, help="belsten_tau: the left-out run")
    ap.add_argument("--extra", nargs="*", default=[], help="belsten: catalogue terms added to the paper model "
                                                           "(names, e.g. temperature_quadratic)")
    ap.add_argument("--within-uninformed", default="free", choices=["free", "shared"],
                    help="generators, belsten, belsten_tau: an uninformed candidate's within-run variation with its "
                         "own coefficient in the runs that do not inform it (free, the default) or the shared mu")
    ap.add_argument("--axis", default="y", choices=list("xyz"), help="belsten_tau: the axis")
    ap.add_argument("--logs", nargs="*", default=[], help="summarise: logs holding DRAW lines")
    ap.add_argument("--sessions", type=int, default=40)
    ap.add_argument("--weak", type=lambda v: None if v == "off" else float(v), default=H.WEAK_NOISE_MULTIPLE,
                    help="generators, belsten: fit_sessions(weak=...), 'off' for the model before the weak directions")
    ap.add_argument("--runs", type=int, default=30)
    ap.add_argument("--generator", nargs="+", default=list(GENERATORS), choices=sorted(GENERATORS))
    ap.add_argument("--likelihood", default="gaussian", choices=list(H.LIKELIHOODS), help="hierarchical model's likelihood")
    ap.add_argument("--df", type=lambda v: v if v == "learned" else float(v), default=4.0,
                    help="its Student-t dof, or 'learned' (a posterior on a grid, issue 24)")
    ap.add_argument("--laplace-draws", default="importance", choices=["importance", "gaussian"],
                    help="Laplace path: draws corrected to the exact posterior (default) or the Gaussian's own")
    args = ap.parse_args()
    print(f"## `python benchmarks/bench_hierarchical.py {' '.join(sys.argv[1:])}`\n")
    {"generators": generators, "belsten": belsten, "belsten_tau": belsten_tau, "pooling": pooling, "summarise": summarise}[args.what](args)


if __name__ == "__main__":
    main()
