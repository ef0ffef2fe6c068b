"""Figures a user would rather look at than read (matplotlib, Agg backend, PNG files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bayesmag._src.app.figure_layout import fixed_layout, plt  # pyplot (Agg) imported at the first figure
from bayesmag._src.core.data import AXES

__all__ = ["residual_interval_figure", "residual_histograms", "residuals_vs",
           "residuals_vs_time", "residual_figures", "physics_figures", "residual_histogram_figure",
           "calibration_curve_figure", "pit_figure", "draw_calibration_curves", "FigureWorker", "InlineFigures",
           "draw_file", "run_tasks", "by_cost", "residual_figure_tasks", "physics_figure_tasks",
           "residual_histogram_task"]


def residual_interval_figure(path: Path, reference: np.ndarray, predicted: np.ndarray, lower: np.ndarray,
                             upper: np.ndarray, *, level: float = 0.95, max_points: int = 600, seed: int = 0,
                             title: str = "Calibrated - reference, with the prediction interval") -> float:
    """Per axis: error ``predicted - reference`` (uT) against the reference, each row with its central
    interval as a bar (``[lower, upper] - reference``): a bar that crosses 0 covers the reference.

    At most ``max_points`` rows are drawn (a seeded random subset, the same for every axis); each
    panel's title gives the coverage of all rows. Returns the mean coverage over the axes.
    """
    reference, predicted = np.asarray(reference), np.asarray(predicted)
    n = len(reference)
    pick = np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False)) if n > max_points else np.arange(n)
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.3))
    covs = []
    for a, ax in enumerate(axes):
        r, e = reference[:, a], predicted[:, a] - reference[:, a]
        lo, hi = np.asarray(lower)[:, a] - reference[:, a], np.asarray(upper)[:, a] - reference[:, a]
        cov = (lo <= 0) & (hi >= 0)
        covs.append(cov.mean())
        for mask, colour, lab in ((cov[pick], "C0", "interval covers the reference"),
                                  (~cov[pick], "C3", "interval misses")):
            idx = pick[mask]
            if idx.size:
                ax.errorbar(r[idx], e[idx], yerr=[e[idx] - lo[idx], hi[idx] - e[idx]], fmt="o", ms=2, lw=0.6,
                            alpha=0.6, color=colour, label=f"{lab} ({idx.size} drawn)")
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel(f"reference B{AXES[a]} (uT)")
        ax.set_ylabel(f"calibrated - reference B{AXES[a]} (uT)")
        ax.set_title(f"{AXES[a]} axis: RMSE {np.sqrt(np.mean(e**2)):.3g} uT, {cov.mean():.1%} covered", fontsize=9)
    axes[0].legend(fontsize=7, loc="upper left")
    fig.suptitle(f"{title} ({level:.0%}; {min(n, max_points)} of {n} test rows drawn)")
    fixed_layout(fig)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return float(np.mean(covs))


def calibration_curve_figure(path: Path, pits: dict[str, np.ndarray],
                             title: str = "Calibration of central intervals (test rows)") -> None:
    """Per axis: observed against nominal coverage of central intervals, from PIT values ``(n, 3)`` per name
    (``y`` is in the central interval of level l iff ``|PIT - 1/2| <= l/2``)."""
    draw_calibration_curves(path, _coverage_curves(pits), title)


def _coverage_curves(pits: dict[str, np.ndarray]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Nominal levels and observed coverage ``(L, 3)`` of central intervals, from PIT values per name."""
    from bayesmag._src.core.metrics import DEFAULT_LEVELS
    levels = np.asarray(DEFAULT_LEVELS)
    return {name: (levels, np.stack([np.mean(np.abs(np.asarray(u) - 0.5) <= lv / 2, axis=0) for lv in levels]))
            for name, u in pits.items()}


