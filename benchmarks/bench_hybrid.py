"""Benchmark: the hybrid stage on the paper's protocol (real data, random 90/10 split, 338 test rows).

Run:  BAYESMAG_DATA_DIR=../shared/data python benchmarks/bench_hybrid.py [--seeds 5] [--config FILE]

For split seeds 0..seeds-1 it runs the job of ``--config`` (paper settings: 4 x 64 ReLU,
DropConnect 0.01, Adam 5e-4, batch 16, <= 1000 epochs, patience 50, M = 100 passes,
Np = 500, Nq = 1000) and collects the hybrid test metrics per axis; then, on split seed 0,
it times

* training of the three axis networks: cold (first call in a fresh process, including jit
  compilation) and warm (the compiled program again, same data);
* inference for the 338 test rows x 3 axes: physics PS-QMC UQ (Np, Nq) + M MC-DropConnect
  passes + fusion, median of repeats after one warm-up call;

and a no-network baseline (physics + mean residual of the 3 nearest training rows), and
prints a markdown section with ratios to the paper's Table 11 (505.5 s training,
39.47 s inference, validation settings).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

import bayesmag as bm
from bayesmag._src.app.config import load_config
from bayesmag._src.pipeline.hybrid import check_network_config, fuse, network_inputs, train_network
from bayesmag._src.core.network import mc_predict

PAPER_TRAIN_S = 505.5
PAPER_INFER_S = 39.47
PAPER = {"rmse": [0.01622, 0.03459, 0.02067], "coverage": [0.9852, 0.9763, 0.9852],
         "nll": [-2.699, -2.732, -2.493], "crps": [0.00891, 0.01213, 0.01069]}
REFERENCE = {"rmse": [0.01837, 0.0353, 0.02123], "coverage": [0.9822, 0.9882, 0.9882],
             "nll": [-2.515, -2.3, -2.454], "crps": [0.01056, 0.01687, 0.01142]}
AXES = ("x", "y", "z")
KEYS = ("rmse", "coverage", "nll", "crps")


def fmt(key, v):
    return f"{100 * v:.1f}" if key == "coverage" else (f"{v:.3f}" if key == "nll" else f"{v:.5f}")


def knn_rmse(data, split, k=3):
    """Test RMSE per axis of a k-nearest-neighbour lookup of the physics residual (no network).

    Neighbours in the standardised (Bx, By, Bz, T) of the training rows (scipy cKDTree): a
    baseline that can only interpolate, to show what a split rewards.
    """
    from scipy.spatial import cKDTree

    train, test = data.subset(split.train), data.subset(split.test)
    fit = bm.fit_physics(train)
    r_train = train.b_ref - fit.predict(bm.inputs_from_data(train))
    r_test = test.b_ref - fit.predict(bm.inputs_from_data(test))
    x_train, x_test = network_inputs(train), network_inputs(test)
    mu, sd = x_train.mean(0), x_train.std(0)
    _, idx = cKDTree((x_train - mu) / sd).query((x_test - mu) / sd, k=k)
    err = r_test - r_train[idx.reshape(len(x_test), -1)].mean(1)
    return [float(v) for v in np.sqrt(np.mean(err**2, axis=0))]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(Path(__file__).resolve().parents[1] / "configs" / "paper_hybrid.toml"))
    ap.add_argument("--seeds", type=int, default=5, help="split seeds 0..seeds-1")
    ap.add_argument("--repeats", type=int, default=5, help="repeats of the inference timing")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    ap.add_argument("--json", help="also write the numbers here")
    ap.add_argument("--no-timing", action="store_true", help="skip the training / inference timing")
    ap.add_argument("--loro", action="store_true",
                    help="leave each run out instead (split.kind = by_run): per run RMSE, coverage, misses flagged")
    args = ap.parse_args()
    if args.loro:
        return loro(args)

    # -- timing on split seed 0 (fresh process: the first training includes compilation) -------
    if args.no_timing:
        return accuracy_only(args)
    cfg = load_config(args.config, ["split.seed=0", "output.figures=false", "output.progress=false", *args.set])
    spec = check_network_config(cfg)[0]
    d = bm.load_dataset(cfg.data.source)
    sp = bm.make_split(d, kind=cfg.split.kind, test_fraction=cfg.split.test_fraction, seed=0,
                       test_runs=cfg.split.test_runs, n_blocks=cfg.split.n_blocks)
    train, test = d.subset(sp.train), d.subset(sp.test)
    fit = bm.fit_physics(train)
    sigma_in = bm.estimate_input_noise(train)
    x_train, x_test = network_inputs(train), network_inputs(test)
    r_train = train.b_ref - fit.predict(bm.inputs_from_data(train))
    net_cfg = cfg.network

    def train_once():
        return train_network(x_train, r_train, spec, net_cfg, groups=train.run)

    t = time.perf_counter()
    net = train_once()
    train_cold = time.perf_counter() - t
    t = time.perf_counter()
    net = train_once()
    train_warm = time.perf_counter() - t
    epochs = [int(e) for e in net.info.epochs_run]

    inp = bm.inputs_from_data(test)

    def infer():
        uq = bm.physics_uncertainty(fit, inp, sigma_in=sigma_in, method=cfg.uq.method, n_params=cfg.uq.n_params,
                                    n_qmc=cfg.uq.n_qmc, seed=cfg.uq.seed, progress=False)
        nn = mc_predict(net, x_test, passes=net_cfg.mc_passes, seed=net_cfg.seed)
        return fuse(uq, nn, spec, fusion=net_cfg.fusion)

    t = time.perf_counter()
    infer()
    infer_cold = time.perf_counter() - t
    ts = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        infer()
        ts.append(time.perf_counter() - t)
    infer_warm = statistics.median(ts)

    # -- accuracy over split seeds, through the job ------------------------------------------------
    per_seed = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.seeds):
            c = load_config(args.config, [f"split.seed={seed}", "output.figures=false", "output.progress=false",
                                          *args.set])
            res = bm.run_job(c, Path(tmp) / f"s{seed}")
            m = res["metrics"]
            name = c.network.likelihoods[0]
            h = m["hybrid"][name]
            per_seed.append({"seed": seed, "physics_rmse": [m["physics"]["rmse"][a] for a in AXES],
                             **{k: [h[k][a] for a in AXES] for k in KEYS},
                             "paper_fusion_coverage": [m["hybrid_paper_fusion"][name]["coverage"][a] for a in AXES],
                             "epochs": [m["network"]["training"][name][a]["epochs_run"] for a in AXES],
                             "train_s": m["timings"]["network_train"],
                             "knn3_rmse": knn_rmse(res["data"], res["split"], k=3)})

    # -- report ------------------------------------------------------------------------------------
    out = []
    out.append(f"## Hybrid stage (issue #3): `{cfg.name}`, `{cfg.split.kind}` split, {args.seeds} split seeds\n")
    cmd = "BAYESMAG_DATA_DIR=../shared/data python benchmarks/bench_hybrid.py --seeds " + str(args.seeds)
    if args.config != ap.get_default("config"):
        cmd += f" --config {args.config}"
    cmd += "".join(f" --set {s}" for s in args.set)
    out.append(f"Command: `{cmd}` (config `{Path(args.config).name}`: {spec.hidden_layers} x {spec.width} "
               f"{spec.activation}, DropConnect {spec.dropconnect}, lr {spec.learning_rate}, batch {spec.batch_size}, "
               f"<= {spec.max_epochs} epochs, patience {spec.patience}, M = {net_cfg.mc_passes}, "
               f"Np = {cfg.uq.n_params}, "
               f"Nq = {cfg.uq.n_qmc}, likelihood {spec.likelihood}, fusion `{net_cfg.fusion}`, "
               f"Fourier features {spec.fourier_features}"
               + (f" at scale {spec.fourier_scale:g}" if spec.fourier_features else "")
               + f"). Split `{cfg.split.kind}` ({cfg.split.test_fraction:.0%} test) of "
               f"the {d.n} rows ({sp.test.size} test rows at seed 0); network seed {net_cfg.seed}.\n")
    out.append("| split seed | RMSE x / y / z (uT) | coverage x / y / z (%) | NLL x / y / z | CRPS x / y / z (uT) "
               "| epochs x / y / z |")
    out.append("|---|---|---|---|---|---|")
    for r in per_seed:
        out.append(f"| {r['seed']} | " + " | ".join(" / ".join(fmt(k, v) for v in r[k]) for k in KEYS)
                   + " | " + " / ".join(map(str, r["epochs"])) + " |")
    arr = {k: np.array([r[k] for r in per_seed]) for k in KEYS}
    out.append("| **mean** | " + " | ".join(" / ".join(fmt(k, v) for v in arr[k].mean(0)) for k in KEYS) + " | |")
    if args.seeds > 1:
        out.append("| sd over seeds | " + " | ".join(" / ".join(fmt(k, v) for v in arr[k].std(0, ddof=1))
                                                   for k in KEYS) + " | |")
    out.append("| paper (Table 7, Gaussian; split seed unknown) | "
               + " | ".join(" / ".join(fmt(k, v) for v in PAPER[k]) for k in KEYS) + " | |")
    out.append("| straightforward reimplementation, seed 0 | "
               + " | ".join(" / ".join(fmt(k, v) for v in REFERENCE[k]) for k in KEYS) + " | |")
    phys = np.array([r["physics_rmse"] for r in per_seed])
    knn = np.array([r["knn3_rmse"] for r in per_seed])
    pcov = np.array([r["paper_fusion_coverage"] for r in per_seed])
    out.append("")
    out.append(f"- Physics-only test RMSE, mean over seeds: {' / '.join(f'{v:.5f}' for v in phys.mean(0))} uT; "
               f"hybrid / physics: {' / '.join(f'{v:.2f}' for v in (arr['rmse'] / phys).mean(0))}.")
    out.append(f"- Baseline without a network: physics + the mean residual of the 3 nearest training rows in "
               f"standardised (B, T), test RMSE mean over seeds {' / '.join(f'{v:.5f}' for v in knn.mean(0))} uT.")
    out.append("- Seeds with hybrid RMSE at or below the paper's, per axis: "
               + " / ".join(str(int(np.sum(arr['rmse'][:, a] <= PAPER['rmse'][a]))) for a in range(3))
               + f" of {args.seeds}; NLL at or below the paper's: "
               + " / ".join(str(int(np.sum(arr['nll'][:, a] <= PAPER['nll'][a]))) for a in range(3))
               + "; 95 % coverage inside 93-97 %: "
               + " / ".join(str(int(np.sum((arr['coverage'][:, a] >= 0.93) & (arr['coverage'][:, a] <= 0.97))))
                            for a in range(3)) + ".")
    out.append(f"- The paper's fusion (adds the physics aleatoric part again) on the same networks covers "
               f"{' / '.join(f'{100 * v:.1f}' for v in pcov.mean(0))} % on average.")
    out.append("")
    out.append("| timing (split seed 0) | seconds | paper s (Table 11) | paper / ours |")
    out.append("|---|---|---|---|")
    out.append(f"| training, 3 axes, cold (incl. jit compilation; epochs {' / '.join(map(str, epochs))}) | "
               f"{train_cold:.1f} | {PAPER_TRAIN_S} | {PAPER_TRAIN_S / train_cold:.0f}x |")
    out.append(f"| training, 3 axes, warm (compiled) | {train_warm:.1f} | {PAPER_TRAIN_S} | "
               f"{PAPER_TRAIN_S / train_warm:.0f}x |")
    out.append(f"| inference, {test.n} rows x 3 axes: physics UQ Np={cfg.uq.n_params} Nq={cfg.uq.n_qmc} + "
               f"M={net_cfg.mc_passes} passes + fusion, first call | {infer_cold:.3f} | {PAPER_INFER_S} | "
               f"{PAPER_INFER_S / infer_cold:.0f}x |")
    out.append(f"| same, median of {args.repeats} after warm-up | {infer_warm:.3f} | {PAPER_INFER_S} | "
               f"{PAPER_INFER_S / infer_warm:.0f}x |")
    print("\n".join(out))
    if args.json:
        Path(args.json).write_text(json.dumps({"per_seed": per_seed, "train_cold_s": train_cold,
                                               "train_warm_s": train_warm, "infer_cold_s": infer_cold,
                                               "infer_warm_s": infer_warm, "epochs_seed0": epochs}, indent=2))


def _split_scores(res) -> dict:
    """Hybrid (or physics) test scores of one job, with the domain flags and the transfer part."""
    m, data, split = res["metrics"], res["data"], res["split"]
    test = data.subset(split.test)
    level = m["uq"]["level"]
    pred = res["hybrid"][res["primary_likelihood"]] if "hybrid" in res else res["physics"].prediction
    lo, hi = pred.interval(level)
    y = test.b_ref
    miss = (y < lo) | (y > hi)
    out = res["domain"].outside(test, res["uq"].mean)
    dom = ~out.any(axis=1)
    n_miss = np.maximum(miss.sum(0), 1)
    return {"n": int(test.n), "n_in_domain": int(dom.sum()),
            "rmse": np.sqrt(np.mean((y - pred.mean) ** 2, axis=0)).tolist(),
            "coverage": (~miss).mean(0).tolist(),
            "coverage_in_domain": ((~miss[dom]).mean(0) if dom.any() else np.full(3, np.nan)).tolist(),
            "misses_flagged": ((miss & ~dom[:, None]).sum(0) / n_miss).tolist(),
            "covered_or_flagged": (1 - (miss & dom[:, None]).mean(0)).tolist(),
            "transfer_sd": [m["transfer"]["sd"][a] for a in AXES],
            "reasons": m["domain"].get("by_reason", {})}


def loro(args):
    """Leave-one-run-out over the recording's runs through the job (``split.kind = by_run``)."""
    base = load_config(args.config, ["output.figures=false", "output.progress=false", *args.set])
    runs = [int(r) for r in bm.load_dataset(base.data.source).runs]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in runs:
            c = load_config(args.config, ['split.kind="by_run"', f"split.test_runs=[{r}]", "output.figures=false",
                                          "output.progress=false", *args.set])
            rows.append({"run": r, **_split_scores(bm.run_job(c, Path(tmp) / f"r{r}"))})
    cmd = f"python benchmarks/bench_hybrid.py --loro --config {args.config}" + "".join(f" --set {s}" for s in args.set)
    f3 = lambda v, p=3: " / ".join(f"{x:.{p}g}" for x in v)                      # noqa: E731
    pc = lambda v: " / ".join("-" if np.isnan(x) else f"{100 * x:.0f}" for x in v)  # noqa: E731
    print(f"## Leave one run out (`{cmd}`)\n")
    print("| left-out run | test rows (in domain) | RMSE x / y / z (uT) | coverage x / y / z (%) | in-domain coverage (%) "
          "| misses flagged (%) | rows covered or flagged (%) | transfer sd (uT) | out-of-domain reasons |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['run']} | {r['n']} ({r['n_in_domain']}) | {f3(r['rmse'])} | {pc(r['coverage'])} | "
              f"{pc(r['coverage_in_domain'])} | {pc(r['misses_flagged'])} | {pc(r['covered_or_flagged'])} | "
              f"{f3(r['transfer_sd'])} | {', '.join(f'{k} {v}' for k, v in r['reasons'].items()) or '-'} |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


def accuracy_only(args):
    """Scores over split seeds 0..seeds-1 without the timing section."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.seeds):
            c = load_config(args.config, [f"split.seed={seed}", "output.figures=false", "output.progress=false",
                                          *args.set])
            res = bm.run_job(c, Path(tmp) / f"s{seed}")
            h = res["metrics"]["hybrid"][res["primary_likelihood"]]
            rows.append({"seed": seed, **{k: [h[k][a] for a in AXES] for k in KEYS},
                         "interval_scale": [res["metrics"]["network"]["training"][res["primary_likelihood"]][a]
                                            .get("interval_scale", 1.0) for a in AXES]})
    cmd = f"python benchmarks/bench_hybrid.py --no-timing --seeds {args.seeds} --config {args.config}"
    cmd += "".join(f" --set {s}" for s in args.set)
    print(f"## `{cmd}`\n")
    print("| split seed | RMSE x / y / z (uT) | coverage x / y / z (%) | NLL x / y / z | CRPS x / y / z (uT) "
          "| interval scale x / y / z |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['seed']} | " + " | ".join(" / ".join(fmt(k, v) for v in r[k]) for k in KEYS)
              + " | " + " / ".join(f"{v:.2f}" for v in r["interval_scale"]) + " |")
    arr = {k: np.array([r[k] for r in rows]) for k in KEYS}
    print("| **mean** | " + " | ".join(" / ".join(fmt(k, v) for v in arr[k].mean(0)) for k in KEYS) + " | |")
    cov = arr["coverage"]
    print("\n95 % coverage inside 93-97 % per axis: "
          + " / ".join(str(int(np.sum((cov[:, a] >= 0.93) & (cov[:, a] <= 0.97)))) for a in range(3))
          + f" of {args.seeds} seeds.")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
