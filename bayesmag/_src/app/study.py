"""The paper's simulation study (section 4) at scale: raw / physics / hybrid test RMSE by sample size.

For every size in ``[study] sizes``: simulate the sensor (``[data.simulate]``, with ``n`` set
to the size), split (``[split]``, the paper's 80/20), fit the physics model, stream the
physics uncertainty over the test rows in chunks, train the residual network on the
training residuals (``[network]``; batch size and epochs come from the config so they can
grow with the data), predict the test rows by MC DropConnect, and score. Writes
``simulation_study.json`` / ``.md`` (the paper's Table 12, with the noise floor),
``significance.json`` / ``.md`` (Table 13, the paired squared-error test, for every size),
``rmse_vs_size.png`` (Figure 6) and ``metrics.json`` (timings and peak memory).

Settings the study does not follow are refused, not ignored (:func:`check_study_config`, run before any
computation): ``nuts.enabled = true`` and more than one ``network.likelihoods``. ``network.enabled = false``
runs the raw and physics columns only (no network, no Table 13); ``output.figures = false`` writes no figure.
Sizes too small for the configured network are refused naming the smallest size that fits it.

The paper's own numbers are printed next to the study's only where the config simulates the paper's sensor
(:func:`paper_comparable`: ``[data.simulate]`` equal to the paper's up to ``n`` and ``seed``, and the random
80/20 split); elsewhere the table says that the paper's columns do not apply.

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

__all__ = ["run_study", "check_study_config", "load_study_config", "paper_comparable"]

PAPER_TABLE12 = {
    "50000": {"raw": [3.6807, 21.5638, 4.5241], "physics": [0.7971, 9.6876, 0.7448], "hybrid": [0.5532, 0.7847, 0.5657]},
    "100000": {"raw": [3.7163, 21.3935, 4.5685], "physics": [0.8002, 9.4931, 0.7415], "hybrid": [0.5588, 0.7975, 0.5729]},
    "200000": {"raw": [3.7061, 21.8569, 4.5585], "physics": [0.8108, 9.6005, 0.7473], "hybrid": [0.5522, 0.7551, 0.5746]},
    "500000": {"raw": [3.7228, 21.4943, 4.5719], "physics": [0.8009, 9.504, 0.7376], "hybrid": [0.5477, 0.7694, 0.5669]},
}


#: the paper's section-4 simulation (``configs/paper_simulation.toml``); ``n`` and ``seed`` aside
PAPER_SIMULATE = {"design": "iid", "noise_sd": 0.5, "effects": [{"name": "axis_quadratic", "out": "y", "inp": "x",
                                                                 "coeff": 0.01}]}


def _normalised_simulation(sim: dict):
    """``[data.simulate]`` with every default filled in (``n`` and ``seed`` dropped), for comparison."""
    import inspect

    from bayesmag._src.core.simulate import _DESIGNS, get_effect
    design = sim.get("design", "iid")
    defaults = {k: p.default for k, p in inspect.signature(_DESIGNS[design]).parameters.items()
                if k not in ("n", "seed")}
    kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in {**defaults, **sim}.items() if k in defaults}
    sd = sim.get("noise_sd", 0.5)
    effects = []
    for item in sim.get("effects", ()):
        spec = {"name": item} if isinstance(item, str) else dict(item)
        effects.append(get_effect(spec.pop("name"), **spec))
    return (design, sim.get("params") in (None, "paper"), tuple(np.broadcast_to(np.asarray(sd, float), (3,))),
            float(sim.get("temp_noise_sd", 0.0)), kw, effects)


def paper_comparable(cfg: Config) -> bool:
    """Whether the paper's Table 12 numbers describe the same experiment as ``cfg``'s study: the config
    simulates the paper's sensor (``[data.simulate]`` equal to :data:`PAPER_SIMULATE` once defaults are
    filled in; ``n`` and ``seed`` may differ) and splits it at random 80/20 as the paper did."""
    if cfg.data.source != "simulated" or cfg.split.kind != "random" or abs(cfg.split.test_fraction - 0.2) > 1e-12:
        return False
    try:
        return _normalised_simulation(dict(cfg.data.simulate)) == _normalised_simulation(PAPER_SIMULATE)
    except (TypeError, ValueError, KeyError):
        return False


def _n_fit(cfg: Config, net_cfg, size: int) -> tuple[int, int]:
    """(training rows, network fitting rows) of ``size`` simulated rows: the split, then the validation rows."""
    tf = cfg.split.test_fraction
    n_train = size if cfg.split.kind == "none" else size - max(1, int(round(tf * size)))
    n_val = int(round(net_cfg.validation_fraction * n_train))
    return n_train, n_train - n_val


def _network_problem(cfg: Config, net_cfg, size: int) -> tuple[str, str] | None:
    """Why the residual network of ``net_cfg`` cannot be trained on ``size`` simulated rows and the setting
    that would fix it, or None
    (the checks of :func:`~bayesmag._src.core.network.train.check_network_size` and the validation rows)."""
    from bayesmag._src.core.network import MAX_PARAMS_PER_ROW, MIN_VALIDATION_ROWS
    n_train, n_fit = _n_fit(cfg, net_cfg, size)
    spec = net_cfg.spec(cfg.network.likelihoods[0])
    if n_train - n_fit < MIN_VALIDATION_ROWS:
        return (f"leaves {n_train - n_fit} validation rows of its {n_train} training rows "
                f"(network.validation_fraction = {net_cfg.validation_fraction}); early stopping needs at least "
                f"{MIN_VALIDATION_ROWS}", "a larger network.validation_fraction")
    if spec.n_params > MAX_PARAMS_PER_ROW * n_fit:
        return (f"leaves {n_fit} rows to fit the residual network ({spec.hidden_layers} hidden layers x {spec.width} "
                f"units, {spec.n_params} parameters per axis; at most {MAX_PARAMS_PER_ROW} per row)",
                "a smaller network (network.width, network.hidden_layers)")
    if spec.batch_size > n_fit:
        return (f"leaves {n_fit} rows to fit the residual network, fewer than its batch_size = {spec.batch_size}",
                "a smaller network.batch_size")
    return None


def _smallest_size(cfg: Config, net_cfg) -> int:
    """The smallest size whose rows train ``net_cfg`` (the checks are monotone in the size)."""
    lo, hi = 100, 100
    while _network_problem(cfg, net_cfg, hi) is not None:
        lo, hi = hi, hi * 2
        if hi > 10**9:
            return hi
    while lo < hi:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if _network_problem(cfg, net_cfg, mid) is None else (mid + 1, hi)
    return hi


def _per_size_network(cfg: Config, size: int):
    """``[network]`` with ``[study.per_size]`` overrides of ``size`` applied (ConfigError naming a bad one)."""
    over = dict(cfg.study.per_size.get(str(size), {}))
    valid = set(cfg.network.table())
    bad = sorted(set(over) - valid)
    if bad:
        raise ConfigError(f"Config key 'study.per_size.{size}' names unknown network setting(s) {bad}; "
                          f"valid: {sorted(valid)}.")
    try:
        return dataclasses.replace(cfg.network, **over)
    except ValueError as e:
        raise config_error(e, f"study.per_size.{size}", valid) from None


def check_study_config(cfg: Config) -> None:
    """ConfigError, before any computation, for a config the study cannot run as written: data that is not
    simulated, bad ``study.sizes`` or ``study.per_size``, sizes too small for the configured network (naming the
    smallest that fits), and settings the study would otherwise ignore (``nuts.enabled``, several
    ``network.likelihoods``)."""
    if cfg.data.source != "simulated":
        raise ConfigError("[study] needs [data] source = \"simulated\" (the study simulates each size).")
    sizes = cfg.study.sizes
    if (not isinstance(sizes, list) or not sizes
            or any(isinstance(s, bool) or not isinstance(s, int) or s < 100 for s in sizes)):
        raise ConfigError(f"Config key 'study.sizes' = {sizes!r} must be a list of integers >= 100.")
    if len(set(sizes)) != len(sizes):
        raise ConfigError(f"Config key 'study.sizes' = {sizes} names a size twice; give each size once.")
    if cfg.nuts.enabled:
        raise ConfigError("Config key 'nuts.enabled' = true: the study does not run NUTS (it scores raw, physics and "
                          "hybrid by size); set nuts.enabled = false, or use `bayesmag run` for the NUTS cross-check.")
    if not cfg.network.enabled:
        return
    if len(cfg.network.likelihoods) != 1:
        raise ConfigError(f"Config key 'network.likelihoods' = {list(cfg.network.likelihoods)}: the study trains one "
                          f"network family per size; name one, e.g. network.likelihoods = "
                          f"[\"{cfg.network.likelihoods[0]}\"].")
    for size in sizes:
        net_cfg = _per_size_network(cfg, size)
        why = _network_problem(cfg, net_cfg, size)
        if why is not None:
            smallest = _smallest_size(cfg, net_cfg)
            raise ConfigError(
                f"Config key 'study.sizes' = {sizes}: size {size:,} {why[0]}. The smallest size this [network] "
                f"trains on is {smallest:,}: use sizes >= {smallest}, {why[1]}"
                f"{' (for one size: study.per_size)' if len(sizes) > 1 else ''}, or network.enabled = false "
                f"(raw and physics only).")


def load_study_config(path, overrides: list[str] = ()) -> Config:
    """The config of ``bayesmag study``: :func:`~bayesmag._src.app.config.load_config` plus
    :func:`check_study_config`; a config without a ``[study]`` table (nor a ``study.*`` override) is refused
    rather than run at the paper's default sizes (50k-500k rows, long for a config not made for them)."""
    from bayesmag._src.app.config import config_from_dict, read_config_dict, resolve_config_path
    path = resolve_config_path(str(path))
    raw = read_config_dict(path, list(overrides))
    if not isinstance(raw.get("study"), dict):
        raise ConfigError(f"{path} has no [study] table: name the sizes to simulate, e.g. "
                          f"--set 'study.sizes=[5000, 20000]' (or add a [study] table with sizes = [...]); "
                          f"`bayesmag study paper_simulation` is the paper's study (50k-500k rows).")
    cfg = config_from_dict(raw)
    check_study_config(cfg)
    return cfg


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
    physics = Predictor(fit=fit, sigma_in=sigma_in, residual_sd=np.zeros(3), uq=uq_options(cfg), level=cfg.uq.level)
    uq = physics.physics_part(test, progress=progress)
    t["physics_uq"] = time.perf_counter() - t0

    y = test.b_ref
    record = {
        "n": int(size), "n_train": int(train.n), "n_test": int(test.n),
        "raw": _axes(M.rmse(y, test.b_meas)), "physics": _axes(M.rmse(y, uq.mean)),
        "noise_floor": _noise_floor(sim, test),
    }
    if cfg.network.enabled:
        record.update(_hybrid(cfg, size, train, test, fit, physics, uq, t))
    record["seconds"] = {k: round(v, 3) for k, v in t.items()}
    record["peak_rss_gb"] = round(_peak_rss_gb(), 3)
    return record


