"""Residual network: DropConnect on weights, training, early stopping, NaN handling, vmap, MC inference."""

import dataclasses
import tempfile
from pathlib import Path

import numpy as np
import scipy.stats
import jax
import jax.numpy as jnp
import pytest

import bayesmag as bm
from bayesmag._src.core import network as N
from bayesmag._src.app.config import config_error, config_from_dict

# Statistical tolerances, stated once.
MASK_SIGMAS = 5.0            # fraction of dropped weights within 5 binomial sds of the rate
SD_TRACK_RTOL = 0.15         # learned sd within 15 % of the true sd (median over a grid)
SD_TRACK_CORR = 0.9          # and correlated with it across the grid
MEAN_RMS_Z = 0.5             # mean error well inside the noise: RMS of (error / true sd) below 0.5
ORACLE_NLL_GAP = 0.1         # validation NLL within 0.1 nats of the true model's

SMALL = dict(hidden_layers=2, width=16, batch_size=32)


def small_spec(**kw):
    return N.NetworkSpec(**{**SMALL, **kw})


# --------------------------------------------------------------------------- DropConnect


def test_drop_connect_masks_weights_not_activations():
    params = N.init(jax.random.key(0), 4, 2, hidden_layers=2, width=32)
    rate = 0.3
    masked = jax.jit(N.drop_connect, static_argnums=2)(params, jax.random.key(1), rate)
    for layer, m in zip(params, masked):
        w, wm = np.asarray(layer.w), np.asarray(m.w)
        kept = wm != 0
        # kept weights are scaled by 1/(1-p), dropped ones are exactly zero; biases untouched
        np.testing.assert_allclose(wm[kept], w[kept] / (1 - rate), rtol=1e-6)
        np.testing.assert_array_equal(np.asarray(m.b), np.asarray(layer.b))
    w = np.asarray(masked[1].w)
    assert w.shape == (32, 32)
    frac = np.mean(w == 0)
    sd = np.sqrt(rate * (1 - rate) / w.size)
    assert abs(frac - rate) < MASK_SIGMAS * sd
    # whole rows/columns are not dropped together (that would be unit dropout): both
    # kept and dropped entries appear in most rows of the masked matrix
    assert np.mean([(row == 0).any() and (row != 0).any() for row in w]) > 0.9

    # apply() with a key is the network with those masked weights, and one mask serves all rows:
    # identical input rows give identical outputs (activation dropout would differ per row).
    x = jnp.tile(jax.random.normal(jax.random.key(2), (1, 4), jnp.float32), (8, 1))
    apply = jax.jit(N.apply, static_argnames="dropconnect")
    out = apply(params, x, jax.random.key(1), dropconnect=rate)
    np.testing.assert_allclose(out, apply(masked, x), rtol=1e-6)
    np.testing.assert_allclose(out, jnp.broadcast_to(out[:1], out.shape), rtol=0, atol=0)


@pytest.mark.parametrize("rate", [0.01, 0.2])
def test_keep_masks_rate_and_independence(rate):
    shapes = ((64, 64), (64, 2))
    masks = [np.concatenate([np.ravel(m) for m in N.keep_masks(jax.random.key(k), shapes, rate)])
             for k in range(20)]
    drops = ~np.stack(masks)                      # (20, 4224)
    n = drops.size
    assert abs(drops.mean() - rate) < MASK_SIGMAS * np.sqrt(rate * (1 - rate) / n)
    # masks from different keys are independent: the overlap of dropped sets is ~ rate^2
    overlap = np.mean(drops[::2] & drops[1::2])
    assert abs(overlap - rate**2) < MASK_SIGMAS * np.sqrt(rate**2 * (1 - rate**2) / (n / 2))


