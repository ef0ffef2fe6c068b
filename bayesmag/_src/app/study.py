"""The paper's simulation study (section 4) at scale: raw / physics / hybrid test RMSE by sample size.

For every size in ``[study] sizes``: simulate the sensor (``[data.simulate]``, with ``n`` set
to the size), split (``[split]``, the paper's 80/20), fit the physics model, stream the
physics uncertainty over the test rows in chunks, train the residual network on the
training residuals (``[network]``; batch size and epochs come from the config so they can
grow with the data), predict the test rows by MC DropConnect, and score. Writes
``simulation_study.json`` / ``.md`` (the paper's Table 12, with the noise floor),
``significance.json`` / ``.md`` (Table 13, the paired squared-error test, for every size),
``rmse_vs_size.png`` (Figure 6) and ``metrics.json`` (timings and peak memory).

The noise floor of axis ``a`` is the RMSE a perfect calibration would still have: the
measurement noise pushed through the true calibration matrix,
``noise_sd * sqrt(mean_i sum_j (S + Ks T_i)_aj^2)`` over the test rows.
"""

from __future__ import annotations

import dataclasses
import resource
import time
from pathlib import Path

import numpy as np

from bayesmag._src.core.jsonio import write_json
from bayesmag._src.core import metrics as M
from bayesmag._src.app.config import Config, ConfigError, config_error
from bayesmag._src.core.data import AXES, make_split
from bayesmag._src.core.fit import fit_physics
from bayesmag._src.app.job import build_model, uq_options
from bayesmag._src.app.outdir import staging_dir
from bayesmag._src.core.physics import inputs_from_data
from bayesmag._src.core.predictor import Components, Predictor, network_inputs

__all__ = ["run_study"]

PAPER_TABLE12 = {
    "50000": {"raw": [3.6807, 21.5638, 4.5241], "physics": [0.7971, 9.6876, 0.7448], "hybrid": [0.5532, 0.7847, 0.5657]},
    "100000": {"raw": [3.7163, 21.3935, 4.5685], "physics": [0.8002, 9.4931, 0.7415], "hybrid": [0.5588, 0.7975, 0.5729]},
    "200000": {"raw": [3.7061, 21.8569, 4.5585], "physics": [0.8108, 9.6005, 0.7473], "hybrid": [0.5522, 0.7551, 0.5746]},
    "500000": {"raw": [3.7228, 21.4943, 4.5719], "physics": [0.8009, 9.504, 0.7376], "hybrid": [0.5477, 0.7694, 0.5669]},
}


def _axes(v) -> dict:
    return {a: float(x) for a, x in zip(AXES, np.asarray(v, dtype=np.float64).reshape(3))}