def draw_calibration_curves(path: Path, curves: dict[str, tuple[np.ndarray, np.ndarray]], title: str) -> None:
    """Per axis: observed ``(L, 3)`` against nominal ``(L,)`` coverage, one line per name; written to ``path``."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.0))
    for a, ax in enumerate(axes):
        ax.plot([0, 1], [0, 1], color="0.6", lw=1)
        for name, (nominal, observed) in curves.items():
            ax.plot(nominal, observed[:, a], marker="o", ms=3, label=name)
        ax.set_xlabel("nominal level")
        ax.set_ylabel("observed coverage")
        ax.set_title(f"{AXES[a]} axis")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fixed_layout(fig)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def pit_figure(path: Path, pits: dict[str, np.ndarray], bins: int = 10,
               title: str = "PIT histograms (flat = calibrated)", *, pad: float = 0.4) -> None:
    """Rows: names; columns: axes; histogram of PIT values ``(n, 3)``, dashed line the uniform density
    (``pad``: inches of height above the rows, for the title)."""
    names = list(pits)
    fig, axes = plt.subplots(len(names), 3, figsize=(12, 2.8 * len(names) + pad), squeeze=False)
    for i, name in enumerate(names):
        for a in range(3):
            ax = axes[i, a]
            ax.hist(np.asarray(pits[name])[:, a], bins=bins, range=(0, 1), density=True, alpha=0.8)
            ax.axhline(1.0, color="k", ls="--", lw=0.8)
            ax.set_title(f"{name}, {AXES[a]} axis", fontsize=9)
            ax.set_xlim(0, 1)
            ax.set_xlabel("PIT value F(y)")
            ax.set_ylabel("density")
    fig.suptitle(title)
    fixed_layout(fig)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def residual_histograms(path: Path, residuals: dict[str, np.ndarray], title: str = "Test residuals") -> None:
    """Per axis: histograms of residuals (reference - prediction) for each named stage."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for a, ax in enumerate(axes):
        for name, r in residuals.items():
            ra = r[:, a]
            ax.hist(ra, bins=40, alpha=0.55, label=f"{name} (sd {ra.std():.3g})")
        ax.axvline(0, color="k", lw=0.8)
        ax.set_xlabel(f"residual B{AXES[a]} (uT)")
        ax.set_ylabel("count")
        ax.set_title(f"{AXES[a]} axis")
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fixed_layout(fig)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _band_panel(ax, x, r, sd, k: float = 2.0) -> float:
    """Residuals against x with the +-k sd band (sorted by x); returns the fraction inside the band."""
    order = np.argsort(x)
    ax.scatter(x, r, s=4, alpha=0.6, color="C0", label="residual", zorder=2)
    ax.fill_between(x[order], -k * sd[order], k * sd[order], color="C1", alpha=0.25, lw=0, label=f"+-{k:g} sd", zorder=0)
    ax.axhline(0, color="k", lw=0.6)
    return float(np.mean(np.abs(r) <= k * sd))


def residuals_vs(x: np.ndarray, residual: np.ndarray, sd: np.ndarray, *, xlabels, title: str):
    """Residual (reference - physics, uT) of each axis against each column of ``x`` (n, m), +-2 sd band.

    Rows: output axes; columns: the variables in ``x`` (labelled ``xlabels``). Returns the figure;
    each panel's title gives the share of rows inside the band (about 95% when sd is right).
    """
    x = np.asarray(x, dtype=np.float64).reshape(len(residual), -1)
    m = x.shape[1]
    fig, axes = plt.subplots(3, m, figsize=(4.2 * m + 0.5, 8.4), squeeze=False)
    for a in range(3):
        for j in range(m):
            ax = axes[a, j]
            inside = _band_panel(ax, x[:, j], residual[:, a], sd[:, a])
            ax.set_title(f"{AXES[a]} axis: {inside:.1%} inside +-2 sd", fontsize=9)
            ax.set_xlabel(xlabels[j])
            ax.set_ylabel(f"residual B{AXES[a]} (uT)")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    fig.suptitle(title)
    fixed_layout(fig)
    return fig