def _hybrid(cfg: Config, size: int, train, test, fit, physics, uq, t: dict) -> dict:
    """Train the residual network of ``size`` and score the hybrid on the test rows."""
    from bayesmag._src.pipeline.hybrid import still_improving, train_network

    t0 = time.perf_counter()
    likelihood = cfg.network.likelihoods[0]
    net_cfg = _per_size_network(cfg, size)
    spec = net_cfg.spec(likelihood)
    r_train = train.b_ref - fit.predict(inputs_from_data(train))
    try:
        net = train_network(network_inputs(train), r_train, spec, net_cfg, groups=train.run)
    except ValueError as e:             # settings that do not fit this size's rows (checked at load for most)
        raise ConfigError(f"Config key 'study.sizes': size {size:,}: {e}") from None
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
        "hybrid": _axes(M.rmse(y, hybrid)),
        "hybrid_coverage": _axes(M.coverage(y, lo_, hi_)), "level": cfg.uq.level,
        "significance": {ax: {k: (v if not isinstance(v, (np.floating, np.integer)) else float(v))
                              for k, v in s.items()} for ax, s in sig.items()},
        "network": {"epochs_run": info, "likelihood": likelihood,
                    "still_improving": [ax for ax, i in info.items() if still_improving(i, net_cfg.max_epochs)],
                    "batch_size": net_cfg.batch_size, "max_epochs": net_cfg.max_epochs, "learning_rate": net_cfg.learning_rate},
    }


