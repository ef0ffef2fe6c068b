"""Benchmark: hybrid + transfer intervals on simulated sessions, leaving each session out.

Run:  python benchmarks/bench_hybrid_shift.py [--sessions 8] [--rows 600] [--seeds 0 1 2] [--transfer hierarchical]
      python benchmarks/bench_hybrid_shift.py --both [--transfer-networks by_run_folds] [--save DIR]

An independent check of the whole default pipeline (physics + residual network + conformal scale +
transfer) on data it was not designed on: ``--sessions`` simulated campaigns, each a session with
its own offsets (sd 0.3 uT) and cross-axis terms (sd 0.003; the generator of
``tests/test_transfer.py``), heated and room-temperature sessions alternating, all with the same
hidden distortion the network has to learn (``axis_quadratic``: y gains 0.001 x^2). Every
session is left out in turn (``split.kind = "by_run"``), the job is run with the quickstart's
network settings, and its ``predictions.csv`` is scored: the coverage of the hybrid's 95 %
intervals (transfer part included) on the rows in domain, the share of rows covered or flagged
out of domain, and the physics intervals' in-domain coverage beside them. The issue's target for
a new session: at least 95 % of the rows covered or flagged.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_transfer import _session  # noqa: E402  (the test's session generator)

import bayesmag  # noqa: E402
from bayesmag._src.app.config import config_from_dict  # noqa: E402
from bayesmag._src.core.data import write_csv  # noqa: E402
from bayesmag._src.core.simulate import get_effect  # noqa: E402

AXES = "xyz"


def physics_loro_predictions(train, fit) -> np.ndarray:
    """(n, 3) prediction of every training row by the physics fit without its run (all folds in one
    compiled fit, :func:`~bayesmag._src.core.fit.fit_folds`); a fold that cannot be fitted keeps ``fit``'s."""
    from bayesmag._src.core.fit import fit_folds
    from bayesmag._src.core.physics import inputs_from_data

    runs = np.unique(train.run)
    held = np.stack([train.run == r for r in runs])
    out = np.asarray(fit.predict(inputs_from_data(train)), np.float64).copy()
    if runs.size < 2:
        return out
    thetas, oks = fit_folds(train, fit.model, ~held)
    for k in np.flatnonzero(oks):
        rows = np.flatnonzero(held[k])
        out[rows] = np.asarray(fit.model.predict_all(thetas[k], inputs_from_data(train.subset(rows))))
    return out


def sessions(n: int, rows: int, seed: int) -> bayesmag.CalibrationData:
    """``n`` simulated sessions (runs 1..n), each with its own shifted parameters, one shared distortion."""
    return _session(seed, n, rows=rows, noise_sd=0.05,
                    effects=[get_effect("axis_quadratic", out="y", inp="x", coeff=0.001)])


def leave_one_out(path: Path, run: int, out: Path, transfer: str = "loro") -> dict:
    raw = {"name": "hybrid_shift", "data": {"path": str(path)}, "split": {"kind": "by_run", "test_runs": [run]},
           "physics": {"t0": "mean"}, "uq": {"method": "psqmc", "n_params": 100, "n_qmc": 128, "seed": 0,
                                             "transfer": transfer},
           "network": {"enabled": True, "learning_rate": 1e-3, "batch_size": 64, "max_epochs": 200, "patience": 20,
                       "mc_passes": 50, "seed": 0},
           "output": {"figures": False, "progress": False}}
    bayesmag.run_job(config_from_dict(raw), out)
    rows = list(csv.DictReader(open(out / "predictions.csv")))
    yes = lambda col: np.array([r[col] in ("1", "True", "true") for r in rows])   # noqa: E731
    ind = yes("x_in_domain")
    hyb = np.column_stack([yes(f"{a}_hybrid_covered") for a in AXES])
    phy = np.column_stack([yes(f"{a}_covered") for a in AXES])
    tau = json.loads((out / "metrics.json").read_text())["transfer"]["sd"]
    nan = np.full(3, np.nan)
    return {"in_domain": ind.mean(), "hybrid": hyb[ind].mean(0) if ind.any() else nan,
            "flagged_or_covered": (hyb | ~ind[:, None]).mean(0), "physics": phy[ind].mean(0) if ind.any() else nan,
            "tau": np.array([tau[a] for a in AXES])}