def residuals_vs_time(time: np.ndarray, run: np.ndarray, residual: np.ndarray, sd: np.ndarray, *,
                      train: tuple | None = None, max_runs: int = 8,
                      title: str = "Physics residuals vs time, per run"):
    """Residual against time since the start of each run (its first row, train or test): rows axes,
    columns runs (first ``max_runs``). Test rows with the +-2 sd band; ``train = (time, run, residual)``
    adds the run's training rows, marked (grey crosses), so every row of the run is shown."""
    t_tr, r_tr, e_tr = (np.asarray(x) for x in train) if train is not None else (np.empty(0), np.empty(0),
                                                                                 np.empty((0, 3)))
    all_runs = np.unique(np.concatenate([np.asarray(run), r_tr]))
    runs = all_runs[:max_runs]
    fig, axes = plt.subplots(3, len(runs), figsize=(3.2 * len(runs) + 0.8, 8.4), squeeze=False, sharey="row")
    for j, r in enumerate(runs):
        sel, sel_tr = run == r, r_tr == r
        start = min(np.min(time[sel]) if sel.any() else np.inf, np.min(t_tr[sel_tr]) if sel_tr.any() else np.inf)
        for a in range(3):
            ax = axes[a, j]
            if sel_tr.any():
                ax.scatter(t_tr[sel_tr] - start, e_tr[sel_tr, a], s=4, marker="x", lw=0.5, color="0.55", alpha=0.6,
                           label="train rows", zorder=1)
            if sel.any():
                inside = _band_panel(ax, time[sel] - start, residual[sel, a], sd[sel, a])
                ax.set_title(f"run {int(r)}, {AXES[a]}: test {inside:.0%} in band", fontsize=8)
            else:
                ax.set_title(f"run {int(r)}, {AXES[a]}: no test rows", fontsize=8)
            ax.set_xlabel("time since run start (s)")
            if j == 0:
                ax.set_ylabel(f"residual B{AXES[a]} (uT)")
    axes[0, 0].legend(fontsize=6, loc="upper right", markerscale=2)
    fig.suptitle(title + " (test rows: dots with +-2 sd band; train rows: crosses)"
                 + ("" if len(all_runs) <= max_runs else f" (first {max_runs} runs)"))
    fixed_layout(fig, wspace=0.45)   # shared y: tick labels on the first column only
    return fig


def _save(fig, path: Path) -> None:
    fig.savefig(path, dpi=100)
    plt.close(fig)


def draw_file(folder: Path, name: str, draw, *args, **kwargs):
    """``draw(folder / name, *args, **kwargs)``: one figure file as a task ``(draw_file, (name, draw, ...), {})``
    that :class:`FigureWorker` or :class:`InlineFigures` runs with the folder (module level, picklable)."""
    return draw(Path(folder) / name, *args, **kwargs)


def run_tasks(out: Path, tasks: list) -> None:
    """Draw figure tasks ``(draw, args, kwargs)`` into ``out`` here, in order."""
    for draw, args, kwargs in tasks:
        draw(Path(out), *args, **kwargs)


#: Relative drawing time of a job's figures (CPU seconds, paper_hybrid on the 2-core machine,
#: ``benchmarks/bench_figures.py --tasks``): the most expensive go first, so that two processes
#: sharing the queue finish together.
_COST = {"physics_residuals_vs_time.png": 1.12, "physics_residuals_vs_reference.png": 0.57,
         "hybrid_uncertainty_vs_temperature.png": 0.42, "residual_histograms.png": 0.40,
         "hybrid_residuals_vs_reference.png": 0.31, "calibration.png": 0.30, "network_loss.png": 0.23,
         "physics_pit.png": 0.22, "physics_residuals_vs_temperature.png": 0.22}


def by_cost(tasks: list) -> list:
    """Figure tasks sorted by :data:`_COST` of the file they draw, the most expensive first (stable)."""
    def cost(t):
        draw, args, _ = t
        return -_COST.get(args[0], 0.2) if draw is draw_file and args else -0.2
    return sorted(tasks, key=cost)


def residuals_vs_figure(path: Path, x, residual, sd, *, xlabels, title: str) -> None:
    """:func:`residuals_vs` written to ``path``."""
    _save(residuals_vs(x, residual, sd, xlabels=xlabels, title=title), path)


def residuals_vs_time_figure(path: Path, time, run, residual, sd, *, train: tuple | None = None,
                             title: str = "Physics residuals vs time, per run") -> None:
    """:func:`residuals_vs_time` written to ``path``."""
    _save(residuals_vs_time(time, run, residual, sd, train=train, title=title), path)


