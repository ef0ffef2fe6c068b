"""Hybrid stage: fusion rules, config checks, end-to-end jobs on simulated and real data."""

import copy
import warnings
import csv
import json

import jax
import numpy as np
import pytest

from bayesmag import ConfigError, run_job
from bayesmag._src.app.config import config_from_dict
from bayesmag._src.core.data import CalibrationWarning
from bayesmag._src.pipeline.hybrid import check_network_config, conformal_plan, fuse
from bayesmag._src.core.network import NetworkSpec
from helpers import uq_parts

LEVEL = 0.95
# 338 test rows: a 95 % interval's coverage has binomial sd 1.2 %; 3 sd either side.
COVERAGE_BAND = (0.91, 0.99)

SIMULATED = {
    "name": "sim_hybrid",
    "data": {"source": "simulated",
             "simulate": {"design": "iid", "n": 3000, "seed": 0, "noise_sd": 0.05,
                          "effects": [{"name": "axis_quadratic", "coeff": 0.01}]}},
    "split": {"kind": "random", "test_fraction": 0.1, "seed": 0},
    "uq": {"n_params": 100, "n_qmc": 256},
    "network": {"enabled": True, "likelihoods": ["gaussian", "laplace"], "max_epochs": 40, "mc_passes": 20},
    "output": {"progress": False},
}


def _config(base=SIMULATED, **network):
    raw = copy.deepcopy(base)
    raw["network"].update(network)
    return config_from_dict(raw)


# --------------------------------------------------------------------------- fusion




@pytest.mark.parametrize("likelihood,df", [("gaussian", 4.0), ("laplace", 4.0), ("student_t", 5.0),
                                           ("student_t", None)])
def test_moment_match_fusion_gives_the_family_mean_and_variance(likelihood, df):
    phys, nn = uq_parts()
    pred = fuse(phys, nn, NetworkSpec(likelihood=likelihood, student_t_df=df), fusion="moment_match")
    var = nn.aleatoric**2 + nn.epistemic**2 + phys.epistemic**2          # physics aleatoric not added
    assert type(pred.dist).name == likelihood
    np.testing.assert_allclose(pred.mean, phys.mean + nn.mean, rtol=1e-14)
    np.testing.assert_allclose(np.asarray(pred.dist.mean), pred.mean, rtol=1e-14)
    np.testing.assert_allclose(np.asarray(pred.dist.variance), var, rtol=1e-12)
    np.testing.assert_allclose(pred.total**2, var, rtol=1e-12)
    if likelihood == "student_t":
        want = nn.shape["df"] if df is None else np.full((50, 3), df)
        np.testing.assert_allclose(np.broadcast_to(pred.dist.df, (50, 3)), want)


def test_paper_fusion_adds_the_physics_aleatoric_part_and_is_gaussian():
    phys, nn = uq_parts(1)
    pred = fuse(phys, nn, NetworkSpec(likelihood="laplace"), fusion="paper")
    var = phys.aleatoric**2 + nn.aleatoric**2 + phys.epistemic**2 + nn.epistemic**2
    assert type(pred.dist).name == "gaussian"
    np.testing.assert_allclose(np.asarray(pred.dist.variance), var, rtol=1e-12)
    lo, hi = pred.dist.interval(LEVEL)
    np.testing.assert_allclose(np.asarray(hi) - pred.mean, 1.959963984540054 * np.sqrt(var), rtol=1e-10)
    # the decomposition sums to the total
    np.testing.assert_allclose(pred.total**2, pred.aleatoric_physics**2 + pred.aleatoric_nn**2
                               + pred.epistemic_physics**2 + pred.epistemic_nn**2, rtol=1e-12)


# --------------------------------------------------------------------------- config checks


