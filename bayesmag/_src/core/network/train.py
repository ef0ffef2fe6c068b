"""Training: the compiled per-axis epoch loop (early stopping, chunks of epochs, threads over the axes), validation rows, size checks and :func:`fit_residual_network`."""

from __future__ import annotations

import functools
import math
import os
import threading
from concurrent.futures import Executor, ThreadPoolExecutor
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from bayesmag._src.core.network.spec import DTYPE, MAX_PARAMS_PER_ROW, MIN_VALIDATION_ROWS, NetworkSpec, VALIDATION_KINDS
from bayesmag._src.core.network.model import (Params, apply, drop_positions, embed, fourier_frequencies, init,
                                              regularized_nll, uses_drop_positions)
from bayesmag._src.core.network.progress import TrainProgress, merged_reporter, progress_bar

__all__ = ['TrainInfo', 'TrainState', 'build_trainer', 'TRAIN_CHUNK_EPOCHS', 'SCAN_UNROLL', 'training_threads', 'Standardizer', 'ResidualNetwork', 'validation_rows', 'check_network_size', 'start_residual_network', 'fit_residual_network']


class TrainInfo(NamedTuple):
    """What training did, per axis when vmapped (leading axis 3).

    ``epochs_run``: epochs completed; ``best_epoch``: epoch (0-based) of the returned weights,
    -1 if no epoch had a finite validation loss (the initial weights are returned);
    ``nan_epoch``: epoch whose loss was non-finite (training stopped there), -1 if none;
    ``train_loss`` / ``val_loss``: per-epoch losses, ``nan`` after the last epoch run.
    """

    epochs_run: jax.Array
    best_epoch: jax.Array
    best_val_loss: jax.Array
    nan_epoch: jax.Array
    train_loss: jax.Array
    val_loss: jax.Array



class TrainState(NamedTuple):
    params: Params
    opt_state: Any
    key: jax.Array
    epoch: jax.Array
    best_params: Params
    best_loss: jax.Array
    best_epoch: jax.Array
    wait: jax.Array
    plateau: jax.Array
    nan_epoch: jax.Array
    train_loss: jax.Array
    val_loss: jax.Array



def shuffle_rounds(n: int) -> int:
    """Sort rounds of ``jax.random.permutation(key, n)``: ``ceil(3 ln n / ln(2^32 - 1))`` (JAX's ``_shuffle``)."""
    return int(np.ceil(3 * np.log(max(1, int(n))) / np.log(np.iinfo(np.uint32).max)))


def masked_permutation(key: jax.Array, n, size: int, rounds) -> jax.Array:
    """``(size,)``: ``jax.random.permutation(key, n)`` for a traced ``n <= size``, then ``n .. size-1``.

    The same algorithm as JAX's (``rounds = shuffle_rounds(n)`` stable sorts by fresh 32-bit keys), with the
    padding elements sorted last in every round, so the real elements meet the same random bits at the same
    positions: under the partitionable threefry (``jax_threefry_partitionable``, JAX's default) the bits of a
    longer shape start with those of a shorter one (``tests/test_network_batch.py`` checks it).
    """
    x = jnp.arange(size)
    for r in range(shuffle_rounds(size)):
        key, sub = jax.random.split(key)
        bits = jax.random.bits(sub, (size,), jnp.uint32)
        _, _, xs = jax.lax.sort(((x >= n).astype(jnp.int32), bits, x), num_keys=2)
        x = jnp.where(r < rounds, xs, x)
    return x


class _Trainer(NamedTuple):
    init_state: Callable      # (params, key) -> TrainState
    epoch: Callable           # (state, x_fit, r_fit, x_val, r_val) -> state after one epoch
    running: Callable         # state -> bool: not stopped (max_epochs, patience, non-finite loss)
    info: Callable            # state -> TrainInfo
    masked_epoch: Callable    # (state, x_fit, r_fit, n_fit, x_val, r_val, n_val, rounds) -> state (padded rows)



