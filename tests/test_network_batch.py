"""Residual networks of many recordings in one batch (core/network_batch.py) against the single-recording training
(core/network.fit_residual_network) with the same seed: same epochs, same weights up to float32 rounding."""

import jax
import numpy as np
import pytest

from bayesmag._src.core.network import NetworkSpec, fit_residual_network, mc_predict
from bayesmag._src.core.network.train import masked_permutation, shuffle_rounds
from bayesmag._src.core.network_batch import fit_residual_networks, mc_predict_many

#: float32 rounding: the padded, vmapped program sums the same numbers in another order (2.4e-7 apart per epoch).
#: Now and then a pre-activation within rounding of 0 takes the other side of a ReLU in one step, and Adam carries
#: that on: here one axis of 9 ends 5.4e-4 apart (max |w| ~ 1), the others 2.4e-7. A different permutation,
#: minibatch or mask moves weights by > 0.05 (checked below with another seed), so 5e-3 still tells them apart.
ATOL_WEIGHTS = 5e-3


@pytest.mark.parametrize("n, size", [(5, 5), (37, 256), (1600, 2048), (1700, 2048), (5000, 5120)])
def test_masked_permutation_is_jax_permutation(n, size):
    """Padded to ``size``, the permutation of the real rows is jax.random.permutation's (1 and 2 sort rounds)."""
    key = jax.random.key(7)
    got = np.asarray(jax.jit(masked_permutation, static_argnums=2)(key, n, size, shuffle_rounds(n)))
    np.testing.assert_array_equal(got[:n], np.asarray(jax.random.permutation(key, n)))
    np.testing.assert_array_equal(np.sort(got[n:]), np.arange(n, size))


@pytest.fixture(scope="module")
def problems():
    """Three residual problems, two runs each (time-block validation): 640 rows are padded to the 900 of the first;
    the third (900 rows, other data) shares the single-run compilation of the first (each new length compiles)."""
    rng = np.random.default_rng(0)
    xs, rs, gs = [], [], []
    for n in (900, 640, 900):
        x = rng.normal(size=(n, 4))
        r = np.column_stack([np.sin(x[:, 0]) + 0.1 * rng.normal(size=n), 0.1 * x[:, 1] ** 2 + 0.05 * rng.normal(size=n),
                             0.1 * rng.normal(size=n)])
        xs.append(x), rs.append(r), gs.append(np.repeat([1, 2], [n // 2, n - n // 2]))
    return xs, rs, gs


SPEC = NetworkSpec(hidden_layers=2, width=16, max_epochs=40, patience=8, batch_size=16, validation="time_blocks",
                   dropconnect=0.05)


@pytest.fixture(scope="module")
def batched(problems):
    xs, rs, gs = problems
    return fit_residual_networks(xs, rs, SPEC, seed=3, groups=gs, batch_size=2)   # 2 batches, one filler copy


@pytest.mark.extended
def test_batched_networks_equal_single_trainings(problems, batched):
    xs, rs, gs = problems
    spec, nets = SPEC, batched
    mcs = mc_predict_many(nets, xs, passes=20, seed=5, batch_size=2)
    stopped_early = 0
    for i in range(3):
        ref = fit_residual_network(xs[i], rs[i], spec, seed=3, groups=gs[i])
        np.testing.assert_array_equal(nets[i].info.epochs_run, ref.info.epochs_run)
        np.testing.assert_array_equal(nets[i].info.best_epoch, ref.info.best_epoch)
        np.testing.assert_array_equal(nets[i].val_rows, ref.val_rows)
        stopped_early += int((np.asarray(ref.info.epochs_run) < spec.max_epochs).sum())
        for a, b in zip(jax.tree.leaves(nets[i].params), jax.tree.leaves(ref.params)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=ATOL_WEIGHTS)
        m = mc_predict(ref, xs[i], passes=20, seed=5)
        sd = rs[i].std(axis=0)
        for got, want in zip(mcs[i][:3], m[:3]):           # mean, aleatoric, epistemic within 1 % of the residual sd
            np.testing.assert_allclose(got, want, rtol=0, atol=0.01 * sd.max())
    assert stopped_early >= 1              # early stopping inside the batch was exercised
    other = fit_residual_network(xs[0], rs[0], spec, seed=4, groups=gs[0])     # the test can fail: another seed
    assert max(float(np.abs(np.asarray(a) - np.asarray(b)).max())
               for a, b in zip(jax.tree.leaves(nets[0].params), jax.tree.leaves(other.params))) > 10 * ATOL_WEIGHTS


def test_mc_predict_many_equals_mc_predict_on_the_same_network(problems, batched):
    """Batched inference (rows padded) is the single inference of the same network, pass for pass."""
    xs, rs, gs = problems
    nets = batched[:2]
    for net, x, got in zip(nets, xs, mc_predict_many(nets, xs[:2], passes=10, seed=2)):
        want = mc_predict(net, x, passes=10, seed=2)
        for g, w in zip(got[:3], want[:3]):
            np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-7)


def test_bad_input_names_the_recording():
    spec = NetworkSpec(hidden_layers=1, width=4, max_epochs=2)
    x = np.zeros((300, 4))
    with pytest.raises(ValueError, match="recording 1"):
        fit_residual_networks([x, np.zeros((300, 3))], [x[:, :3], x[:, :3]], spec)
