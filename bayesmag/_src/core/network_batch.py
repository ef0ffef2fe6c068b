r"""Residual networks of many recordings trained in one compiled batch (the fleet's network stage).

:func:`fit_residual_networks` is :func:`~bayesmag._src.core.network.fit_residual_network` for a list of
recordings (e.g. one per sensor of a fleet): every (recording, axis) network is one training of the same
compiled program, ``vmap``-ped over ``batch_size`` recordings x 3 axes at a time. Recordings of different
lengths are zero-padded to one row count (a multiple of :data:`ROW_BUCKET`) and masked: the padded epoch
(``_trainer(...).masked_epoch``) draws the same permutation of the real rows
(:func:`~bayesmag._src.core.network.masked_permutation`), the same minibatches, DropConnect masks and step keys
as the unpadded one, skips the steps after the recording's last minibatch, and takes the validation loss over
the real validation rows only. So each recording's network is the one ``fit_residual_network`` trains alone with
the same seed, up to float32 rounding (``tests/test_network_batch.py`` states the tolerance). Training stops per
network (early stopping); a batch runs until its last network stops.

:func:`mc_predict_many` is :func:`~bayesmag._src.core.network.mc_predict` for many networks at once (the same
masks: one key per pass shared by all recordings, as for one).
"""

from __future__ import annotations

import functools
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from bayesmag._src.core.network import (DTYPE, MCPrediction, NetworkSpec, ResidualNetwork, Standardizer, TrainProgress,
                                        check_network_size, embed, fourier_frequencies, validation_rows)
from bayesmag._src.core.network.infer import _mc_axes, _mc_in_units
from bayesmag._src.core.network.train import (TRAIN_CHUNK_EPOCHS, _axis_keys, _init_axes, _trainer, report_chunk,
                                              shuffle_rounds)

__all__ = ["fit_residual_networks", "mc_predict_many", "ROW_BUCKET"]

#: Rows are padded to a multiple of this, so batches of similar recordings share one compiled program.
ROW_BUCKET = 256