def test_keep_masks_are_bernoulli_against_scipy():
    """The sparse (geometric-gap) masks at the paper's rate: the number of drops per mask follows
    Binomial(n, rate) (scipy chi-square goodness of fit over 2000 masks, p > 1e-3), dropped positions
    are uniform over the weights (chi-square over 16 bins, p > 1e-3), and the static drop budget has
    tail probability <= DROP_TAIL (scipy)."""
    shapes = ((4, 64), (64, 64), (64, 64), (64, 2))
    rate, n_masks = 0.01, 2000
    keys = jax.random.split(jax.random.key(7), n_masks)
    drops = ~np.asarray(jax.vmap(lambda k: jnp.concatenate([m.ravel() for m in N.keep_masks(k, shapes, rate)]))(keys))
    n = drops.shape[1]
    counts = drops.sum(1)
    edges = np.arange(int(n * rate) - 30, int(n * rate) + 31, 5)
    obs = np.histogram(counts, np.r_[-np.inf, edges, np.inf])[0]
    cdf = scipy.stats.binom.cdf(np.r_[edges - 1, n], n, rate)
    expected = np.diff(np.r_[0.0, cdf]) * n_masks
    assert scipy.stats.chisquare(obs, expected * obs.sum() / expected.sum()).pvalue > 1e-3
    assert n % 16 == 0
    assert scipy.stats.chisquare(drops.reshape(n_masks, 16, -1).sum((0, 2))).pvalue > 1e-3
    k = N.max_drops(n, rate)
    assert scipy.stats.binom.sf(k, n, rate) <= N.DROP_TAIL < scipy.stats.binom.sf(k - 2, n, rate)


# --------------------------------------------------------------------------- training


def _hetero_problem(n, seed):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, size=(n, 4))
    true_sd = 0.05 + 0.25 * (x[:, 0] + 1) / 2
    r = np.sin(2 * x[:, 0]) + true_sd * rng.normal(size=n)
    return x, r[:, None], true_sd


def test_training_reduces_nll_and_learns_the_sd():
    x, r, true_sd = _hetero_problem(3000, 0)
    spec = small_spec(width=32, max_epochs=150, patience=30, learning_rate=3e-3, batch_size=64, dropconnect=0.0)
    net = N.fit_residual_network(x, r, spec, seed=0)
    hist = np.asarray(net.info.val_loss[0])
    hist = hist[np.isfinite(hist)]
    # NLL of the true model on the validation rows, in the network's standardised units
    _, val_rows = N.validation_rows(3000, 0.1, seed=0)
    st = net.standardizer
    z = (r[val_rows, 0] - np.sin(2 * x[val_rows, 0])) / true_sd[val_rows]
    oracle = np.mean(0.5 * np.log(2 * np.pi) + np.log(true_sd[val_rows] / st.r_scale[0]) + 0.5 * z**2)
    assert net.info.best_val_loss[0] < hist[0] - 0.3                   # training reduced the NLL ...
    assert net.info.best_val_loss[0] < oracle + ORACLE_NLL_GAP          # ... to near the true model's

    grid = np.zeros((41, 4))
    grid[:, 0] = np.linspace(-0.9, 0.9, 41)
    pred = N.mc_predict(net, grid, passes=2)
    true_sd = 0.05 + 0.25 * (grid[:, 0] + 1) / 2
    learned = pred.aleatoric[:, 0]
    assert np.median(np.abs(learned / true_sd - 1)) < SD_TRACK_RTOL
    assert np.corrcoef(learned, true_sd)[0, 1] > SD_TRACK_CORR
    assert np.sqrt(np.mean(((pred.mean[:, 0] - np.sin(2 * grid[:, 0])) / true_sd) ** 2)) < MEAN_RMS_Z


def test_early_stopping_restores_the_best_weights():
    x, r, _ = _hetero_problem(600, 1)
    spec = small_spec(max_epochs=400, patience=8, learning_rate=1e-2, lr_plateau_factor=1.0)
    net = N.fit_residual_network(x, r, spec, seed=3)
    info = net.info_dict(["a"])["a"]
    hist = np.asarray(net.info.val_loss[0])
    assert info["epochs_run"] < spec.max_epochs                      # stopped early
    assert info["epochs_run"] == info["best_epoch"] + 1 + spec.patience
    assert info["best_val_loss"] == pytest.approx(np.nanmin(hist), rel=0, abs=0)
    # the returned weights are those of the best epoch: recompute their validation loss
    fit_rows, val_rows = N.validation_rows(600, 0.1, seed=3)
    st = net.standardizer
    p0 = jax.tree.map(lambda a: a[0], net.params)
    raw = N.apply(p0, st.x(x[val_rows]), activation=spec.activation)
    val = N.regularized_nll(spec, raw, st.r(r[val_rows])[:, 0])
    assert float(val) == pytest.approx(info["best_val_loss"], rel=1e-5)
    assert float(val) < hist[info["epochs_run"] - 1]                 # better than the last epoch's