def leave_one_out_both(data: bayesmag.CalibrationData, run: int, transfers=("loro", "hierarchical"),
                       transfer_networks: str = "none", save: Path | None = None, transfer_check: str = "loro") -> dict:
    """Both transfers from one calibration: the job's settings, ``calibrate`` in this process (compiled
    programs reused across sessions), the hybrid predictor with each transfer part.

    The network and its conformal scale do not depend on ``uq.transfer`` (the scale is computed on rows of
    the training sessions, without the transfer part), so swapping the transfer part of the predictor
    gives what a job with that transfer would predict (``--separate-jobs`` runs the jobs). With
    ``transfer_networks = "by_run_folds"`` every transfer is scored twice, without and with the calibration's
    network part (``<transfer>+net``; it does not depend on the transfer), and the hierarchical transfer a third
    time as the calibration predicts it: the session model refitted on the out-of-fold hybrid residuals, no
    network part added (``hierarchical_oof``, :func:`~bayesmag._src.pipeline.network_transfer.hybrid_session_model`).
    ``save``: an ``.npz`` of the per-row pieces (test and training rows) for :func:`analyse`. ``transfer_check``:
    ``[uq] transfer_check`` (``"loro"``, the default: an axis of the physics session model more than 2x
    leave-one-run-out's takes loro's sd; ``"warn"`` keeps the model's; the hybrid's out-of-fold session model only
    warns either way since 4d79bc2, so ``--transfer-check`` no longer changes its row).
    """
    import dataclasses

    from bayesmag._src.core.predictor import estimate_transfer
    from bayesmag._src.pipeline.calibrate import calibrate

    raw = {"name": "hybrid_shift", "data": {"path": "unused.csv"}, "split": {"kind": "by_run", "test_runs": [run]},
           "physics": {"t0": "mean"}, "uq": {"method": "psqmc", "n_params": 100, "n_qmc": 128, "seed": 0,
                                             "transfer": "hierarchical", "transfer_networks": transfer_networks,
                                             "transfer_check": transfer_check},
           "network": {"enabled": True, "learning_rate": 1e-3, "batch_size": 64, "max_epochs": 200, "patience": 20,
                       "mc_passes": 50, "seed": 0},
           "output": {"figures": False, "progress": False}}
    train, test = data.subset(np.flatnonzero(data.run != run)), data.subset(np.flatnonzero(data.run == run))
    cr = calibrate(train, config_from_dict(raw).settings(), test=test)
    hyb, phys = cr.predictor, cr.physics.predictor
    nt = cr.hybrid.network_transfer.get(cr.hybrid.primary)
    loro = estimate_transfer(train, cr.fit).sd
    variants = [(t, False) for t in transfers] + ([(t, True) for t in transfers] if nt is not None else [])
    oof = nt is not None and nt.session_model is not None        # the calibration's own hybrid session model
    if oof:
        variants.append(("hierarchical_oof", False))
    # the physics session model, without and with the network part in quadrature (the predictor before the
    # out-of-fold session model)
    hyb0 = dataclasses.replace(hyb, sessions=phys.sessions, network_transfer_sd=None)
    out, dump = {}, {"test_b_ref": test.b_ref}
    for t, net in variants:
        if t == "loro":
            hp, pp = (dataclasses.replace(p, sessions=None, transfer_sd=loro) for p in (hyb0, phys))
            tau = loro
            if net:
                hp = dataclasses.replace(hp, network_transfer_sd=nt.sd)
        elif t == "hierarchical_oof":
            hp, pp = hyb, phys
            tau = np.sqrt(np.mean(hyb.transfer_part(train) ** 2, axis=0))
        else:
            hp, pp = (dataclasses.replace(hyb0, network_transfer_sd=nt.sd) if net else hyb0), phys
            tau = np.sqrt(np.mean(hyb0.transfer_part(train) ** 2, axis=0))
        name = t + ("+net" if net else "")
        res, width = {}, None
        for key, pr in (("hybrid", hp), ("physics", pp)):
            p = pr.predict(test)
            lo, hi = p.interval(0.95)
            res[key] = (test.b_ref >= lo) & (test.b_ref <= hi)
            if key == "hybrid":
                width = hi - lo
                dump[f"{name}_mean"], dump[f"{name}_total"] = p.mean, p.total
        ind = np.asarray(p.in_domain, bool)
        nan = np.full(3, np.nan)
        dump["in_domain"] = ind
        out[name] = {"in_domain": ind.mean(), "hybrid": res["hybrid"][ind].mean(0) if ind.any() else nan,
                     "flagged_or_covered": (res["hybrid"] | ~ind[:, None]).mean(0),
                     "physics": res["physics"][ind].mean(0) if ind.any() else nan, "tau": tau,
                     "width": width[ind].mean(0) if ind.any() else nan,
                     "tau_net": hp.network_transfer_sd if net else np.zeros(3)}
    if save is not None and nt is not None:
        # the pieces of the other estimates analyse() scores: out-of-session hybrid error (loro physics + fold
        # network), the predictor's variance at the training rows (no transfer), the hierarchical transfer sd there
        cheap = dataclasses.replace(hyb0, uq=dataclasses.replace(hyb0.uq, method="auto", n_params=50, n_qmc=32))
        comp = cheap.components(train)
        phys_loro = physics_loro_predictions(train, cr.fit)
        dump.update({"train_nn_oof": nt.rows["nn_oof"], "train_nn_full": nt.rows["nn_full"], "train_run": train.run,
                     "train_phys_pooled": train.b_ref - nt.rows["resid"], "train_phys_loro": phys_loro,
                     "train_err": train.b_ref - phys_loro - nt.rows["nn_oof"],
                     "train_var": cheap.compose(comp, new_session=False).total ** 2, "train_tau_p": comp.transfer})
        dump["train_b_ref"], dump["loro"] = train.b_ref, loro
        np.savez(save, **dump)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=8)
    ap.add_argument("--rows", type=int, default=600)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--transfer", default="loro", help="[uq] transfer of every job (loro, hierarchical, ...)")
    ap.add_argument("--both", action="store_true",
                    help="loro and hierarchical from one calibration per left-out session, in this process")
    ap.add_argument("--transfer-networks", default="none", choices=("none", "by_run_folds"),
                    help="with --both: [uq] transfer_networks; by_run_folds scores every transfer without and with "
                         "the network part")
    ap.add_argument("--transfer-check", default="loro", choices=("loro", "warn"),
                    help="with --both: [uq] transfer_check of the session models (default loro, the library's)")
    ap.add_argument("--save", default=None, help="with --both: a folder for one .npz of per-row pieces per session")
    ap.add_argument("--analyse", default=None, help="a --save folder: score other estimates of the network part "
                                                    "offline (diagnostic; nothing is trained)")
    ap.add_argument("--analyse-oof", default=None, help="a --save folder: refit the hybrid session model on the out-of-fold "
                                                        "hybrid residuals with --effects and score it (diagnostic)")
    ap.add_argument("--effects", nargs="+", default=None, help="with --analyse-oof: the candidate random effects "
                                                               "(default: the library's)")
    a = ap.parse_args(argv)
    if a.analyse_oof:
        return analyse_oof(Path(a.analyse_oof), a.effects)
    if a.analyse:
        return analyse(Path(a.analyse))
    if a.both:
        return main_both(a)
    f = lambda v: " / ".join("-" if np.isnan(x) else f"{100 * x:.1f}" for x in v)   # noqa: E731
    print(f"## `python benchmarks/bench_hybrid_shift.py --sessions {a.sessions} --rows {a.rows} --seeds "
          f"{' '.join(map(str, a.seeds))}{'' if a.transfer == 'loro' else ' --transfer ' + a.transfer}`\n")
    print("| seed | left-out session | rows in domain (%) | hybrid in-domain coverage x / y / z (%) | rows covered or "
          "flagged x / y / z (%) | physics in-domain coverage (%) | transfer sd x / y / z (uT) |")
    print("|---|---|---|---|---|---|---|")
    allr = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for seed in a.seeds:
            write_csv(sessions(a.sessions, a.rows, seed), tmp / f"s{seed}.csv")
            for run in range(1, a.sessions + 1):
                r = leave_one_out(tmp / f"s{seed}.csv", run, tmp / f"o{seed}_{run}", a.transfer)
                allr.append(r)
                print(f"| {seed} | {run} | {100 * r['in_domain']:.1f} | {f(r['hybrid'])} | {f(r['flagged_or_covered'])} | "
                      f"{f(r['physics'])} | {' / '.join(f'{x:.3g}' for x in r['tau'])} |", flush=True)
    fc = np.array([r["flagged_or_covered"] for r in allr])
    print(f"\nMean over {len(allr)} left-out sessions: hybrid in-domain coverage "
          f"{f(np.nanmean([r['hybrid'] for r in allr], 0))}, rows covered or flagged {f(fc.mean(0))}, physics "
          f"in-domain {f(np.nanmean([r['physics'] for r in allr], 0))}; sessions under 95 % covered or flagged: "
          f"{' / '.join(str(int(v)) for v in (fc < 0.95).sum(0))} of {len(allr)}.")
    return 0