def test_network_config_errors_name_the_key_and_the_valid_set():
    with pytest.raises(ConfigError, match=r"'cauchy'.*\['gaussian', 'laplace', 'student_t'\]"):
        check_network_config(_config(likelihoods=["gaussian", "cauchy"]))
    with pytest.raises(ConfigError, match=r"network\.likelihoods.*empty"):
        check_network_config(_config(likelihoods=[]))
    with pytest.raises(ConfigError, match=r"repeats"):
        check_network_config(_config(likelihoods=["laplace", "laplace"]))
    with pytest.raises(ConfigError, match=r"network\.mc_passes"):
        check_network_config(_config(mc_passes=1))
    with pytest.raises(ConfigError, match=r"network\.student_t_df"):
        check_network_config(_config(likelihoods=["student_t"], student_t_df="guess"))
    specs = check_network_config(_config(likelihoods=["student_t", "gaussian"], student_t_df="learn"))
    assert [s.likelihood for s in specs] == ["student_t", "gaussian"] and specs[0].df is None


def test_network_too_large_or_validation_too_small_stop_the_job(tmp_path):
    raw = copy.deepcopy(SIMULATED)
    raw["data"]["simulate"]["n"] = 400
    raw["output"]["figures"] = False
    with pytest.raises(ConfigError, match=r"network\.width.*network\.hidden_layers"):
        run_job(_config(raw, likelihoods=["gaussian"]), tmp_path / "big")
    with pytest.raises(ConfigError, match=r"network\.validation_fraction"):
        run_job(_config(raw, likelihoods=["gaussian"], width=8, validation_fraction=0.02), tmp_path / "val")
    assert not (tmp_path / "big").exists() and not (tmp_path / "val").exists()


@pytest.mark.extended
def test_nan_loss_warns_with_the_epoch_and_the_job_finishes(tmp_path):
    raw = copy.deepcopy(SIMULATED)
    raw["data"]["simulate"]["n"] = 1000
    raw["output"]["figures"] = False
    cfg = _config(raw, likelihoods=["gaussian"], hidden_layers=2, width=16, learning_rate=0.3, epsilon=0.0,
                  log_scale_clip=[-300.0, 300.0], log_scale_l2=0.0, validation="random",
                  interval_calibration="none")                 # the rows and seed known to diverge
    with pytest.warns(CalibrationWarning, match=r"NaN/inf in epoch \d+; training stopped there"):
        result = run_job(cfg, tmp_path / "nan")
    info = result["metrics"]["network"]["training"]["gaussian"]
    assert any(info[ax]["nan_epoch"] >= 0 for ax in "xyz")
    assert result["metrics"]["network"]["warnings"]
    assert json.loads((tmp_path / "nan" / "metrics.json").read_text())["network"]["warnings"]


def test_a_network_stopped_by_max_epochs_while_improving_is_warned_about(tmp_path):
    """4 epochs on a quadratic the network has to learn: the validation loss is still falling when max_epochs ends
    training, and the job says so per axis (it was silent); the rule agrees with the saved training record."""
    from bayesmag._src.pipeline.hybrid import still_improving
    raw = copy.deepcopy(SIMULATED)
    raw["data"]["simulate"]["n"] = 1000
    raw["output"]["figures"] = False
    cfg = _config(raw, likelihoods=["gaussian"], hidden_layers=2, width=16, max_epochs=4, interval_calibration="none")
    with pytest.warns(CalibrationWarning, match=r"stopped at network.max_epochs = 4 with the validation loss still"):
        result = run_job(cfg, tmp_path / "short")
    info = result["metrics"]["network"]["training"]["gaussian"]
    flagged = [ax for ax in "xyz" if still_improving(info[ax], 4)]
    assert flagged and any(f"axis {', '.join(flagged)}:" in w for w in result["metrics"]["network"]["warnings"])
    assert set(result["metrics"]["network"]["warnings"]) <= set(result["metrics"]["warnings"])   # printed by the CLI


# --------------------------------------------------------------------------- end to end