def _trainer(spec: NetworkSpec) -> _Trainer:
    """The pieces of the training loop of one axis (pure, traceable; see :func:`build_trainer`)."""
    opt = optax.inject_hyperparams(optax.adam)(learning_rate=spec.learning_rate)
    bs = spec.batch_size
    lr_min = spec.learning_rate * spec.lr_min_factor

    # DropConnect at the paper's rates: every minibatch's dropped positions of an epoch drawn at once (vmapped
    # over the step keys: the same bits, so the same masks, as one draw per step), the masks built per step
    shapes = tuple((a, b) for a, b in zip([spec.n_features] + [spec.width] * spec.hidden_layers,
                                          [spec.width] * spec.hidden_layers + [spec.n_out]))
    by_drops = uses_drop_positions(spec.dropconnect)
    n_weights = sum(a * b for a, b in shapes)

    def step_noise(keys):
        """What each step's mask is made of: its key, or its dropped positions (drawn here, vmapped)."""
        return jax.vmap(lambda k: drop_positions(k, n_weights, spec.dropconnect))(keys) if by_drops else keys

    def loss_fn(params, noise, xb, rb, wb):
        if by_drops:
            raw = apply(params, xb, dropconnect=spec.dropconnect, activation=spec.activation, dropped=noise)
        else:
            raw = apply(params, xb, noise, dropconnect=spec.dropconnect, activation=spec.activation)
        return regularized_nll(spec, raw, rb, wb)

    grad_fn = jax.value_and_grad(loss_fn)

    def init_state(params, key):
        nan_hist = jnp.full((spec.max_epochs,), jnp.nan, DTYPE)
        return TrainState(params=params, opt_state=opt.init(params), key=key, epoch=jnp.asarray(0),
                          best_params=params, best_loss=jnp.asarray(jnp.inf, DTYPE), best_epoch=jnp.asarray(-1),
                          wait=jnp.asarray(0), plateau=jnp.asarray(0), nan_epoch=jnp.asarray(-1),
                          train_loss=nan_hist, val_loss=nan_hist)

    def epoch(s: TrainState, x_fit, r_fit, x_val, r_val) -> TrainState:
        n = x_fit.shape[0]
        n_batches = -(-n // bs)
        pad = n_batches * bs - n
        weight = jnp.concatenate([jnp.ones((n,), DTYPE), jnp.zeros((pad,), DTYPE)]).reshape(n_batches, bs)

        def step(carry, batch):
            params, opt_state = carry
            idx, w, k = batch
            loss, g = grad_fn(params, k, x_fit[idx], r_fit[idx], w)
            updates, opt_state = opt.update(g, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), loss * jnp.sum(w)

        key, k_perm, k_steps = jax.random.split(s.key, 3)
        perm = jax.random.permutation(k_perm, n)
        idx = jnp.concatenate([perm, perm[:pad]]).reshape(n_batches, bs)
        step_keys = step_noise(jax.random.split(k_steps, n_batches))
        (params, opt_state), losses = jax.lax.scan(step, (s.params, s.opt_state), (idx, weight, step_keys),
                                                   unroll=SCAN_UNROLL)
        train_loss = jnp.sum(losses) / n
        val = regularized_nll(spec, apply(params, x_val, activation=spec.activation), r_val)
        return finish(s, params, opt_state, key, train_loss, val)

    def masked_epoch(s: TrainState, x_fit, r_fit, n_fit, x_val, r_val, n_val, rounds) -> TrainState:
        """:func:`epoch` on the first ``n_fit`` of the padded fitting rows and ``n_val`` validation rows: the same
        permutation of the real rows (:func:`masked_permutation`), the same minibatches and keys, steps past the
        real rows' last minibatch left out (so it traces under ``vmap`` over recordings of different lengths)."""
        size = x_fit.shape[0]
        n_batches_max = -(-size // bs)
        p = jnp.arange(n_batches_max * bs)
        n_safe = jnp.maximum(n_fit, 1)
        key, k_perm, k_steps = jax.random.split(s.key, 3)
        perm = masked_permutation(k_perm, n_fit, size, rounds)
        src = jnp.minimum(jnp.where(p < n_fit, p, (p - n_fit) % n_safe), size - 1)   # a short last batch wraps
        idx = perm[src].reshape(n_batches_max, bs)
        weight = (p < n_fit).astype(DTYPE).reshape(n_batches_max, bs)
        active = jnp.arange(n_batches_max) < -(-n_fit // bs)
        step_keys = step_noise(jax.random.split(k_steps, n_batches_max))   # a prefix is the unpadded epoch's keys

        def step(carry, batch):
            params, opt_state = carry
            idx, w, k, on = batch
            loss, g = grad_fn(params, k, x_fit[idx], r_fit[idx], w)
            updates, new_state = opt.update(g, opt_state, params)
            new = (optax.apply_updates(params, updates), new_state)
            return jax.tree.map(lambda a, b: jnp.where(on, a, b), new, carry), jnp.where(on, loss * jnp.sum(w), 0.0)

        (params, opt_state), losses = jax.lax.scan(step, (s.params, s.opt_state), (idx, weight, step_keys, active),
                                                   unroll=SCAN_UNROLL)
        train_loss = jnp.sum(losses) / n_safe
        wv = (jnp.arange(x_val.shape[0]) < n_val).astype(DTYPE)
        val = regularized_nll(spec, apply(params, x_val, activation=spec.activation), r_val, wv)
        return finish(s, params, opt_state, key, train_loss, val)

    def finish(s: TrainState, params, opt_state, key, train_loss, val) -> TrainState:
        """Early stopping, best weights, learning-rate plateau and loss history after one epoch."""
        finite = jnp.isfinite(train_loss) & jnp.isfinite(val)
        improved = finite & (val < s.best_loss - spec.min_delta)
        best_params = jax.tree.map(lambda new, old: jnp.where(improved, new, old), params, s.best_params)
        plateau = jnp.where(improved, 0, s.plateau + 1)
        reduce = plateau >= spec.lr_plateau_patience
        lr = opt_state.hyperparams["learning_rate"]
        lr = jnp.where(reduce, jnp.maximum(lr * spec.lr_plateau_factor, lr_min), lr).astype(lr.dtype)
        opt_state = opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": lr})
        return TrainState(
            params=params, opt_state=opt_state, key=key, epoch=s.epoch + 1, plateau=jnp.where(reduce, 0, plateau),
            best_params=best_params,
            best_loss=jnp.where(improved, val, s.best_loss),
            best_epoch=jnp.where(improved, s.epoch, s.best_epoch),
            wait=jnp.where(improved, 0, s.wait + 1),
            nan_epoch=jnp.where(finite, s.nan_epoch, s.epoch),
            train_loss=s.train_loss.at[s.epoch].set(train_loss),
            val_loss=s.val_loss.at[s.epoch].set(val),
        )

    def running(s: TrainState):
        return (s.epoch < spec.max_epochs) & (s.wait < spec.patience) & (s.nan_epoch < 0)

    def info(s: TrainState) -> TrainInfo:
        return TrainInfo(epochs_run=s.epoch, best_epoch=s.best_epoch, best_val_loss=s.best_loss,
                         nan_epoch=s.nan_epoch, train_loss=s.train_loss, val_loss=s.val_loss)

    return _Trainer(init_state, epoch, running, info, masked_epoch)



def build_trainer(spec: NetworkSpec) -> Callable[..., tuple[Params, TrainInfo]]:
    """``train(params, key, x_fit, r_fit, x_val, r_val) -> (best_params, TrainInfo)`` for one axis.

    Pure and traceable (wrap in ``jax.jit`` / ``jax.vmap``): Adam on
    :func:`regularized_nll` with one DropConnect mask per minibatch, reshuffled minibatches
    every epoch, early stopping with best-weight restore, stop at the first non-finite loss.
    Inputs are float32 and already standardised.
    """
    t = _trainer(spec)

    def train(params, key, x_fit, r_fit, x_val, r_val):
        s = jax.lax.while_loop(t.running, lambda s: t.epoch(s, x_fit, r_fit, x_val, r_val), t.init_state(params, key))
        return s.best_params, t.info(s)

    return train



#: Epochs per compiled call of the training loop: between calls :func:`fit_residual_network`
#: reports progress (epochs run, best validation loss per axis). The chunks run the same
#: epochs in the same order, so the trained weights depend on it only through float32 rounding.
TRAIN_CHUNK_EPOCHS = 25



#: Minibatch steps per iteration of the compiled step loop (``jax.lax.scan(unroll=...)``).
SCAN_UNROLL = 1



@functools.partial(jax.jit, static_argnames=("spec",))
def _init_axes(spec: NetworkSpec, keys):
    t = _trainer(spec)

    def one(key):
        k_init, k_train = jax.random.split(key)
        params = init(k_init, spec.n_features, spec.n_out, hidden_layers=spec.hidden_layers, width=spec.width)
        return t.init_state(params, k_train)

    return jax.vmap(one)(keys)



@functools.partial(jax.jit, static_argnames=("spec",))
def _train_chunk(spec: NetworkSpec, state: TrainState, stop, x_fit, r_fit, x_val, r_val):
    """Run every axis's training loop until it stops or reaches epoch ``stop`` (vmapped)."""
    t = _trainer(spec)

    def one(s, r_f, r_v):
        return jax.lax.while_loop(lambda s: t.running(s) & (s.epoch < stop),
                                  lambda s: t.epoch(s, x_fit, r_f, x_val, r_v), s)

    s = jax.vmap(one, in_axes=(0, 1, 1))(state, r_fit, r_val)
    return s, jax.vmap(t.running)(s)



@functools.partial(jax.jit, static_argnums=1)
def _axis_keys(seed, n: int):
    """The training key of each axis: ``fold_in(key(seed), a)`` for ``a < n``."""
    base = jax.random.key(seed)
    return jax.vmap(lambda a: jax.random.fold_in(base, a))(jnp.arange(n))



def _train_axes(spec: NetworkSpec, keys, x_fit, r_fit, x_val, r_val, *,
                progress: Callable[[TrainProgress], None] | None = None, chunk: int = TRAIN_CHUNK_EPOCHS):
    """Init + train one network per column of ``r_fit`` (vmapped), ``chunk`` epochs per compiled call.

    :func:`fit_residual_network` calls it with one column per thread (:func:`_train_parallel`).
    """
    spec = spec.compiled_key()
    s = _init_axes(spec, keys)
    stop = 0
    while stop < spec.max_epochs:
        stop = min(stop + chunk, spec.max_epochs)
        s, running = _train_chunk(spec, s, stop, x_fit, r_fit, x_val, r_val)
        running = np.asarray(running)
        report_chunk(progress, s, running, spec.max_epochs)
        if not running.any():
            break
    t = _trainer(spec)
    return s.best_params, jax.vmap(t.info)(s)


def report_chunk(progress: Callable[[TrainProgress], None] | None, s: TrainState, running: np.ndarray,
                 max_epochs: int) -> None:
    """Tell ``progress`` (if any) where the networks of ``s`` stand after a chunk of epochs."""
    if progress is not None:
        ep = np.asarray(s.epoch)
        last = np.asarray(s.val_loss)[np.arange(ep.size), np.maximum(ep - 1, 0)]
        progress(TrainProgress(ep, np.asarray(s.best_loss), last, ~running, max_epochs))



def training_threads() -> int:
    """Threads :func:`fit_residual_network` trains the axes on: the cores this process may use, at
    most 3 (``BAYESMAG_TRAIN_THREADS`` overrides). The results do not depend on it."""
    env = os.environ.get("BAYESMAG_TRAIN_THREADS", "").strip()
    if env:
        return max(1, int(env))
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cores, 3))



#: Held while :func:`_compile_once` compiles: XLA compiling on several threads at once (the axes and the
#: cross-conformal folds train on threads) crashed the interpreter with SIGSEGV inside
#: ``backend_compile_and_load`` (jaxlib 0.10.2, CPU); the threads then only run compiled programs.
_COMPILE_LOCK = threading.Lock()


def _compile_once(spec: NetworkSpec, keys, x_fit, r_fit, x_val, r_val) -> None:
    """Compile the programs :func:`_train_axes` runs for one column (init, a chunk of epochs, the summary) in
    this thread, one compilation at a time in the process, before the axes start on threads. A chunk with
    ``stop = 0`` runs no epoch: nothing is trained and no result depends on it."""
    spec = spec.compiled_key()
    with _COMPILE_LOCK:
        s = _init_axes(spec, keys[:1])
        s, running = _train_chunk(spec, s, 0, x_fit, r_fit[:, :1], x_val, r_val[:, :1])
        jax.block_until_ready((running, jax.vmap(_trainer(spec).info)(s), s.best_params))


def _train_parallel(spec: NetworkSpec, keys, x_fit, r_fit, x_val, r_val, *,
                    progress: Callable[[TrainProgress], None] | None = None, threads: int | None = None,
                    pool: Executor | None = None):
    """Every axis trained alone (:func:`_train_axes` on one column), the axes on ``threads`` threads.

    One compiled training of a 4 x 64 network on 16-row batches keeps one core busy; the axes run
    side by side on the cores there are (on the paper's data two threads finish the three axes in
    about the time of the longest). Each axis is the same compiled program with its own key and
    column, so the results are the same for any number of threads or cores, and an axis stops
    computing when it stops (a vmapped loop would compute it, masked, until the last one stops).
    Progress from the axes is merged under a lock. ``pool``: run the axes on this executor instead
    (shared by several trainings at once, e.g. the cross-conformal fold networks, so that they
    share the cores without oversubscribing them).
    """
    n_axes = r_fit.shape[1]
    threads = training_threads() if threads is None else threads
    report = merged_reporter(n_axes, 1, progress) if progress is not None else None   # waiting axes: epoch 0
    r_fit, r_val = np.asarray(r_fit), np.asarray(r_val)
    if n_axes > 1 and (pool is not None or threads > 1):
        _compile_once(spec, keys, x_fit, r_fit, x_val, r_val)

    def run(a):
        return _train_axes(spec, keys[a:a + 1], x_fit, r_fit[:, a:a + 1], x_val, r_val[:, a:a + 1],
                           progress=None if report is None else lambda p: report(a, p))

    if pool is not None:
        parts = [f.result() for f in [pool.submit(run, a) for a in range(n_axes)]]
    elif threads < 2 or n_axes < 2:
        parts = [run(a) for a in range(n_axes)]
    else:
        with ThreadPoolExecutor(min(threads, n_axes), thread_name_prefix="bayesmag-train") as own:
            parts = list(own.map(run, range(n_axes)))
    join = lambda *leaves: np.concatenate([np.asarray(leaf) for leaf in leaves])   # noqa: E731
    params = jax.tree.map(lambda *leaves: jax.device_put(join(*leaves)), *[p for p, _ in parts])   # no program per shape
    info = jax.tree.map(join, *[i for _, i in parts])
    return params, info



class Standardizer(NamedTuple):
    """Affine maps to the network's units: ``(x - x_mean)/x_scale`` and ``(r - r_mean)/r_scale``."""

    x_mean: np.ndarray
    x_scale: np.ndarray
    r_mean: np.ndarray
    r_scale: np.ndarray

    @classmethod
    def fit(cls, x: np.ndarray, r: np.ndarray) -> "Standardizer":
        def sd(a):
            s = np.std(a, axis=0)
            return np.where(s > 0, s, 1.0)
        return cls(np.mean(x, axis=0), sd(x), np.mean(r, axis=0), sd(r))

    def x(self, x: np.ndarray) -> jax.Array:
        return jnp.asarray((np.asarray(x, np.float64) - self.x_mean) / self.x_scale, DTYPE)

    def r(self, r: np.ndarray) -> jax.Array:
        return jnp.asarray((np.asarray(r, np.float64) - self.r_mean) / self.r_scale, DTYPE)



class ResidualNetwork(NamedTuple):
    """Trained per-axis residual networks: ``params`` stacked over axes (leading axis ``n_axes``)."""

    spec: NetworkSpec
    params: Params
    standardizer: Standardizer
    info: TrainInfo
    n_fit: int
    n_val: int
    frequencies: np.ndarray | None = None    # (n_in, fourier_features) fixed Fourier frequencies, or None
    variance_scale: np.ndarray | None = None  # (A,) factor on the MC variances from :func:`recalibrate`, or None
    val_rows: np.ndarray | None = None       # rows of the training inputs held out for early stopping

    def info_dict(self, axes: tuple[str, ...] = ("x", "y", "z")) -> dict:
        """Per-axis ``epochs_run``, ``best_epoch``, ``best_val_loss``, ``nan_epoch`` as plain Python."""
        out = {}
        for a, ax in enumerate(axes):
            out[ax] = {"epochs_run": int(self.info.epochs_run[a]), "best_epoch": int(self.info.best_epoch[a]),
                       "best_val_loss": float(self.info.best_val_loss[a]), "nan_epoch": int(self.info.nan_epoch[a])}
        return out



def validation_rows(n: int, fraction: float, *, seed: int, kind: str = "random",
                    groups: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Seeded ``(fit_rows, val_rows)`` of ``range(n)``; ``ValueError`` if val < ``MIN_VALIDATION_ROWS``.

    ``kind = "random"``: rows drawn at random (the paper). ``kind = "time_blocks"``: one
    contiguous block of ``fraction`` of the rows inside every group of ``groups`` (the run of
    each row, rows in time order), so early stopping and recalibration see rows whose time
    neighbours were not fitted.
    """
    if kind not in VALIDATION_KINDS:
        raise ValueError(f"validation = {kind!r} is not valid; it must be one of "
                          f"{list(VALIDATION_KINDS)}.")
    n_val = int(round(fraction * n))
    if not 0.0 < fraction < 1.0 or n_val < MIN_VALIDATION_ROWS or n - n_val < 1:
        raise ValueError(
            f"validation_fraction = {fraction} leaves {n_val} of {n} training rows for "
            f"validation; early stopping needs at least {MIN_VALIDATION_ROWS} (and some rows left to fit). "
            f"Raise it to at least {math.ceil(MIN_VALIDATION_ROWS / max(n, 1) * 1000) / 1000:g} or use more data.")
    if kind == "time_blocks":
        from bayesmag._src.core.data import split_time_blocks

        groups = np.zeros(n, int) if groups is None else np.asarray(groups)
        if groups.shape != (n,):
            raise ValueError(f"groups must have shape ({n},), got {groups.shape}")
        sp = split_time_blocks(groups, test_fraction=fraction, seed=seed)
        return sp.train, sp.test
    perm = np.random.default_rng(seed).permutation(n)
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])



def check_network_size(spec: NetworkSpec, n_fit: int) -> None:
    """``ValueError`` if the network has more than ``MAX_PARAMS_PER_ROW`` parameters per fitting row."""
    if spec.n_params > MAX_PARAMS_PER_ROW * n_fit:
        raise ValueError(
            f"The residual network ({spec.hidden_layers} hidden layers x {spec.width} units, {spec.n_params} "
            f"parameters per axis) is too large for {n_fit} fitting rows: at most {MAX_PARAMS_PER_ROW} parameters "
            f"per row ({MAX_PARAMS_PER_ROW * n_fit}). Lower 'width' or 'hidden_layers', "
            "or use more data.")
    if spec.batch_size > n_fit:
        raise ValueError(f"batch_size = {spec.batch_size} exceeds the {n_fit} fitting rows.")



def start_residual_network(x: np.ndarray, r: np.ndarray, spec: NetworkSpec, *,
                           validation_fraction: float | None = None, seed: int | None = None,
                           validation: str | None = None, groups: np.ndarray | None = None
                           ) -> Callable[..., ResidualNetwork]:
    """:func:`fit_residual_network` up to the training, on this thread: the checks, the validation rows, the
    standardisation and the compilation of the training programs. Returns ``train(progress=False, pool=None)
    -> ResidualNetwork``, which runs no new compilation and may run on another thread (the hybrid stage trains
    there while the physics stage finishes: :func:`~bayesmag._src.pipeline.prefetch.start_training`)."""
    validation_fraction = spec.validation_fraction if validation_fraction is None else validation_fraction
    seed = spec.seed if seed is None else seed
    validation = spec.validation if validation is None else validation
    x = np.asarray(x, np.float64)
    r = np.asarray(r, np.float64)
    if x.ndim != 2 or x.shape[1] != spec.n_in:
        raise ValueError(f"x must have shape (n, {spec.n_in}), got {x.shape}")
    if r.ndim != 2 or r.shape[0] != x.shape[0]:
        raise ValueError(f"r must have shape ({x.shape[0]}, A), got {r.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(r))):
        raise ValueError("x and r must be finite")
    fit_rows, val_rows = validation_rows(x.shape[0], validation_fraction, seed=seed, kind=validation, groups=groups)
    check_network_size(spec, fit_rows.size)
    st = Standardizer.fit(x[fit_rows], r[fit_rows])
    keys = _axis_keys(seed, r.shape[1])
    freqs = fourier_frequencies(spec, seed) if spec.fourier_features else None
    # residuals as NumPy, as _train_parallel takes them: the programs compiled here are the ones it runs
    arrays = (embed(st.x(x[fit_rows]), freqs), np.asarray(st.r(r[fit_rows])), embed(st.x(x[val_rows]), freqs),
              np.asarray(st.r(r[val_rows])))
    _compile_once(spec, keys, *arrays)

    def train(progress: bool | Callable[[TrainProgress], None] = False, pool: Executor | None = None) -> ResidualNetwork:
        bar = None
        if progress is True:
            progress, bar = progress_bar(spec.max_epochs, r.shape[1],
                                         desc=f"network training ({spec.likelihood}, {r.shape[1]} axes)")
        try:
            params, info = _train_parallel(spec, keys, *arrays, progress=progress or None, pool=pool)
        finally:
            if bar is not None:
                bar.close()
        return ResidualNetwork(spec, params, st, jax.device_get(info), int(fit_rows.size), int(val_rows.size), freqs,
                               None, val_rows)

    return train



def fit_residual_network(x: np.ndarray, r: np.ndarray, spec: NetworkSpec, *,
                         validation_fraction: float | None = None, seed: int | None = None,
                         validation: str | None = None, groups: np.ndarray | None = None,
                         progress: bool | Callable[[TrainProgress], None] = False,
                         pool: Executor | None = None) -> ResidualNetwork:
    """Train one network per column of the residuals ``r`` ``(n, A)`` on inputs ``x`` ``(n, n_in)``.

    A seeded ``validation_fraction`` of the rows is held out for early stopping (chosen as
    :func:`validation_rows` ``kind = validation`` with the rows' run ``groups``); inputs and
    residuals are standardised by the fitting rows' mean and sd. Axis ``a`` uses the key
    ``fold_in(key(seed), a)``, and each column trains alone (:func:`_train_parallel`: one compiled program
    for every axis, the axes on threads; the results do not depend on the thread count), in compiled chunks
    of :data:`TRAIN_CHUNK_EPOCHS` epochs;
    ``progress`` (``True`` for a progress bar, or a callable taking :class:`TrainProgress`)
    hears after every chunk. ``validation_fraction``, ``seed`` and ``validation`` default to
    the spec's. ``pool``: an executor the axes train on, shared with other trainings (see
    :func:`_train_parallel`); the result does not depend on it.
    """
    return start_residual_network(x, r, spec, validation_fraction=validation_fraction, seed=seed,
                                  validation=validation, groups=groups)(progress=progress, pool=pool)