def _noise_floor(sim: dict, test) -> dict:
    from bayesmag._src.core.simulate import TrueParams
    p = TrueParams.paper()
    g = p.S[None] + p.Ks[None] * test.temperature[:, None, None]        # (n, 3, 3)
    sd = float(sim.get("noise_sd", 0.5))
    return _axes(sd * np.sqrt(np.mean(np.sum(g**2, axis=2), axis=0)))


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def run_size(cfg: Config, size: int, *, progress: bool = False) -> dict:
    """Simulate ``size`` rows, calibrate and score; returns the per-size record."""
    from bayesmag._src.pipeline.hybrid import still_improving, train_network
    from bayesmag._src.core.simulate import simulate_from_config

    t = {}
    t0 = time.perf_counter()
    sim = {**cfg.data.simulate, "n": int(size)}
    data = simulate_from_config(sim)
    split = make_split(data, kind=cfg.split.kind, test_fraction=cfg.split.test_fraction, seed=cfg.split.seed)
    train, test = data.subset(split.train), data.subset(split.test)
    t["simulate"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    model = build_model(cfg, train)
    fit = fit_physics(train, model, covariance_method=cfg.physics.covariance)
    t["physics_fit"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    sigma_in = np.diag(np.r_[np.full(3, float(sim.get("noise_sd", 0.5))), max(float(sim.get("temp_noise_sd", 0.0)), 1e-3)] ** 2)
    physics = Predictor(fit=fit, sigma_in=sigma_in, residual_sd=np.zeros(3), uq=uq_options(cfg))
    uq = physics.physics_part(test, progress=progress)
    t["physics_uq"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    likelihood = cfg.network.likelihoods[0]
    over = dict(cfg.study.per_size.get(str(size), {}))
    valid = set(cfg.network.table())
    bad = sorted(set(over) - valid)
    if bad:
        raise ConfigError(f"Config key 'study.per_size.{size}' names unknown network setting(s) {bad}; "
                          f"valid: {sorted(valid)}.")
    try:
        net_cfg = dataclasses.replace(cfg.network, **over)
    except ValueError as e:
        raise config_error(e, f"study.per_size.{size}", valid) from None
    spec = net_cfg.spec(likelihood)
    r_train = train.b_ref - fit.predict(inputs_from_data(train))
    net = train_network(network_inputs(train), r_train, spec, net_cfg, groups=train.run)
    t["network_train"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    hyb = dataclasses.replace(physics, network=net, passes=net_cfg.mc_passes, network_seed=net_cfg.seed,
                              fusion=net_cfg.fusion)
    pred = hyb.compose(Components(uq, hyb.network_part(test)))      # the family and fusion of [network]
    t["network_predict"] = time.perf_counter() - t0

    info = net.info_dict()
    y = test.b_ref
    hybrid = pred.mean
    lo_, hi_ = pred.interval(cfg.uq.level)
    e_phys, e_hyb = y - uq.mean, y - hybrid
    sig = {ax: M.paired_test(e_phys[:, a], e_hyb[:, a]) for a, ax in enumerate(AXES)}
    return {
        "n": int(size), "n_train": int(train.n), "n_test": int(test.n),
        "raw": _axes(M.rmse(y, test.b_meas)), "physics": _axes(M.rmse(y, uq.mean)), "hybrid": _axes(M.rmse(y, hybrid)),
        "noise_floor": _noise_floor(sim, test),
        "hybrid_coverage": _axes(M.coverage(y, lo_, hi_)), "level": cfg.uq.level,
        "significance": {ax: {k: (v if not isinstance(v, (np.floating, np.integer)) else float(v))
                              for k, v in s.items()} for ax, s in sig.items()},
        "network": {"epochs_run": info, "likelihood": likelihood,
                    "still_improving": [ax for ax, i in info.items() if still_improving(i, net_cfg.max_epochs)],
                    "batch_size": net_cfg.batch_size, "max_epochs": net_cfg.max_epochs, "learning_rate": net_cfg.learning_rate},
        "seconds": {k: round(v, 3) for k, v in t.items()},
        "peak_rss_gb": round(_peak_rss_gb(), 3),
    }


def _table12_md(records: dict) -> str:
    lines = ["| size | axis | raw | physics | hybrid | noise floor | paper raw | paper physics | paper hybrid |",
             "|---|---|---|---|---|---|---|---|---|"]
    for size, r in records.items():
        paper = PAPER_TABLE12.get(size)
        for a, ax in enumerate(AXES):
            pp = [f"{paper[k][a]:.4f}" for k in ("raw", "physics", "hybrid")] if paper else ["", "", ""]
            lines.append(f"| {int(size):,} | {ax} | {r['raw'][ax]:.4f} | {r['physics'][ax]:.4f} | {r['hybrid'][ax]:.4f} "
                         f"| {r['noise_floor'][ax]:.4f} | " + " | ".join(pp) + " |")
    return "\n".join(lines) + "\n"


def _table13_md(records: dict) -> str:
    lines = ["| size | axis | mean diff (uT^2) | t | p (one-sided) | 95% CI | Cohen's d |", "|---|---|---|---|---|---|---|"]
    for size, r in records.items():
        for ax in AXES:
            s = r["significance"][ax]
            lines.append(f"| {int(size):,} | {ax} | {s['mean_diff']:.4f} | {s['t']:.2f} | {s['p']:.3g} | "
                         f"[{s['ci95'][0]:.4f}, {s['ci95'][1]:.4f}] | {s['cohens_d']:.4f} |")
    return "\n".join(lines) + "\n"


def _figure(path: Path, records: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    sizes = [int(s) for s in records]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for a, ax in enumerate(AXES):
        for stage, mk in (("raw", "o-"), ("physics", "s-"), ("hybrid", "^-"), ("noise_floor", "k--")):
            axes[a].plot(sizes, [records[s][stage][ax] for s in records], mk, label=stage.replace("_", " "))
        axes[a].set_xscale("log")
        axes[a].set_yscale("log")
        axes[a].set_xlabel("sample size")
        axes[a].set_ylabel("test RMSE (uT)")
        axes[a].set_title(f"{ax} axis")
    axes[0].legend(fontsize=8)
    fig.suptitle("RMSE vs sample size (simulated sensor)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_study(cfg: Config, out: str | Path, *, progress: bool = True) -> dict:
    """Run the study over ``cfg.study.sizes`` and write its tables and figure into ``out``."""
    if cfg.data.source != "simulated":
        raise ConfigError("[study] needs [data] source = \"simulated\" (the study simulates each size).")
    sizes = list(cfg.study.sizes)
    if not sizes or any((not isinstance(s, int)) or s < 100 for s in sizes):
        raise ConfigError(f"Config key 'study.sizes' = {sizes} must be a list of integers >= 100.")
    records, t_all = {}, time.perf_counter()
    it = sizes
    if progress:
        from tqdm.auto import tqdm
        it = tqdm(sizes, desc="simulation study", unit="size")
    for size in it:
        records[str(size)] = run_size(cfg, size, progress=False)
    summary = {"sizes": sizes, "seconds_total": round(time.perf_counter() - t_all, 2),
               "peak_rss_gb": round(_peak_rss_gb(), 3),
               "per_size": {s: {"seconds": r["seconds"], "peak_rss_gb": r["peak_rss_gb"],
                                "network": r["network"]} for s, r in records.items()}}
    short = {s: r["network"]["still_improving"] for s, r in records.items() if r["network"]["still_improving"]}
    summary["warnings"] = [f"size {int(s):,}: the network of axis {', '.join(ax)} stopped at max_epochs = "
                           f"{records[s]['network']['max_epochs']} with its validation loss still falling "
                           f"(under-trained; its hybrid RMSE is not the method's). Raise network.max_epochs or "
                           f"study.per_size.{s}.max_epochs." for s, ax in short.items()]
    table12 = {s: {k: r[k] for k in ("raw", "physics", "hybrid", "noise_floor")} for s, r in records.items()}
    table13 = {s: r["significance"] for s, r in records.items()}
    with staging_dir(Path(out), kind="study") as tmp:
        write_json(tmp / "simulation_study.json", table12)
        (tmp / "simulation_study.md").write_text("# Test RMSE (uT) by sample size (the paper's Table 12)\n\n"
                                                 + _table12_md(records)
                                                 + "".join(f"\nWARNING: {w}\n" for w in summary["warnings"]))
        write_json(tmp / "significance.json", table13)
        (tmp / "significance.md").write_text("# Paired test of physics vs hybrid squared errors (the paper's "
                                             "Table 13, every size)\n\n" + _table13_md(records))
        _figure(tmp / "rmse_vs_size.png", records)
        write_json(tmp / "metrics.json", {"records": records, **summary})
    return {"records": records, **summary}
