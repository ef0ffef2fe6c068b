"""The simulation study: outputs shaped as documented, numbers consistent with the paper's design."""

import json
from pathlib import Path

import numpy as np
import pytest

from bayesmag import ConfigError, load_config
from bayesmag._src.app.study import run_study
from bayesmag._src.pipeline.hybrid import still_improving

CFG = Path(__file__).resolve().parents[1] / "configs/paper_simulation.toml"


@pytest.mark.extended
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


# --- the fourth safety pass: the study's config is checked before any computation -------------------------------

def _cli(argv, capsys):
    from bayesmag._src.app.cli import main
    rc = main(argv)
    return rc, capsys.readouterr()


def test_sizes_too_small_for_the_network_are_one_line_at_load(tmp_path, capsys):
    # was: a traceback ending in "ValueError: The residual network ... is too large for 720 fitting rows"
    rc, cap = _cli(["study", str(CFG), "--set", "study.sizes=[1000]", "--out", str(tmp_path / "st"), "--no-progress"],
                   capsys)
    err = cap.err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "Traceback" not in err
    assert "study.sizes" in err and "1,796" in err and "network.width" in err
    assert not (tmp_path / "st").exists()                   # refused before the output folder
    from bayesmag._src.app.study import load_study_config
    load_study_config(CFG, ["study.sizes=[1796]"])           # the smallest it names is accepted
    load_study_config(CFG, ["study.sizes=[1000]", "network.enabled=false"])   # no network, no limit


@pytest.mark.parametrize("sets, key", [
    (["nuts.enabled=true"], "nuts.enabled"),
    (["network.likelihoods=['gaussian', 'student_t']"], "network.likelihoods"),
    (['study.per_size={"4000" = {widht = 8}}'], r"study\.per_size\.4000"),     # was checked only when 4000 ran
])
def test_settings_the_study_does_not_follow_are_refused(sets, key):
    from bayesmag._src.app.study import load_study_config
    with pytest.raises(ConfigError, match=key):
        load_study_config(CFG, ["study.sizes=[4000]", *sets])


def test_network_and_figures_off_are_honoured_and_other_simulations_get_no_paper_columns(tmp_path):
    from bayesmag._src.app.study import load_study_config, paper_comparable
    cfg = load_study_config(CFG, ["study.sizes=[600]", "network.enabled=false", "output.figures=false",
                                  "data.simulate.noise_sd=0.05"])
    res = run_study(cfg, tmp_path / "s", progress=False)
    files = {p.name for p in (tmp_path / "s").iterdir()}
    assert "rmse_vs_size.png" not in files and "significance.json" not in files
    assert set(json.loads((tmp_path / "s/simulation_study.json").read_text())["600"]) == {"raw", "physics",
                                                                                          "noise_floor"}
    assert "hybrid" not in res["records"]["600"] and "network" not in res["per_size"]["600"]
    md = (tmp_path / "s/simulation_study.md").read_text()
    assert "hybrid |" not in md and "paper raw" not in md and "not comparable" in md
    assert not res["paper_comparable"] and not paper_comparable(cfg)


def test_paper_columns_only_for_the_papers_simulation():
    from bayesmag._src.app.study import _table12_md, load_study_config, paper_comparable
    assert paper_comparable(load_study_config(CFG))
    assert paper_comparable(load_study_config(CFG, ["data.simulate.seed=7", "data.simulate.noise_sd=[0.5, 0.5, 0.5]",
                                                    "data.simulate.effects=['axis_quadratic']"]))   # the same, spelled out
    for sets in (["data.simulate.noise_sd=0.05"], ["data.simulate.design='campaign'"], ["split.test_fraction=0.3"],
                 ["data.simulate.effects=[]"]):
        assert not paper_comparable(load_study_config(CFG, sets)), sets
    assert not paper_comparable(load_study_config("quickstart", ["study.sizes=[5000]"]))
    rec = {"50000": {k: dict(x=1.0, y=2.0, z=3.0) for k in ("raw", "physics", "hybrid", "noise_floor")}}
    assert "21.5638" in _table12_md(rec, paper=True, network=True)
    assert "paper" not in _table12_md(rec, paper=False, network=True)


def test_a_config_without_a_study_table_is_refused(tmp_path, capsys):
    # was: quickstart ran the paper's 50k-500k sizes silently
    rc, cap = _cli(["study", "quickstart", "--out", str(tmp_path / "q"), "--no-progress"], capsys)
    err = cap.err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "no [study] table" in err and "study.sizes" in err


def test_study_on_a_fleet_config_points_to_fleet(tmp_path, capsys):
    rc, cap = _cli(["study", "fleet_simulated", "--out", str(tmp_path / "f")], capsys)
    err = cap.err.strip()
    assert rc == 2 and "is a fleet config" in err and "bayesmag fleet" in err and len(err.splitlines()) == 1