def residual_figure_tasks(data, predicted: np.ndarray, sd: np.ndarray, *, stage: str = "physics",
                          train: tuple | None = None) -> list:
    """The three figures of :func:`residual_figures` as tasks (plain arrays: no JAX needed to draw them)."""
    r = np.asarray(data.b_ref) - np.asarray(predicted)
    sd, t = np.asarray(sd), np.asarray(data.temperature)
    train = None if train is None else tuple(np.asarray(x) for x in train)
    name = stage.capitalize()
    return [
        (draw_file, (f"{stage}_residuals_vs_temperature.png", residuals_vs_figure, t, r, sd),
         {"xlabels": ["temperature (C)"], "title": f"{name} residuals vs temperature (test rows)"}),
        (draw_file, (f"{stage}_residuals_vs_time.png", residuals_vs_time_figure, np.asarray(data.time),
                     np.asarray(data.run), r, sd), {"train": train, "title": f"{name} residuals vs time, per run"}),
        (draw_file, (f"{stage}_residuals_vs_reference.png", residuals_vs_figure, np.asarray(data.b_ref), r, sd),
         {"xlabels": [f"reference B{a} (uT)" for a in AXES],
          "title": f"{name} residuals vs the reference field (test rows)"}),
    ]


def residual_figures(out: Path, data, predicted: np.ndarray, sd: np.ndarray, *, stage: str = "physics",
                     train: tuple | None = None) -> list[str]:
    """Belsten-style residual diagnostics of the rows in ``data`` (with reference): vs temperature, vs time per
    run (with the training rows ``train = (time, run, residual)`` marked), vs each reference field component,
    each with the +-2 sd band of the predictive uncertainty."""
    tasks = residual_figure_tasks(data, predicted, sd, stage=stage, train=train)
    run_tasks(out, tasks)
    return [args[0] for _, args, _ in tasks]


def physics_figure_tasks(test, columns: dict, extra: dict | None = None) -> list:
    """The figures of :func:`physics_figures` as tasks ``(draw, args, kwargs)`` (plain arrays)."""
    extra = extra or {}
    level = extra.get("level", 0.95)
    col = {k: np.asarray(columns[k]) for k in ("reference", "predicted", "lower", "upper", "total")}
    tasks = [(draw_file, ("calibration.png", residual_interval_figure, col["reference"], col["predicted"],
                          col["lower"], col["upper"]),
              {"level": level, "title": "Physics: calibrated - reference, with the prediction interval"})]
    tr = extra.get("train")
    train = (tr.time, tr.run, extra["train_residual"]) if tr is not None else None
    tasks += residual_figure_tasks(test, col["predicted"], col["total"], train=train)
    if extra.get("pit") is not None:
        pits = {"physics": np.asarray(extra["pit"])}
        tasks += [(draw_file, ("physics_calibration.png", draw_calibration_curves, _coverage_curves(pits),
                               "Physics stage: calibration of central intervals (test rows)"), {}),
                  (draw_file, ("physics_pit.png", pit_figure, pits),
                   {"title": "Physics stage: PIT histograms (flat = calibrated)"})]
    return tasks


def physics_figures(out: Path, test, columns: dict, extra: dict | None = None) -> None:
    """The physics stage's figures of a job: error with interval bars against the reference, residual
    diagnostics of the test rows (training rows marked on the time axis), and, given the PIT values,
    the physics calibration curve and PIT histograms.

    ``extra``: ``train`` (CalibrationData) and ``train_residual`` (n_train, 3), ``pit`` (n_test, 3), ``level``.
    """
    run_tasks(out, physics_figure_tasks(test, columns, extra))


def residual_histogram_task(reference: np.ndarray, physics: np.ndarray, hybrid: np.ndarray | None = None) -> tuple:
    """``residual_histograms.png`` (test residuals of the physics and, when given, hybrid predictions) as a task."""
    ref = np.asarray(reference)
    res = {"physics": ref - np.asarray(physics)}
    if hybrid is not None:
        res["hybrid"] = ref - np.asarray(hybrid)
    return (draw_file, ("residual_histograms.png", residual_histograms, res), {})


def residual_histogram_figure(out: Path, result, columns: dict) -> None:
    """Histograms of the test residuals of the physics and (when there) hybrid predictions."""
    run_tasks(out, [residual_histogram_task(columns["reference"], result["uq"].mean, columns.get("hybrid_predicted"))])


from bayesmag._src.app.figure_worker import FigureWorker, InlineFigures  # noqa: E402  (moved there; kept importable here)