def test_nan_loss_stops_training_and_reports_the_epoch():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(600, 4))
    r = np.sin(x[:, :1]) + 0.1 * rng.normal(size=(600, 1))
    # a learning rate this large blows the weights up within two epochs
    spec = small_spec(max_epochs=100, patience=100, learning_rate=0.3, log_scale_clip=(-300.0, 300.0),
                      epsilon=0.0, log_scale_l2=0.0, lr_plateau_factor=1.0, dropconnect=0.0)
    net = N.fit_residual_network(x, r, spec, seed=0)
    info = net.info_dict(["a"])["a"]
    assert info["nan_epoch"] >= 0
    assert info["epochs_run"] == info["nan_epoch"] + 1               # stopped right there
    assert info["best_epoch"] < info["nan_epoch"]
    assert all(np.isfinite(np.asarray(leaf)).all() for leaf in jax.tree.leaves(net.params))
    assert not np.isfinite(np.asarray(net.info.val_loss[0])[info["nan_epoch"]]) or \
        not np.isfinite(np.asarray(net.info.train_loss[0])[info["nan_epoch"]])


@pytest.mark.extended
def test_vmap_over_axes_equals_one_axis_alone():
    x, r1, _ = _hetero_problem(800, 2)
    r = np.column_stack([r1[:, 0], -2 * r1[:, 0] + 1, np.cos(3 * x[:, 2])])
    spec = small_spec(max_epochs=5, patience=5)
    fit_rows, val_rows = N.validation_rows(800, 0.1, seed=0)
    st = N.Standardizer.fit(x[fit_rows], r[fit_rows])
    keys = jax.vmap(lambda a: jax.random.fold_in(jax.random.key(7), a))(jnp.arange(3))
    args = (st.x(x[fit_rows]), st.r(r[fit_rows]), st.x(x[val_rows]), st.r(r[val_rows]))
    p3, info3 = N._train_axes(spec, keys, *args)
    for a in (0, 2):
        xf, rf, xv, rv = args
        p1, info1 = N._train_axes(spec, keys[a:a + 1], xf, rf[:, a:a + 1], xv, rv[:, a:a + 1])
        for l3, l1 in zip(jax.tree.leaves(p3), jax.tree.leaves(p1)):
            np.testing.assert_allclose(l3[a], l1[0], rtol=2e-4, atol=2e-6)
        np.testing.assert_allclose(info3.val_loss[a], info1.val_loss[0], rtol=1e-4)


@pytest.mark.extended
def test_chunked_training_is_the_one_loop_and_reports_progress():
    """Training in compiled chunks (for progress), with the last axis continuing alone once the
    others stopped, runs the same epochs as build_trainer's single vmapped while_loop: the same
    epochs per axis and the same weights and losses up to float32 rounding (differently fused
    programs: 1e-6 absolute on weights of order 1, losses to 1e-5) for any chunk size; progress
    hears every chunk with the epochs and val loss. Two pure-noise axes stop early, so the
    last-axis-alone path runs."""
    x, r1, _ = _hetero_problem(600, 2)
    noise = np.random.default_rng(5).normal(size=(600, 2))
    r = np.column_stack([r1[:, 0], noise])
    spec = small_spec(max_epochs=40, patience=6)
    fit_rows, val_rows = N.validation_rows(600, 0.1, seed=0)
    st = N.Standardizer.fit(x[fit_rows], r[fit_rows])
    keys = jax.vmap(lambda a: jax.random.fold_in(jax.random.key(3), a))(jnp.arange(3))
    args = (st.x(x[fit_rows]), st.r(r[fit_rows]), st.x(x[val_rows]), st.r(r[val_rows]))

    def one_loop(key, r_f, r_v):                     # the un-chunked reference: build_trainer's single loop
        k_init, k_train = jax.random.split(key)
        p0 = N.init(k_init, spec.n_features, spec.n_out, hidden_layers=spec.hidden_layers, width=spec.width)
        return N.build_trainer(spec)(p0, k_train, args[0], r_f, args[2], r_v)

    p_ref, info_ref = jax.jit(jax.vmap(one_loop, in_axes=(0, 1, 1)))(keys, args[1], args[3])
    epochs = np.asarray(info_ref.epochs_run)
    assert epochs[0] > epochs[1:].max() + 7          # the last axis runs alone for at least a chunk of 7
    seen = []
    for chunk in (1, 7, 1000):
        p, info = N._train_axes(spec, keys, *args, chunk=chunk, progress=seen.append if chunk == 7 else None)
        for a, c in zip(jax.tree.leaves(p), jax.tree.leaves(p_ref)):
            np.testing.assert_allclose(a, c, rtol=0, atol=1e-6)
        np.testing.assert_allclose(info.val_loss, info_ref.val_loss, rtol=1e-5)
        np.testing.assert_array_equal(info.epochs_run, info_ref.epochs_run)
    assert len(seen) >= 2 and seen[-1].done.all() and np.array_equal(seen[-1].epochs, np.asarray(info_ref.epochs_run))
    assert all(np.all(b.epochs >= a.epochs) for a, b in zip(seen, seen[1:]))
    first = seen[0]
    np.testing.assert_allclose(first.val_loss, np.asarray(info_ref.val_loss)[:, 6], rtol=1e-5)   # epoch 7's loss
    # the job saves the curves as a figure
    from bayesmag._src.app.network_plots import loss_curves
    net = N.ResidualNetwork(spec, p, st, jax.device_get(info), 0, 0)
    path = loss_curves(Path(tempfile.mkdtemp()) / "loss.png", {"gaussian": net}, axes=("a", "b", "c"))
    assert path.stat().st_size > 0