@pytest.mark.extended
def test_simulated_job_hybrid_beats_physics_and_compares_likelihoods(tmp_path):
    out = tmp_path / "sim"
    result = run_job(_config(conformal_folds=2), out)     # 2 cross-conformal folds: the default 5 trains 5 networks
    m = result["metrics"]
    for name in ("gaussian", "laplace"):
        h = m["hybrid"][name]
        assert h["rmse"]["y"] < 0.2 * m["physics"]["rmse"]["y"]        # the quadratic effect is learned
        assert set(h) == {"rmse", "mae", "coverage", "nll", "crps", "mean_width"}
        assert m["network"]["training"][name]["y"]["epochs_run"] >= 1
    # the likelihoods give different scores
    assert m["hybrid"]["gaussian"]["nll"]["x"] != m["hybrid"]["laplace"]["nll"]["x"]
    # field metrics per stage (issue 26): the hybrid's heading error is below the physics stage's
    assert set(m["field"]) == {"raw", "physics", "hybrid (gaussian)", "hybrid (laplace)"}
    assert m["field"]["hybrid (gaussian)"]["heading"]["rms"] < m["field"]["physics"]["heading"]["rms"]
    assert m["hybrid"]["gaussian"]["crps"]["x"] != m["hybrid"]["laplace"]["crps"]["x"]

    records = json.loads((out / "likelihood_comparison.json").read_text())
    assert [r["likelihood"] for r in records] == ["gaussian", "laplace"]
    assert records[1]["nll"] == m["hybrid"]["laplace"]["nll"]
    md = (out / "likelihood_comparison.md").read_text()
    assert "| Likelihood | Axis | RMSE (uT) | MAE (uT) | Coverage (%) | NLL | CRPS (uT) |" in md
    assert md.count("| laplace |") == 3
    for fig in ("hybrid_residuals_vs_reference.png", "hybrid_uncertainty_vs_temperature.png",
                "hybrid_calibration.png", "hybrid_pit.png"):
        assert (out / fig).stat().st_size > 10_000

    with open(out / "predictions.csv") as f:
        header = next(csv.reader(f))
    for col in ("hybrid_predicted", "aleatoric_nn", "epistemic_nn", "hybrid_total", "hybrid_lower",
                "hybrid_upper", "hybrid_covered"):
        assert f"y_{col}" in header
    # primary (gaussian) columns: total^2 = k^2 (NN aleatoric^2 + NN epistemic^2 + physics epistemic^2), k the
    # conformal scale (>= 1, default interval_calibration); random test rows are same-session: no transfer part
    pred = result["hybrid"]["gaussian"]
    k = result["predictor"].scale
    assert k.shape == (3,) and np.all(k >= 1.0) and np.all(pred.transfer == 0)
    assert m["network"]["training"]["gaussian"]["conformal"]["folds"] == 2
    assert len(result["predictor"].network.members) == 2      # the fold networks predict as a deep ensemble
    assert m["network"]["training"]["gaussian"]["conformal"]["ensemble_passes"] == [10, 10]
    np.testing.assert_allclose(pred.total**2, k**2 * (pred.aleatoric_nn**2 + pred.epistemic_nn**2
                                                      + pred.epistemic_physics**2), rtol=1e-12)
    assert "network_train" in m["timings"] and "hybrid_inference" in m["timings"]


@pytest.mark.parametrize("split,folds_cfg,want", [
    ({"kind": "random", "test_fraction": 0.2}, 5, (0.1, 5)),                    # no test blocks: validation_fraction
    ({"kind": "by_run", "test_runs": [1]}, 5, (0.1, 5)),
    ({"kind": "time_blocks", "test_fraction": 0.05}, 5, (0.1, 5)),              # test blocks shorter: unchanged
    ({"kind": "time_blocks", "test_fraction": 0.1}, 5, (0.1 / 0.9, 5)),         # 0.1 of a run = 0.111 of its training rows
    ({"kind": "time_blocks", "test_fraction": 0.2}, 5, (0.25, 3)),              # 5 x 0.25 > 1: three folds
    ({"kind": "time_blocks", "test_fraction": 0.2, "n_blocks": 2}, 5, (0.125, 5)),
    ({"kind": "time_blocks", "test_fraction": 0.4}, 5, (0.49, 2)),              # longer than half the rows: capped
    ({"kind": "time_blocks", "test_fraction": 0.2}, 2, (0.25, 2)),
])
def test_conformal_blocks_are_as_long_as_the_test_blocks(split, folds_cfg, want):
    """The fold blocks calibrate the intervals of the test rows, so they are at least as long as the
    job's test blocks, with as many folds (at most the configured number) as fit in a run."""
    raw = copy.deepcopy(SIMULATED)
    raw["split"] = {**split, "seed": 0}
    cfg = _config(raw, conformal_folds=folds_cfg, validation_fraction=0.1)
    fraction, n = conformal_plan(cfg.split, cfg.network)
    assert (fraction, n) == (pytest.approx(want[0]), want[1])
    assert n * fraction < 1.0


