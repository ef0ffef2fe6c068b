"""Figures as tasks (app/plots.py, hybrid_plots.py, network_plots.py, figure_worker.py): the command line's
worker process and this process share them; the files and their pixels are those drawn in-process."""

from __future__ import annotations

import numpy as np
import pytest

from bayesmag._src.app.config import config_from_dict
from bayesmag._src.app.job import run_job

SMALL_HYBRID = {
    "name": "small_hybrid",
    "data": {"source": "simulated",
             "simulate": {"design": "iid", "n": 600, "seed": 0, "noise_sd": 0.05,
                          "effects": [{"name": "axis_quadratic", "coeff": 0.01}]}},
    "split": {"kind": "random", "test_fraction": 0.2, "seed": 0},
    "uq": {"n_params": 50, "n_qmc": 64},
    "network": {"enabled": True, "likelihoods": ["gaussian", "laplace"], "hidden_layers": 2, "width": 8,
                "max_epochs": 15, "mc_passes": 5, "interval_calibration": "none"},
    "output": {"progress": False},
}

FIGURES = {"calibration.png", "physics_residuals_vs_temperature.png", "physics_residuals_vs_time.png",
           "physics_residuals_vs_reference.png", "physics_calibration.png", "physics_pit.png",
           "hybrid_residuals_vs_reference.png", "hybrid_uncertainty_vs_temperature.png", "hybrid_calibration.png",
           "hybrid_pit.png", "network_loss.png", "residual_histograms.png"}


def _untimed(x):
    """``x`` without what measures or stamps time."""
    if isinstance(x, dict):
        return {k: _untimed(v) for k, v in x.items() if k not in ("timings", "train_seconds", "seconds", "date_utc")}
    return [_untimed(v) for v in x] if isinstance(x, list) else x


def _pixels(path):
    from PIL import Image
    return np.asarray(Image.open(path).convert("RGBA"))


@pytest.mark.extended
def test_worker_and_in_process_draw_the_same_figures_pixel_for_pixel(tmp_path):
    """The job's twelve figures, shared with the worker process (command line) or drawn here (library):
    the same files with identical pixels, and the same metrics."""
    from bayesmag._src.app.figure_worker import JOB_BARE, JOB_MODULES, FigureWorker
    cfg = config_from_dict(SMALL_HYBRID)
    here = run_job(cfg, tmp_path / "inline")
    with FigureWorker(preload=JOB_MODULES, bare=JOB_BARE) as worker:   # as the command line: started first
        worker.warm()
        shared = run_job(cfg, tmp_path / "worker", figure_worker=worker)
        assert worker.pid is not None and worker._proc.poll() is None
    pngs = {p.name for p in (tmp_path / "inline").glob("*.png")}
    assert pngs == FIGURES and {p.name for p in (tmp_path / "worker").glob("*.png")} == FIGURES
    for name in sorted(FIGURES):
        np.testing.assert_array_equal(_pixels(tmp_path / "inline" / name), _pixels(tmp_path / "worker" / name),
                                      err_msg=name)
    assert _untimed(here["metrics"]) == _untimed(shared["metrics"])


def test_figure_tasks_are_plain_data_and_the_most_expensive_go_first():
    """Tasks carry NumPy arrays only (a figure process never needs JAX); by_cost puts the costly first."""
    import pickle

    import jax.numpy as jnp

    import bayesmag
    from bayesmag._src.app import plots
    d = bayesmag.simulate.simulate(200, design="iid", seed=1)
    cols = {k: jnp.asarray(d.b_ref) for k in ("reference", "predicted", "lower", "upper")}
    cols["total"] = jnp.ones((200, 3))
    tasks = plots.physics_figure_tasks(d, cols, {"train": d, "train_residual": np.zeros((200, 3)),
                                                 "pit": jnp.full((200, 3), 0.5), "level": 0.9})
    tasks.append(plots.residual_histogram_task(d.b_ref, jnp.asarray(d.b_ref)))

    def leaves(x):
        if isinstance(x, dict):
            return [y for v in x.values() for y in leaves(v)]
        if isinstance(x, (list, tuple)):
            return [y for v in x for y in leaves(v)]
        return [x]
    assert not [x for t in tasks for x in leaves(t[1:]) if type(x).__module__.startswith("jax")]
    pickle.dumps(tasks)
    names = [args[0] for _, args, _ in plots.by_cost(tasks)]
    assert names[0] == "physics_residuals_vs_time.png" and len(names) == 7 == len(set(names))
    assert names.index("physics_residuals_vs_reference.png") < names.index("physics_calibration.png")


@pytest.mark.parametrize("value, on", [(None, True), ("1", True), ("0", False), ("off", False)])
def test_the_command_shares_figures_with_a_worker_unless_told_not_to(monkeypatch, value, on):
    from bayesmag._src.app.cli import _figure_worker
    if value is None:
        monkeypatch.delenv("BAYESMAG_FIGURE_WORKER", raising=False)
    else:
        monkeypatch.setenv("BAYESMAG_FIGURE_WORKER", value)
    assert _figure_worker() is on
