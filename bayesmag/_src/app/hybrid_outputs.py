"""Files of the hybrid stage (application layer): the likelihood comparison and the figures."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bayesmag._src.core import metrics as M
from bayesmag._src.core.jsonio import write_json
from bayesmag._src.pipeline.hybrid import HybridStage, comparison_markdown, comparison_records

__all__ = ["hybrid_writers"]


def hybrid_writers(cfg, hs: HybridStage, columns: dict, test, level: float) -> list:
    """Writers ``f(folder)`` of the stage's files: likelihood comparison (several likelihoods), figures
    (with ``cfg.output.figures``)."""
    writers = []
    if len(hs.specs) > 1:
        scores = {name: M.score_per_axis(test.b_ref, p.dist, level, mean=p.mean) for name, p in hs.predictions.items()}
        md = comparison_markdown(scores, fusion=hs.fusion, level=level, n_test=test.n)
        records = comparison_records(scores)

        def write_comparison(out: Path) -> None:
            (Path(out) / "likelihood_comparison.md").write_text(md)
            write_json(Path(out) / "likelihood_comparison.json", records)

        writers.append(write_comparison)
    if cfg.output.figures:
        temperature = np.asarray(test.temperature)
        dists = {name: p.dist for name, p in hs.predictions.items()}
        cols = dict(columns)

        def write_figures(out: Path) -> None:
            from bayesmag._src.app.hybrid_plots import hybrid_figures
            hybrid_figures(Path(out), cols, temperature, dists, level=level)
            from bayesmag._src.app.network_plots import loss_curves
            loss_curves(Path(out) / "network_loss.png", hs.networks)

        writers.append(write_figures)
    return writers