def main_both(a) -> int:
    f = lambda v: " / ".join("-" if np.isnan(x) else f"{100 * x:.1f}" for x in v)   # noqa: E731
    tn = a.transfer_networks
    print(f"## `python benchmarks/bench_hybrid_shift.py --both --sessions {a.sessions} --rows {a.rows} --seeds "
          f"{' '.join(map(str, a.seeds))}{'' if tn == 'none' else ' --transfer-networks ' + tn}"
          f"{'' if a.transfer_check == 'loro' else ' --transfer-check ' + a.transfer_check}`\n")
    print("| seed | left-out session | transfer | rows in domain (%) | hybrid in-domain coverage x / y / z (%) | rows "
          "covered or flagged x / y / z (%) | physics in-domain coverage (%) | transfer sd x / y / z (uT) | network "
          "transfer sd (uT) | hybrid in-domain width (uT) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    allr: dict = {}
    for seed in a.seeds:
        d = sessions(a.sessions, a.rows, seed)
        for run in range(1, a.sessions + 1):
            save = None if a.save is None else Path(a.save) / f"s{seed}_r{run}.npz"
            for t, r in leave_one_out_both(d, run, transfer_networks=tn, save=save,
                                                    transfer_check=a.transfer_check).items():
                allr.setdefault(t, []).append((seed, run, r))
                print(f"| {seed} | {run} | {t} | {100 * r['in_domain']:.1f} | {f(r['hybrid'])} | "
                      f"{f(r['flagged_or_covered'])} | {f(r['physics'])} | {' / '.join(f'{x:.3g}' for x in r['tau'])} | "
                      f"{' / '.join(f'{x:.3g}' for x in r['tau_net'])} | {' / '.join(f'{x:.3g}' for x in r['width'])} |",
                      flush=True)
    base = np.array([r["flagged_or_covered"] for _, _, r in allr["loro"]]) >= 0.95      # (sessions, 3)
    w_loro = np.array([r["width"] for _, _, r in allr["loro"]])
    for t, rows in allr.items():
        fc = np.array([r["flagged_or_covered"] for _, _, r in rows])
        miss = ", ".join(f"{s}-{u} {AXES[k]} {100 * r['flagged_or_covered'][k]:.1f}" for s, u, r in rows for k in range(3)
                         if r["flagged_or_covered"][k] < 0.95)
        ratio = np.array([r["width"] for _, _, r in rows]) / w_loro
        rq = [np.nanmedian(ratio[base[:, k], k]) for k in range(3)]
        rx = [np.nanmax(ratio[base[:, k], k]) for k in range(3)]
        over = [int(np.sum(ratio[base[:, k], k] > 1.5)) for k in range(3)]
        print(f"\n{t}: mean over {len(rows)} left-out sessions: hybrid in-domain coverage "
              f"{f(np.nanmean([r['hybrid'] for _, _, r in rows], 0))}, rows covered or flagged {f(fc.mean(0))}, "
              f"physics in-domain {f(np.nanmean([r['physics'] for _, _, r in rows], 0))}; sessions under 95 % "
              f"covered or flagged: {' / '.join(str(int(v)) for v in (fc < 0.95).sum(0))} of {len(rows)} ({miss}). "
              f"Width / loro width where loro covers ({' / '.join(str(int(v)) for v in base.sum(0))} session-axes): "
              f"median {' / '.join(f'{v:.2f}' for v in rq)}, largest {' / '.join(f'{v:.2f}' for v in rx)}, "
              f"over 1.5x {' / '.join(map(str, over))}.")
    return 0


def analyse(folder: Path) -> int:
    """Sessions under 95 % and width / loro width for three estimates of the network part, from ``--save`` files.

    ``shift`` (the library's, :func:`~bayesmag._src.pipeline.network_transfer.network_transfer_sd`): the grouped
    95 % quantile of ``(d/z)^2``, ``d`` the fold network's correction less the full network's, on the rows inside the
    other folds' domain (``shift_all_rows``: on all rows); ``joint``: the
    grouped 95 % quantile of ``(e/z)^2 - sigma^2 - tau_p^2``, ``e`` the out-of-session hybrid error
    (leave-one-run-out physics + fold network), i.e. only what the physics transfer part does not already cover;
    ``net_only``: ``(e/z)^2 - sigma^2`` with the pooled physics fit (the network's out-of-session error against its
    target, added to the physics transfer). Gaussian family only (the interval is ``mean +- z total``).
    """
    import scipy.stats

    from bayesmag._src.pipeline.network_transfer import (fold_domain_mask, grouped_excess_quantile, network_transfer_sd,
                                                        run_folds)

    z = scipy.stats.norm.ppf(0.975)
    files = sorted(folder.glob("s*_r*.npz"), key=lambda q: tuple(int(v) for v in q.stem[1:].split("_r")))
    estimates = ("none", "shift", "shift_all_rows", "joint", "net_only")
    res = {(t, e): [] for t in ("loro", "hierarchical") for e in estimates}
    data = {}
    for q in files:
        d = np.load(q)
        y, ind = d["test_b_ref"], d["in_domain"].astype(bool)
        run, var = d["train_run"], d["train_var"]
        seed, left = (int(v) for v in q.stem[1:].split("_r"))
        if seed not in data:
            data[seed] = sessions(8, d["test_b_ref"].shape[0], seed)      # the bench's defaults (--sessions 8)
        train = data[seed].subset(np.flatnonzero(data[seed].run != left))
        inside = fold_domain_mask(train, run_folds(train.run, 5, 2)[0])  # the job's folds (conformal_folds 5, seed 0)
        e_pool = d["train_b_ref"] - d["train_phys_pooled"] - d["train_nn_oof"]
        for t in ("loro", "hierarchical"):
            tau_p = np.broadcast_to(d["loro"], var.shape) if t == "loro" else d["train_tau_p"]
            tn = {"none": np.zeros(3),
                  "shift": network_transfer_sd(d["train_nn_oof"][inside], d["train_nn_full"][inside], run[inside]),
                  "shift_all_rows": network_transfer_sd(d["train_nn_oof"], d["train_nn_full"], run),
                  "joint": grouped_excess_quantile(d["train_err"], var + tau_p**2, run),
                  "net_only": grouped_excess_quantile(e_pool, var, run)}
            for e in estimates:
                half = z * np.sqrt(d[f"{t}_total"] ** 2 + tn[e] ** 2)
                cov = np.abs(y - d[f"{t}_mean"]) <= half
                res[(t, e)].append(((cov | ~ind[:, None]).mean(0), (2 * half)[ind].mean(0), tn[e], q.stem))
    wl = np.array([w for _, w, _, _ in res[("loro", "none")]])
    base = np.array([c for c, _, _, _ in res[("loro", "none")]]) >= 0.95
    print(f"## `python benchmarks/bench_hybrid_shift.py --analyse {folder}` ({len(files)} sessions)\n")
    print("| transfer | network part | under 95 % x / y / z | median network sd x / y / z (uT) | width / loro width "
          "where loro covers: median x / y / z | largest | over 1.5x | the sessions under 95 % |")
    print("|---|---|---|---|---|---|---|---|")
    for (t, e), rows in res.items():
        fc = np.array([c for c, _, _, _ in rows])
        ratio = np.array([w for _, w, _, _ in rows]) / wl
        tn = np.array([v for _, _, v, _ in rows])
        miss = ", ".join(f"{n[1:].replace('_r', '-')} {AXES[k]} {100 * c[k]:.1f}" for c, _, _, n in rows for k in range(3)
                         if c[k] < 0.95)
        f2 = lambda v: " / ".join(f"{x:.2f}" for x in v)  # noqa: E731
        print(f"| {t} | {e} | {' / '.join(str(int(v)) for v in (fc < 0.95).sum(0))} | {f2(np.median(tn, 0))} | "
              f"{f2([np.median(ratio[base[:, k], k]) for k in range(3)])} | "
              f"{f2([np.max(ratio[base[:, k], k]) for k in range(3)])} | "
              f"{' / '.join(str(int(np.sum(ratio[base[:, k], k] > 1.5))) for k in range(3))} | {miss} |")
    return 0


def analyse_oof(folder: Path, effects=None) -> int:
    """The hybrid session model on the out-of-fold hybrid residuals, refitted from ``--save`` files with the
    candidate random ``effects`` (None: the library's, which reproduces ``hierarchical_oof``) and scored against
    loro: the hybrid's within-session variance is the saved loro total less loro's transfer variance, the
    transfer sd the refitted model's at the left-out session's rows (Gaussian intervals ``mean +- z total``)."""
    import scipy.stats

    from bayesmag._src.core.fit import fit_physics
    from bayesmag._src.pipeline.network_transfer import (NetworkTransfer, fold_domain_mask, hybrid_residual_rows,
                                                        run_folds)
    from bayesmag._src.pipeline.sessions import DEFAULT_EFFECTS, hierarchical_transfer

    z = scipy.stats.norm.ppf(0.975)
    eff = tuple(effects) if effects else DEFAULT_EFFECTS
    settings = config_from_dict({"name": "x", "data": {"path": "unused.csv"}, "physics": {"t0": "mean"}}).settings()
    files = sorted(folder.glob("s*_r*.npz"), key=lambda q: tuple(int(v) for v in q.stem[1:].split("_r")))
    data, rows = {}, []
    for q in files:
        d = np.load(q)
        seed, left = (int(v) for v in q.stem[1:].split("_r"))
        if seed not in data:
            data[seed] = sessions(8, d["test_b_ref"].shape[0], seed)
        train = data[seed].subset(np.flatnonzero(data[seed].run != left))
        test = data[seed].subset(np.flatnonzero(data[seed].run == left))
        fit = fit_physics(train, settings.physics.model(train))
        inside = fold_domain_mask(train, run_folds(train.run, 5, 2)[0])   # the job's folds (conformal_folds 5, seed 0)
        nt = NetworkTransfer(np.zeros(3), 0, (), np.zeros(3), np.zeros(3), 0, {"nn_oof": d["train_nn_oof"],
                                                                               "inside": inside})
        _, post = hierarchical_transfer(hybrid_residual_rows(train, nt), fit, effects=eff)
        within2 = d["loro_total"] ** 2 - d["loro"] ** 2
        y, ind = d["test_b_ref"], d["in_domain"].astype(bool)
        out = {}
        for name, tot in (("loro", d["loro_total"]), ("oof", np.sqrt(within2 + post.transfer_sd_for(fit, test) ** 2))):
            cov = np.abs(y - d["loro_mean"]) <= z * tot
            out[name] = ((cov | ~ind[:, None]).mean(0), (2 * z * tot)[ind].mean(0))
        rows.append((q.stem, out))
    base = np.array([o["loro"][0] for _, o in rows]) >= 0.95
    ratio = np.array([o["oof"][1] for _, o in rows]) / np.array([o["loro"][1] for _, o in rows])
    fc = np.array([o["oof"][0] for _, o in rows])
    f2 = lambda v: " / ".join(f"{x:.2f}" for x in v)  # noqa: E731
    miss = ", ".join(f"{n[1:].replace('_r', '-')} {AXES[k]} {100 * o['oof'][0][k]:.1f}" for n, o in rows
                     for k in range(3) if o["oof"][0][k] < 0.95)
    print(f"## `python benchmarks/bench_hybrid_shift.py --analyse-oof {folder}{' --effects ' + ' '.join(eff) if effects else ''}` "
          f"({len(rows)} sessions)\n")
    print(f"effects {', '.join(eff)}: under 95 % {' / '.join(str(int(v)) for v in (fc < 0.95).sum(0))} ({miss}); width / "
          f"loro width where loro covers: median {f2([np.median(ratio[base[:, k], k]) for k in range(3)])}, largest "
          f"{f2([np.max(ratio[base[:, k], k]) for k in range(3)])}, over 1.5x "
          f"{' / '.join(str(int(np.sum(ratio[base[:, k], k] > 1.5))) for k in range(3))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