def _table12_md(records: dict, *, paper: bool, network: bool) -> str:
    """Table 12 as markdown: the stages run (hybrid only with the network), the paper's numbers only when
    ``paper`` (the config simulates the paper's sensor: :func:`paper_comparable`)."""
    stages = ("raw", "physics", "hybrid") if network else ("raw", "physics")
    head = ["size", "axis", *stages, "noise floor"] + ([f"paper {k}" for k in stages] if paper else [])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for size, r in records.items():
        pp = PAPER_TABLE12.get(size)
        for a, ax in enumerate(AXES):
            row = [f"{int(size):,}", ax, *(f"{r[k][ax]:.4f}" for k in stages), f"{r['noise_floor'][ax]:.4f}"]
            if paper:
                row += [f"{pp[k][a]:.4f}" for k in stages] if pp else [""] * len(stages)
            lines.append("| " + " | ".join(row) + " |")
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
            if stage not in records[next(iter(records))]:
                continue                                    # network.enabled = false: no hybrid
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
    """Run the study over ``cfg.study.sizes`` and write its tables and figure into ``out``
    (:func:`check_study_config` first: nothing is computed for a config it refuses)."""
    check_study_config(cfg)
    sizes = list(cfg.study.sizes)
    network, paper = cfg.network.enabled, paper_comparable(cfg)
    records, t_all = {}, time.perf_counter()
    it = sizes
    if progress:
        from tqdm.auto import tqdm
        it = tqdm(sizes, desc="simulation study", unit="size")
    for size in it:
        records[str(size)] = run_size(cfg, size, progress=False)
    summary = {"sizes": sizes, "seconds_total": round(time.perf_counter() - t_all, 2),
               "peak_rss_gb": round(_peak_rss_gb(), 3), "network": network, "paper_comparable": paper,
               "per_size": {s: {k: r[k] for k in ("seconds", "peak_rss_gb", "network") if k in r}
                            for s, r in records.items()}}
    short = {s: r["network"]["still_improving"] for s, r in records.items()
             if network and r["network"]["still_improving"]}
    summary["warnings"] = [f"size {int(s):,}: the network of axis {', '.join(ax)} stopped at max_epochs = "
                           f"{records[s]['network']['max_epochs']} with its validation loss still falling "
                           f"(under-trained; its hybrid RMSE is not the method's). Raise network.max_epochs or "
                           f"study.per_size.{s}.max_epochs." for s, ax in short.items()]
    stages = ("raw", "physics", "hybrid", "noise_floor") if network else ("raw", "physics", "noise_floor")
    table12 = {s: {k: r[k] for k in stages} for s, r in records.items()}
    shown = paper and any(str(s) in PAPER_TABLE12 for s in sizes)     # the paper's columns, where it has a size
    if shown:
        title = "# Test RMSE (uT) by sample size, with the paper's Table 12\n\n"
    elif paper:
        title = ("# Test RMSE (uT) by sample size\n\nThe paper's Table 12 has none of these sizes (it has "
                 + ", ".join(f"{int(k):,}" for k in PAPER_TABLE12) + ").\n\n")
    else:
        title = ("# Test RMSE (uT) by sample size\n\nThis config does not simulate the paper's sensor (section 4: "
                 "design iid, noise_sd 0.5, By += 0.01 Bx^2, random 80/20 split), so the paper's Table 12 numbers "
                 "are not comparable and are not shown.\n\n")
    if not network:
        title += "network.enabled = false: raw and physics only (no hybrid, no significance test).\n\n"
    with staging_dir(Path(out), kind="study") as tmp:
        write_json(tmp / "simulation_study.json", table12)
        (tmp / "simulation_study.md").write_text(title + _table12_md(records, paper=shown, network=network)
                                                 + "".join(f"\nWARNING: {w}\n" for w in summary["warnings"]))
        if network:
            table13 = {s: r["significance"] for s, r in records.items()}
            write_json(tmp / "significance.json", table13)
            (tmp / "significance.md").write_text("# Paired test of physics vs hybrid squared errors (the paper's "
                                                 "Table 13, every size)\n\n" + _table13_md(records))
        if cfg.output.figures:
            _figure(tmp / "rmse_vs_size.png", records)
        write_json(tmp / "metrics.json", {"records": records, **summary})
    return {"records": records, **summary}
