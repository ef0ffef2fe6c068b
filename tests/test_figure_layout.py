"""Fixed figure margins (app/figure_layout.py): every label stays on the canvas and no two panels' labels overlap,
for the grids the job draws, with tick labels as long as its residual panels have."""

from __future__ import annotations

import itertools

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from bayesmag._src.app.figure_layout import fixed_layout  # noqa: E402


@pytest.mark.parametrize("rows, cols, size, sharey, wspace", [(1, 3, (14, 4.3), False, 0.95), (3, 3, (13.1, 8.4), False, 0.95),
                                                             (3, 6, (20, 8.4), "row", 0.45), (3, 1, (4.7, 8.4), False, 0.95),
                                                             (2, 3, (12, 6.0), False, 0.95)])
def test_labels_stay_on_the_canvas_and_apart(rows, cols, size, sharey, wspace):
    rng = np.random.default_rng(0)
    fig, axes = plt.subplots(rows, cols, figsize=size, squeeze=False, sharey=sharey)
    for i, j in itertools.product(range(rows), range(cols)):
        ax = axes[i, j]
        x = rng.uniform(0, 200, 50) if sharey else rng.normal(0, 40, 50)   # time since the run's start, or a field
        ax.scatter(x, rng.normal(0, 0.05, 50), s=4)                          # y ticks like -0.075
        ax.set_title(f"run {j + 1}, x: test 100% in band" if sharey else f"x axis: 94.1% inside +-2 sd, row {i}",
                     fontsize=8 if sharey else 9)                   # the job's titles for such panels
        ax.set_xlabel("reference Bx (uT)")
        ax.set_ylabel("calibrated - reference Bx (uT)")
    fig.suptitle("Physics residuals vs the reference field (test rows)")
    fixed_layout(fig, wspace=wspace)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    w, h = fig.bbox.width, fig.bbox.height
    boxes = [ax.get_tightbbox(r) for ax in axes.flat]
    for b in boxes + [fig._suptitle.get_window_extent(r)]:
        assert b.x0 >= -1 and b.y0 >= -1 and b.x1 <= w + 1 and b.y1 <= h + 1, (b, w, h)
    for a, b in itertools.combinations(boxes, 2):            # panels (with their labels) do not overlap
        overlap_x = min(a.x1, b.x1) - max(a.x0, b.x0)
        overlap_y = min(a.y1, b.y1) - max(a.y0, b.y0)
        assert overlap_x <= 1 or overlap_y <= 1, (a, b)
    plt.close(fig)
