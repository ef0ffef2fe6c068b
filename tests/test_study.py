"""The simulation study: outputs shaped as documented, numbers consistent with the paper's design."""

import json
from pathlib import Path

import numpy as np
import pytest

from bayesmag import ConfigError, load_config
from bayesmag._src.app.study import run_study

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


def test_study_needs_simulated_data(tmp_path):
    cfg = load_config(CFG, ['data.source="belsten2023"'])
    with pytest.raises(ConfigError, match="simulated"):
        run_study(cfg, tmp_path / "s", progress=False)
    cfg = load_config(CFG, ["study.sizes=[5000]", 'study.per_size={"5000" = {batch = 3}}'])
    with pytest.raises(ConfigError, match=r"study.per_size.5000.*batch"):
        run_study(cfg, tmp_path / "s", progress=False)