def test_axes_trained_on_threads_equal_one_vmapped_call_and_do_not_depend_on_threads():
    """_train_parallel (each axis alone, on threads, as fit_residual_network trains) gives every axis the
    weights, losses and epochs of one vmapped _train_axes call (float32 rounding: 1e-6 on weights of
    order 1), bit-identical results for 1, 2 or 3 threads, and merged progress covering all three axes."""
    x, r1, _ = _hetero_problem(600, 2)
    r = np.column_stack([r1[:, 0], np.random.default_rng(5).normal(size=(600, 2))])
    spec = small_spec(max_epochs=40, patience=6)
    fit_rows, val_rows = N.validation_rows(600, 0.1, seed=0)
    st = N.Standardizer.fit(x[fit_rows], r[fit_rows])
    keys = N._axis_keys(3, 3)
    args = (st.x(x[fit_rows]), st.r(r[fit_rows]), st.x(x[val_rows]), st.r(r[val_rows]))
    p1, info1 = N._train_axes(spec, keys, *args)
    seen = []
    p2, info2 = N._train_parallel(spec, keys, *args, progress=seen.append, threads=2)
    for a, b in zip(jax.tree.leaves(p1), jax.tree.leaves(p2)):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(info1.epochs_run, info2.epochs_run)
    np.testing.assert_allclose(info1.val_loss, info2.val_loss, rtol=1e-5)
    assert seen and all(p.epochs.shape == (3,) for p in seen) and seen[-1].done.all()
    np.testing.assert_array_equal(seen[-1].epochs, np.asarray(info1.epochs_run))
    for threads in (1, 3):                      # one core, or BAYESMAG_TRAIN_THREADS: the same numbers
        p3, info3 = N._train_parallel(spec, keys, *args, threads=threads)
        for a, b in zip(jax.tree.leaves(p2), jax.tree.leaves(p3)):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(info3.val_loss, info2.val_loss)


def test_merged_progress_counts_waiting_trainings_at_zero_and_stopped_ones_as_finished():
    a = N.TrainProgress(np.array([10, 40]), np.array([0.5, 0.2]), np.array([0.6, 0.3]), np.array([False, True]), 40)
    p = N.merge_progress([None, a], 2, 40)
    np.testing.assert_array_equal(p.epochs, [0, 0, 10, 40])
    np.testing.assert_array_equal(p.done, [False, False, False, True])
    assert np.isnan(p.best_val_loss[:2]).all() and p.best_val_loss[3] == 0.2 and p.max_epochs == 40
    update, bar = N.progress_bar(40, 4)
    try:
        update(p)
        assert bar.n == 10 + 40 and bar.total == 160          # the stopped axis counts all its epochs
        update(N.merge_progress([a, a], 2, 40))
        assert bar.n == 100
    finally:
        bar.close()