def _bucket(n: int) -> int:
    return max(ROW_BUCKET, -(-int(n) // ROW_BUCKET) * ROW_BUCKET)


@functools.partial(jax.jit, static_argnames=("spec",))
def _train_masked_chunk(spec: NetworkSpec, state, stop, x_fit, r_fit, n_fit, x_val, r_val, n_val, rounds):
    """Run every training (leading axis) until it stops or reaches epoch ``stop``; padded rows masked."""
    t = _trainer(spec)

    def one(s, xf, rf, nf, xv, rv, nv, ro):
        return jax.lax.while_loop(lambda s: t.running(s) & (s.epoch < stop),
                                  lambda s: t.masked_epoch(s, xf, rf, nf, xv, rv, nv, ro), s)

    s = jax.vmap(one)(state, x_fit, r_fit, n_fit, x_val, r_val, n_val, rounds)
    return s, jax.vmap(t.running)(s)


def _pad(a: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros((n,) + a.shape[1:], np.float32)
    out[:a.shape[0]] = a
    return out


def fit_residual_networks(xs: Sequence[np.ndarray], rs: Sequence[np.ndarray], spec: NetworkSpec, *,
                          validation_fraction: float | None = None, seed: int | None = None,
                          validation: str | None = None, groups: Sequence[np.ndarray] | None = None,
                          batch_size: int = 16,
                          progress: Callable[[TrainProgress], None] | None = None) -> list[ResidualNetwork]:
    """One :class:`~bayesmag._src.core.network.ResidualNetwork` per recording ``(xs[i], rs[i])`` (``(n_i, n_in)``,
    ``(n_i, A)``), trained in batches of ``batch_size`` recordings (memory ~ batch x A x rows).

    Each equals ``fit_residual_network(xs[i], rs[i], spec, validation_fraction=..., seed=seed,
    validation=..., groups=groups[i])`` up to float32 rounding; ``progress`` hears after every chunk of
    :data:`~bayesmag._src.core.network.TRAIN_CHUNK_EPOCHS` epochs (all trainings of the batch).

    Example:
      >>> import numpy as np
      >>> rng = np.random.default_rng(0)
      >>> xs = [rng.normal(size=(n, 4)) for n in (300, 250)]
      >>> spec = NetworkSpec(hidden_layers=1, width=4, max_epochs=3, batch_size=32)
      >>> nets = fit_residual_networks(xs, [x[:, :3] ** 2 for x in xs], spec)
      >>> [int(e) for e in nets[1].info.epochs_run]
      [3, 3, 3]
    """
    validation_fraction = spec.validation_fraction if validation_fraction is None else validation_fraction
    seed = spec.seed if seed is None else seed
    validation = spec.validation if validation is None else validation
    if len(xs) != len(rs) or not len(xs):
        raise ValueError(f"need one residual array per input array (got {len(xs)} and {len(rs)}), at least one.")
    freqs = fourier_frequencies(spec, seed) if spec.fourier_features else None
    prep = []
    for i, (x, r) in enumerate(zip(xs, rs)):
        x, r = np.asarray(x, np.float64), np.asarray(r, np.float64)
        if x.ndim != 2 or x.shape[1] != spec.n_in or r.ndim != 2 or r.shape[0] != x.shape[0]:
            raise ValueError(f"recording {i}: x must be (n, {spec.n_in}) and r (n, A); got {x.shape} and {r.shape}.")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(r))):
            raise ValueError(f"recording {i}: x and r must be finite.")
        g = None if groups is None else groups[i]
        fit_rows, val_rows = validation_rows(x.shape[0], validation_fraction, seed=seed, kind=validation, groups=g)
        check_network_size(spec, fit_rows.size)
        st = Standardizer.fit(x[fit_rows], r[fit_rows])
        prep.append((st, fit_rows, val_rows, np.asarray(embed(st.x(x[fit_rows]), freqs)), np.asarray(st.r(r[fit_rows])),
                     np.asarray(embed(st.x(x[val_rows]), freqs)), np.asarray(st.r(r[val_rows]))))
    n_axes = prep[0][4].shape[1]
    if any(p[4].shape[1] != n_axes for p in prep):
        raise ValueError("every recording needs the same number of residual columns.")
    size_f = _bucket(max(p[1].size for p in prep))
    size_v = _bucket(max(p[2].size for p in prep))
    ckey = spec.compiled_key()
    axis_keys = _axis_keys(seed, n_axes)
    t = _trainer(ckey)
    n_rec = len(prep)
    b = max(1, min(int(batch_size), n_rec))
    params_all, info_all = [], []
    for lo in range(0, n_rec, b):
        members = list(range(lo, min(lo + b, n_rec)))
        members += [members[0]] * (b - len(members))          # same shapes every batch: one compilation
        rec = np.repeat(members, n_axes)                      # training k: recording rec[k], axis ax[k]
        ax = np.tile(np.arange(n_axes), b)
        xf = np.stack([_pad(prep[i][3], size_f) for i in members])[np.repeat(np.arange(b), n_axes)]
        xv = np.stack([_pad(prep[i][5], size_v) for i in members])[np.repeat(np.arange(b), n_axes)]
        rf = np.stack([_pad(prep[i][4][:, a], size_f) for i, a in zip(rec, ax)])
        rv = np.stack([_pad(prep[i][6][:, a], size_v) for i, a in zip(rec, ax)])
        nf = np.array([prep[i][1].size for i in rec], np.int32)
        nv = np.array([prep[i][2].size for i in rec], np.int32)
        rounds = np.array([shuffle_rounds(n) for n in nf], np.int32)
        s = _init_axes(ckey, axis_keys[jnp.asarray(ax)])
        stop = 0
        while stop < spec.max_epochs:
            stop = min(stop + TRAIN_CHUNK_EPOCHS, spec.max_epochs)
            s, running = _train_masked_chunk(ckey, s, stop, jnp.asarray(xf, DTYPE), jnp.asarray(rf, DTYPE),
                                             jnp.asarray(nf), jnp.asarray(xv, DTYPE), jnp.asarray(rv, DTYPE),
                                             jnp.asarray(nv), jnp.asarray(rounds))
            running = np.asarray(running)
            report_chunk(progress, s, running, spec.max_epochs)
            if not running.any():
                break
        keep = min(b, n_rec - lo)
        params_all.append(jax.tree.map(lambda a: np.asarray(a)[:keep * n_axes], s.best_params))
        info_all.append(jax.tree.map(lambda a: np.asarray(a)[:keep * n_axes], jax.device_get(jax.vmap(t.info)(s))))
    params = jax.tree.map(lambda *a: np.concatenate(a), *params_all)
    info = jax.tree.map(lambda *a: np.concatenate(a), *info_all)
    nets = []
    for i, (st, fit_rows, val_rows, *_) in enumerate(prep):
        sl = slice(i * n_axes, (i + 1) * n_axes)
        nets.append(ResidualNetwork(spec, jax.tree.map(lambda a: jnp.asarray(a[sl]), params),
                                    st, jax.tree.map(lambda a: a[sl], info), int(fit_rows.size), int(val_rows.size),
                                    freqs, None, val_rows))
    return nets


@functools.partial(jax.jit, static_argnames=("spec", "passes"))
def _mc_many(spec: NetworkSpec, params, x, key, passes: int):
    return jax.vmap(lambda p, xx: _mc_axes(spec, p, xx, key, passes))(params, x)


def mc_predict_many(nets: Sequence[ResidualNetwork], xs: Sequence[np.ndarray], *, passes: int, seed: int = 0,
                    batch_size: int = 16) -> list[MCPrediction]:
    """:func:`~bayesmag._src.core.network.mc_predict` of ``nets[i]`` on ``xs[i]`` for every ``i``, ``batch_size``
    networks per compiled call (rows padded to a multiple of :data:`ROW_BUCKET`). The networks share one spec."""
    if len(nets) != len(xs) or not len(nets):
        raise ValueError(f"need one input array per network (got {len(nets)} and {len(xs)}), at least one.")
    if passes < 2:
        raise ValueError(f"passes = {passes} must be at least 2 (the epistemic variance is a sample variance).")
    spec = nets[0].spec.compiled_key()
    if any(n.spec.compiled_key() != spec for n in nets):
        raise ValueError("mc_predict_many needs networks of one spec.")
    z = [np.asarray(embed(n.standardizer.x(x), n.frequencies)) for n, x in zip(nets, xs)]
    size = _bucket(max(a.shape[0] for a in z))
    b = max(1, min(int(batch_size), len(nets)))
    key = jax.random.key(seed)
    out = []
    for lo in range(0, len(nets), b):
        members = list(range(lo, min(lo + b, len(nets))))
        members += [members[0]] * (b - len(members))
        params = jax.tree.map(lambda *a: jnp.stack(a), *[nets[i].params for i in members])
        x = jnp.asarray(np.stack([_pad(z[i], size) for i in members]), DTYPE)
        mean, alea, epi, shape = jax.device_get(_mc_many(spec, params, x, key, passes))
        for j, i in enumerate(members[:min(b, len(nets) - lo)]):
            k = z[i].shape[0]
            out.append(_mc_in_units(nets[i], mean[j, :k], alea[j, :k], epi[j, :k],
                                    {name: v[j, :k] for name, v in shape.items()}))
    return out
