"""Files of the hybrid stage (application layer): the likelihood comparison and the figures."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bayesmag._src.core import metrics as M
from bayesmag._src.core.jsonio import write_json
from bayesmag._src.pipeline.hybrid import HybridStage, comparison_markdown, comparison_records

__all__ = ["hybrid_writers", "hybrid_figure_tasks"]


def hybrid_writers(cfg, hs: HybridStage, columns: dict, test, level: float, *, figures: bool = True) -> list:
    """Writers ``f(folder)`` of the stage's files: likelihood comparison (several likelihoods), figures
    (with ``cfg.output.figures`` and ``figures``; :func:`hybrid_figure_tasks` gives them as tasks instead)."""
    writers = []
    if len(hs.specs) > 1:
        scores = {name: M.score_per_axis(test.b_ref, p.dist, level, mean=p.mean) for name, p in hs.predictions.items()}
        md = comparison_markdown(scores, fusion=hs.fusion, level=level, n_test=test.n)
        records = comparison_records(scores)

        def write_comparison(out: Path) -> None:
            (Path(out) / "likelihood_comparison.md").write_text(md)
            write_json(Path(out) / "likelihood_comparison.json", records)

        writers.append(write_comparison)
    if cfg.output.figures and figures:
        def write_figures(out: Path) -> None:
            from bayesmag._src.app.plots import run_tasks
            run_tasks(out, hybrid_figure_tasks(hs, columns, test, level))

        writers.append(write_figures)
    return writers


def hybrid_figure_tasks(hs: HybridStage, columns: dict, test, level: float) -> list:
    """The stage's figures as tasks ``(draw, args, kwargs)`` for a figure drawer (plain arrays only):
    :func:`~bayesmag._src.app.hybrid_plots.hybrid_figure_tasks` and the training loss curves."""
    from bayesmag._src.app.hybrid_plots import hybrid_figure_tasks as figure_tasks
    from bayesmag._src.app.network_plots import loss_curve_task
    dists = {name: p.dist for name, p in hs.predictions.items()}
    return figure_tasks(columns, np.asarray(test.temperature), dists, level=level) + [loss_curve_task(hs.networks)]