def test_conformal_folds_are_one_block_per_run_in_their_own_stretch():
    """Fold k: one contiguous block of ``fraction`` of every run, inside the k-th of K equal stretches of the run."""
    from bayesmag._src.pipeline.hybrid import conformal_folds
    run = np.repeat([3, 1, 7], [200, 310, 95])
    fold = conformal_folds(run, fraction=0.1, folds=5, seed=1)
    assert set(np.unique(fold)) == {-1, 0, 1, 2, 3, 4}
    for r in (3, 1, 7):
        rows = np.flatnonzero(run == r)
        f = fold[rows]
        for k in range(5):
            at = np.flatnonzero(f == k)
            assert at.size == round(0.1 * rows.size) and np.all(np.diff(at) == 1)      # one contiguous block
            assert np.all(at // (rows.size // 5) == k)                                 # in the k-th stretch
    np.testing.assert_array_equal(fold, conformal_folds(run, fraction=0.1, folds=5, seed=1))   # seeded


@pytest.mark.extended
def test_each_conformal_fold_is_scored_by_a_network_that_never_saw_it(tmp_path, monkeypatch):
    """Cross-conformal in the job: K networks, network k trained without fold k's rows; no fold row is a test row."""
    from bayesmag._src.pipeline import hybrid
    seen, real = [], hybrid.train_network

    def spy(x, r, spec, net_cfg, groups=None, progress=False, pool=None):     # the folds train at once, unordered
        seen.append({tuple(v) for v in x})
        return real(x, r, spec, net_cfg, groups=groups, progress=progress, pool=pool)

    monkeypatch.setattr(hybrid, "train_network", spy)
    raw = copy.deepcopy(SIMULATED)
    raw["data"]["simulate"].update(n=1200, design="campaign")
    raw["split"] = {"kind": "time_blocks", "test_fraction": 0.1, "seed": 0}
    raw["output"]["figures"] = False
    cfg = _config(raw, likelihoods=["gaussian"], max_epochs=5, mc_passes=5, conformal_folds=3, width=16)
    result = run_job(cfg, tmp_path / "cv")
    assert len(seen) == 3
    data, split = result["data"], result["split"]
    train = data.subset(split.train)
    fraction, n_folds = hybrid.conformal_plan(cfg.split, cfg.network)
    assert n_folds == 3 and fraction == pytest.approx(0.1 / 0.9)      # as long as the test blocks (0.1 of a run)
    folds = hybrid.conformal_folds(train.run, fraction=fraction, folds=3, seed=1)
    x = np.column_stack([train.b_meas, train.temperature])
    test_x = {tuple(v) for v in np.column_stack([data.b_meas, data.temperature])[split.test]}
    for k in range(3):
        fitted = [rows for rows in seen if rows == {tuple(v) for v in x[folds != k]}]
        assert len(fitted) == 1                                          # one network on everything but fold k
        fold = {tuple(v) for v in x[folds == k]}
        assert fold and not fold & fitted[0] and not fold & test_x       # never trained on, never a test row
    assert result["metrics"]["network"]["training"]["gaussian"]["conformal"] == {
        "folds": 3, "block_fraction": round(fraction, 6), "rows": int(np.sum(folds >= 0)),
        "ensemble_passes": [2, 2, 2]}                                                 # 5 passes: at least 2 each
    # the predictor keeps the three fold networks as its ensemble, fold 0's first; metrics describe fold 0's
    ens = result["predictor"].network
    assert len(ens.members) == 3
    for k, member in enumerate(ens.members):
        assert member.n_fit + member.n_val == np.sum(folds != k)


@pytest.mark.realdata
def test_real_data_hybrid_beats_physics_on_the_random_split(belsten, tmp_path):
    raw = {
        "name": "belsten_hybrid_reduced",
        "data": {"source": "belsten2023"},
        "split": {"kind": "random", "test_fraction": 0.1, "seed": 0},
        "uq": {"n_params": 100, "n_qmc": 256},
        "network": {"enabled": True, "likelihoods": ["gaussian"], "max_epochs": 200, "mc_passes": 30,
                    "validation": "random", "interval_calibration": "none"},          # the paper's protocol
        "output": {"progress": False, "figures": False},
    }
    result = run_job(config_from_dict(raw), tmp_path / "real")
    m = result["metrics"]
    assert m["split"]["n_test"] == 338
    h = m["hybrid"]["gaussian"]
    for ax in "xyz":
        assert h["rmse"][ax] < 0.9 * m["physics"]["rmse"][ax]
        assert COVERAGE_BAND[0] <= h["coverage"][ax] <= COVERAGE_BAND[1]
        assert h["nll"][ax] < m["physics"]["nll"][ax]
        # the paper's fusion counts the input noise twice: wider intervals than moment matching
        assert m["hybrid_paper_fusion"]["gaussian"]["mean_width"][ax] > h["mean_width"][ax]


def test_fold_networks_trained_together_equal_each_trained_alone():
    """train_fold_networks trains the K cross-conformal networks at once on one shared pool of threads;
    each must be bit-identical to the network train_network gives for its rows alone."""
    from bayesmag._src.pipeline.hybrid import conformal_folds, train_fold_networks, train_network
    cfg = _config(max_epochs=6, likelihoods=["gaussian"], width=16, hidden_layers=2)
    rng = np.random.default_rng(3)
    n = 400
    x, run = rng.normal(size=(n, 4)), np.repeat([1, 2], n // 2)
    r = np.column_stack([0.1 * x[:, 0] ** 2, np.sin(x[:, 1]), x[:, 2] * x[:, 3]]) + 0.05 * rng.normal(size=(n, 3))
    spec = check_network_config(cfg)[0]
    folds = conformal_folds(run, fraction=0.1, folds=3, seed=1)
    together = train_fold_networks(x, r, spec, cfg.network, run, folds, 3)
    for k, net in enumerate(together):
        rows = np.flatnonzero(folds != k)
        alone = train_network(x[rows], r[rows], spec, cfg.network, groups=run[rows])
        for a, b in zip(jax.tree.leaves(net.params), jax.tree.leaves(alone.params)):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(net.info.val_loss, alone.info.val_loss)


@pytest.mark.extended
def test_predictions_name_the_hybrid_family_and_write_its_learned_dof(tmp_path):
    """Sixth outside pass: with `network.student_t_df = "learn"` the per-row dof was written nowhere (the scores could
    not be recomputed), and with several families nothing said whose the hybrid columns are. Now `hybrid_family`
    names it and `hybrid_df` holds each row's dof: the interval is the Student-t's with that dof and the written sd
    (scipy's quantile, to the file's 8 significant figures)."""
    import pandas as pd
    import scipy.stats

    raw = copy.deepcopy(SIMULATED)
    raw["data"]["simulate"]["n"] = 1000
    raw["output"]["figures"] = False
    cfg = _config(raw, likelihoods=["student_t", "gaussian"], student_t_df="learn", max_epochs=15, mc_passes=10,
                  hidden_layers=2, width=16)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)        # 15 epochs: under-trained, said
        run_job(cfg, tmp_path / "t")
    p = pd.read_csv(tmp_path / "t" / "predictions.csv")
    for a in "xyz":
        assert (p[f"{a}_hybrid_family"] == "student_t").all()
        df, sd = p[f"{a}_hybrid_df"].to_numpy(), p[f"{a}_hybrid_total"].to_numpy()
        assert np.all(df > 2) and np.ptp(df) > 0                    # learned: one dof per row
        half = sd * np.sqrt((df - 2) / df) * scipy.stats.t.ppf(0.975, df)
        np.testing.assert_allclose(p[f"{a}_hybrid_upper"] - p[f"{a}_hybrid_predicted"], half, rtol=1e-5)  # 8 digits
