"""The simulation study: outputs shaped as documented, numbers consistent with the paper's design."""

import json
from pathlib import Path

import numpy as np
import pytest

from bayesmag import ConfigError, load_config
from bayesmag._src.app.study import run_study
from bayesmag._src.pipeline.hybrid import still_improving

CFG = Path(__file__).resolve().parents[1] / "configs/paper_simulation.toml"


def test_small_study(tmp_path):
    cfg = load_config(CFG, ["study.sizes=[4000, 6000]", "network.hidden_layers=2", "network.width=32",
                            "network.max_epochs=40", "network.batch_size=128", "network.mc_passes=10",
                            'study.per_size={"6000" = {batch_size = 256}}'])
    res = run_study(cfg, tmp_path / "s", progress=False)
    t12 = json.loads((tmp_path / "s/simulation_study.json").read_text())
    assert set(t12) == {"4000", "6000"}
    for size, r in t12.items():
        for stage in ("raw", "physics", "hybrid", "noise_floor"):
            assert set(r[stage]) == {"x", "y", "z"}
        # the paper's design: raw y error ~21.5 uT, physics cannot model the quadratic (~9.5), the network can
        assert 19 < r["raw"]["y"] < 24 and 8 < r["physics"]["y"] < 11
        assert r["hybrid"]["y"] < 0.5 * r["physics"]["y"]
        assert all(r["hybrid"][a] >= 0.95 * r["noise_floor"][a] for a in "xyz")   # nothing beats the noise floor
    t13 = json.loads((tmp_path / "s/significance.json").read_text())
    assert t13["6000"]["y"]["mean_diff"] > 0 and t13["6000"]["y"]["p"] < 1e-6
    assert res["records"]["6000"]["network"]["batch_size"] == 256
    for f in ("simulation_study.md", "significance.md", "rmse_vs_size.png", "metrics.json"):
        assert (tmp_path / "s" / f).exists()
    # 40 epochs: a network still improving at the last one is named in the table (it was not flagged)
    md = (tmp_path / "s/simulation_study.md").read_text()
    for size, r in res["records"].items():
        short = [ax for ax, i in r["network"]["epochs_run"].items() if still_improving(i, 40)]
        assert r["network"]["still_improving"] == short
        assert (f"size {int(size):,}: the network of axis" in md) == bool(short)


@pytest.mark.parametrize("epochs_run, best_epoch, nan_epoch, max_epochs, flagged", [
    (40, 39, -1, 40, True),      # best at the last epoch
    (40, 36, -1, 40, True),      # in the last tenth (4 of 40)
    (40, 35, -1, 40, False),     # just before it
    (25, 24, -1, 40, False),     # early stopping ended it before max_epochs
    (40, 39, 40, 40, False),     # a NaN stop has its own warning
    (10, 8, -1, 10, True),       # the last 2 epochs at least
])
def test_still_improving_at_max_epochs(epochs_run, best_epoch, nan_epoch, max_epochs, flagged):
    info = {"epochs_run": epochs_run, "best_epoch": best_epoch, "nan_epoch": nan_epoch}
    assert still_improving(info, max_epochs) is flagged