# --------------------------------------------------------------------------- MC inference


@pytest.mark.parametrize("likelihood,df", [("gaussian", 4.0), ("student_t", None)])
@pytest.mark.extended
def test_mc_inference_matches_a_loop_over_passes(likelihood, df):
    x, r, _ = _hetero_problem(600, 3)
    spec = small_spec(likelihood=likelihood, student_t_df=df, dropconnect=0.2)
    # inference does not care whether the weights were trained: two random networks
    params = jax.vmap(lambda k: N.init(k, 4, spec.n_out, hidden_layers=spec.hidden_layers, width=spec.width))(
        jax.random.split(jax.random.key(0), 2))
    net = N.ResidualNetwork(spec, params, N.Standardizer.fit(x, np.column_stack([r, 3 * r])), None, 600, 0)
    xt = x[:50]
    passes = 16
    pred = N.mc_predict(net, xt, passes=passes, seed=5)
    # the same passes by hand: key (t, a) from split(key(5), (passes, A))
    keys = jax.random.split(jax.random.key(5), (passes, 2))
    st = net.standardizer

    @jax.jit
    def one_pass(p, k):
        d = N.head_distribution(spec, N.apply(p, st.x(xt), k, dropconnect=spec.dropconnect))
        return d.mean, d.variance

    means, variances = np.zeros((passes, 50, 2)), np.zeros((passes, 50, 2))
    for t in range(passes):
        for a in range(2):
            m, v = one_pass(jax.tree.map(lambda l: l[a], net.params), keys[t, a])
            means[t, :, a] = np.asarray(m) * st.r_scale[a] + st.r_mean[a]
            variances[t, :, a] = np.asarray(v) * st.r_scale[a] ** 2
    np.testing.assert_allclose(pred.mean, means.mean(0), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(pred.aleatoric**2, variances.mean(0), rtol=1e-4)
    np.testing.assert_allclose(pred.epistemic**2, means.var(0, ddof=1), rtol=1e-3, atol=1e-12)
    np.testing.assert_allclose(pred.total**2, pred.aleatoric**2 + pred.epistemic**2, rtol=1e-12)
    assert np.all(pred.epistemic > 0)                  # DropConnect is active at inference
    if likelihood == "student_t":
        assert pred.shape["df"].shape == (50, 2) and np.all(pred.shape["df"] > 2)


# --------------------------------------------------------------------------- bad input


def test_bad_network_settings_are_value_errors_naming_the_setting():
    """The library names its own parameters (plain ValueError, no config keys)."""
    x, r, _ = _hetero_problem(300, 4)
    with pytest.raises(ValueError, match=r"'width' or 'hidden_layers'") as e:
        N.fit_residual_network(x, r, N.NetworkSpec(hidden_layers=4, width=64), seed=0)
    assert "network." not in str(e.value) and not isinstance(e.value, bm.ConfigError)
    with pytest.raises(ValueError, match=r"^validation_fraction = 0.05 leaves"):
        N.fit_residual_network(x, r, small_spec(), validation_fraction=0.05, seed=0)
    with pytest.raises(ValueError, match=r"gaussian.*laplace.*student_t"):
        N.NetworkSpec(likelihood="cauchy")
    with pytest.raises(ValueError, match=r"^dropconnect = 1.0 must be in \[0, 1\)"):
        N.NetworkSpec(dropconnect=1.0)
    with pytest.raises(ValueError, match=r"^student_t_df = 2.0 must be a number > 2"):
        N.NetworkSpec(likelihood="student_t", student_t_df=2.0)
    with pytest.raises(ValueError, match=r"^passes = 1 must be at least 2"):
        N.mc_predict(None, x, passes=1)


def test_config_reports_library_errors_with_the_key_path():
    raw = {"data": {"source": "simulated"}, "network": {"dropconnect": 1.0}}
    with pytest.raises(bm.ConfigError, match=r"^Config key 'network.dropconnect' = 1.0 must be in \[0, 1\)"):
        config_from_dict(raw)
    raw["network"] = {"student_t_df": "guess", "likelihoods": ["student_t"]}
    with pytest.raises(bm.ConfigError, match=r"^Config key 'network.student_t_df' = 'guess'"):
        config_from_dict(raw)
    raw["network"] = {"likelihood": "laplace"}                    # a spec field the job sets, not the table
    with pytest.raises(bm.ConfigError, match=r"Unknown config key 'network.likelihood'"):
        config_from_dict(raw)
    try:
        N.check_network_size(N.NetworkSpec(), 100)
    except ValueError as e:
        msg = str(config_error(e, "network", ("width", "hidden_layers")))
    assert "'network.width' or 'network.hidden_layers'" in msg


def test_one_settings_type_for_the_table_and_the_library():
    """[network] is NetworkSpec plus the job's switches: every spec setting is a table key with the
    same default, and the spec of a likelihood carries the table's values."""
    from bayesmag._src.app.config import NetworkConfig
    spec_fields = {f.name: f.default for f in dataclasses.fields(N.NetworkSpec)}
    cfg_fields = {f.name: f.default for f in dataclasses.fields(NetworkConfig)}
    assert issubclass(NetworkConfig, N.NetworkSpec)
    same = [k for k in spec_fields if k not in NetworkConfig.job_defaults]
    assert {k: cfg_fields[k] for k in same} == {k: spec_fields[k] for k in same}
    assert NetworkConfig.job_defaults == ("validation",) and cfg_fields["validation"] == "time_blocks"
    cfg = config_from_dict({"data": {"source": "simulated"},
                            "network": {"width": 8, "student_t_df": "learn", "likelihoods": ["student_t"]}})
    spec = cfg.network.spec("student_t")
    assert type(spec) is N.NetworkSpec and spec.width == 8 and spec.df is None and spec.fixed_shape == {}
    assert "likelihood" not in cfg.to_dict()["network"] and cfg.to_dict()["network"]["student_t_df"] == "learn"
    assert N.NetworkSpec.from_dict({**N.NetworkSpec().to_dict(), "df": None, "student_t_df": None}).df is None
    assert N.NetworkSpec.from_dict({"likelihood": "student_t", "df": 5.0}).fixed_shape == {"df": 5.0}


# --------------------------------------------------------------------------- Fourier input features


FOURIER_SD_RTOL = 0.1        # 4 x 400 frequencies: their sd within 10 % of fourier_scale (sd error ~3.5 %)


@pytest.mark.parametrize("jit", [False, True])
def test_fourier_embedding_is_the_closed_form(jit):
    spec = small_spec(fourier_features=400, fourier_scale=3.0)
    b = N.fourier_frequencies(spec, seed=7)
    assert b.shape == (4, 400)
    np.testing.assert_array_equal(b, N.fourier_frequencies(spec, seed=7))          # seeded
    assert abs(b.std() / 3.0 - 1) < FOURIER_SD_RTOL and abs(b.mean()) < 0.3
    z = np.random.default_rng(0).normal(size=(5, 4)).astype(np.float32)
    f = jax.jit(N.embed)(z, b) if jit else N.embed(jnp.asarray(z), b)
    a = 2 * np.pi * z.astype(np.float64) @ b
    np.testing.assert_allclose(np.asarray(f), np.hstack([z, np.sin(a), np.cos(a)]), atol=2e-4)
    assert N.embed(jnp.asarray(z), None) is not None and np.array_equal(N.embed(jnp.asarray(z), None), z)
    assert spec.n_features == 804
    assert spec.n_params == N.count_params(804, 2, hidden_layers=2, width=16)


@pytest.mark.extended
def test_fourier_features_fit_structure_a_plain_mlp_smooths_over():
    """A residual with 3 cycles across the standardised input range: the same small ReLU MLP
    leaves most of it unfitted, with 16 Fourier features (scale 1) it fits to near the noise."""
    rng = np.random.default_rng(3)
    x = np.zeros((3000, 4))
    x[:, 0] = rng.uniform(-1.7, 1.7, 3000)           # ~ standardised already
    r = (0.3 * np.sin(2 * np.pi * 3 * x[:, 0] / 3.4) + 0.02 * rng.normal(size=3000))[:, None]
    kw = dict(width=32, max_epochs=120, patience=30, learning_rate=3e-3, batch_size=64, dropconnect=0.0)
    grid = np.zeros((200, 4))
    grid[:, 0] = np.linspace(-1.6, 1.6, 200)
    truth = 0.3 * np.sin(2 * np.pi * 3 * grid[:, 0] / 3.4)
    err = {}
    for m in (0, 16):
        net = N.fit_residual_network(x, r, small_spec(fourier_features=m, **kw), seed=0)
        err[m] = np.sqrt(np.mean((N.mc_predict(net, grid, passes=2).mean[:, 0] - truth) ** 2))
    assert err[16] < 0.015                      # under the noise sd (0.02) from the truth
    assert err[16] < 0.5 * err[0]


def test_bad_fourier_settings_are_value_errors():
    with pytest.raises(ValueError, match=r"^fourier_features = -1"):
        N.NetworkSpec(fourier_features=-1)
    with pytest.raises(ValueError, match=r"^fourier_scale = 0.0"):
        N.NetworkSpec(fourier_scale=0.0)


# --------------------------------------------------------------------------- validation rows and recalibration


def test_time_block_validation_rows_are_one_block_per_run():
    groups = np.repeat([1, 2, 5], [400, 250, 350])
    fit, val = N.validation_rows(1000, 0.1, seed=3, kind="time_blocks", groups=groups)
    assert np.array_equal(np.sort(np.concatenate([fit, val])), np.arange(1000))
    for g, n in [(1, 400), (2, 250), (5, 350)]:
        rows = val[groups[val] == g]
        assert rows.size == round(0.1 * n) and np.all(np.diff(rows) == 1)     # contiguous, 10 % of the run
    with pytest.raises(ValueError, match=r"^validation = 'blocks'.*random.*time_blocks"):
        N.validation_rows(1000, 0.1, seed=0, kind="blocks")


RECAL_RTOL = 0.012           # the grid step is log(400)/600 = 0.010 in log c


@pytest.mark.parametrize("likelihood", ["gaussian", "laplace", "student_t"])
@pytest.mark.extended
def test_recalibration_minimises_the_validation_nll(likelihood):
    """The fitted factor equals scipy's 1-D minimiser of the same NLL (Gaussian: the closed form)."""
    from scipy import optimize, stats

    x, r, _ = _hetero_problem(1500, 5)
    spec = small_spec(likelihood=likelihood, max_epochs=30, patience=30, learning_rate=3e-3, batch_size=64)
    net = N.fit_residual_network(x, r, spec, seed=1)
    xv, rv = x[net.val_rows], r[net.val_rows] * 1.0
    rv = rv + 0.6 * (rv - np.sin(2 * xv[:, :1]))                      # wider errors than trained on: c > 1
    out = N.recalibrate(net, xv, rv, passes=20, seed=4)
    base = N.mc_predict(net, xv, passes=20, seed=4)
    mu, var, e = base.mean[:, 0], base.aleatoric[:, 0] ** 2 + base.epistemic[:, 0] ** 2, rv[:, 0]

    def nll(logc):
        v = np.exp(logc) * var
        if likelihood == "gaussian":
            return -np.mean(stats.norm.logpdf(e, mu, np.sqrt(v)))
        if likelihood == "laplace":
            return -np.mean(stats.laplace.logpdf(e, mu, np.sqrt(v / 2)))
        return -np.mean(stats.t.logpdf(e, 4.0, mu, np.sqrt(v * 2 / 4)))

    ref = np.exp(optimize.minimize_scalar(nll, bounds=(np.log(0.05), np.log(20)), method="bounded").x)
    assert out.variance_scale[0] > 1.2
    np.testing.assert_allclose(out.variance_scale[0], ref, rtol=RECAL_RTOL)
    if likelihood == "gaussian":
        np.testing.assert_allclose(out.variance_scale[0], np.mean((e - mu) ** 2 / var), rtol=RECAL_RTOL)
    scaled = N.mc_predict(out, xv, passes=20, seed=4)                 # both parts scaled, mean untouched
    np.testing.assert_allclose(scaled.aleatoric, base.aleatoric * np.sqrt(out.variance_scale), rtol=1e-6)
    np.testing.assert_allclose(scaled.epistemic, base.epistemic * np.sqrt(out.variance_scale), rtol=1e-6)
    np.testing.assert_array_equal(scaled.mean, base.mean)
