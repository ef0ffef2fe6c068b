"""The NUTS sampler: many independent problems (axes, simulations) in one compiled program."""

from __future__ import annotations

import collections
import contextlib
import functools
import itertools
import time
import warnings
from typing import Any, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from numpyro.infer.hmc import hmc
from numpyro.infer.util import log_density, potential_energy

from bayesmag._src.core.physics import PhysicsModel
from bayesmag._src.pipeline.nuts.constants import CHAIN_METHODS, INIT_RADIUS, MIN_CHAINS, MIN_DRAWS, NutsWarning
from bayesmag._src.pipeline.nuts.model import NutsProblem, constrain, learned_shape, nuts_model

__all__ = ["NutsDraws", "check_settings", "sample_nuts"]


class NutsDraws(NamedTuple):
    """Raw output of :func:`sample_nuts` for B stacked problems, C chains, D draws (after warm-up).

    ``sites`` are the whitened sample sites, ``theta`` (B, C, D, p), ``sigma`` (B, C, D) and
    ``shape`` (``{field: (B, C, D)}`` for the learned shape fields) their physical values; ``stats`` (B, C, D) hold
    ``diverging``, ``n_steps``, ``acceptance_rate``, ``energy``, ``lp`` and ``step_size``;
    ``warmup_divergences`` (B, C); ``seconds`` the compile and sampling wall times.
    """

    sites: dict
    theta: np.ndarray
    sigma: np.ndarray
    shape: dict
    stats: dict
    warmup_divergences: np.ndarray
    seconds: dict


def check_settings(*, chains: int, warmup: int, draws: int, target_accept: float,
                   chain_method: str = "vectorized") -> list[str]:
    """Validate sampler settings; return warnings for settings too small for trustworthy diagnostics.

    Rule: fewer than :data:`MIN_CHAINS` chains (no between-chain R-hat) or fewer than
    :data:`MIN_DRAWS` draws per chain (R-hat and ESS estimates are themselves noisy) ->
    a warning naming the setting. Impossible settings raise ``ValueError``.

    Example:
      >>> check_settings(chains=1, warmup=100, draws=50, target_accept=0.8)[0][:33]
      'chains = 1: R-hat compares chains'
    """
    for name, v, lo in (("chains", chains, 1), ("draws", draws, 4), ("warmup", warmup, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise ValueError(f"{name} = {v!r} must be an integer >= {lo}.")
    if not 0 < target_accept < 1:
        raise ValueError(f"target_accept = {target_accept!r} must be in (0, 1); 0.8 is the default, "
                         f"0.9-0.99 for difficult posteriors.")
    if chain_method not in CHAIN_METHODS:
        raise ValueError(f"chain_method = {chain_method!r} must be one of {list(CHAIN_METHODS)}.")
    out = []
    if chains < MIN_CHAINS:
        out.append(f"chains = {chains}: R-hat compares chains, so it needs at least {MIN_CHAINS} "
                   f"(4 recommended); convergence is unchecked.")
    if draws < MIN_DRAWS:
        out.append(f"draws = {draws} per chain is too few for reliable R-hat and ESS (need >= {MIN_DRAWS}; "
                   f"1000 recommended).")
    if warmup < MIN_DRAWS:
        out.append(f"warmup = {warmup} is too short for step-size and mass-matrix adaptation "
                   f"(need >= {MIN_DRAWS}; 1000 recommended).")
    return out


class _Progress:
    """Progress bars of the running :func:`sample_nuts` calls, by call id.

    The compiled sampler is shared by calls with the same settings, so it cannot hold a
    bar; it reports ``(call id, iterations)`` through ``jax.debug.callback`` and the call
    that owns the id holds its bar here only while it runs (no global "current bar").
    """

    _bars: dict[int, Any] = {}
    _next = itertools.count(1)

    @classmethod
    @contextlib.contextmanager
    def open(cls, bar):
        token = next(cls._next) % (2**31 - 1)
        cls._bars[token] = bar
        try:
            yield token
        finally:
            cls._bars.pop(token, None)

    @classmethod
    def tick(cls, token, k) -> None:
        bar = cls._bars.get(int(token))
        if bar is not None:
            bar.update(int(k))


def _hashable(x) -> bool:
    try:
        hash(x)
        return True
    except TypeError:
        return False


class _Sampler(NamedTuple):
    model: Any          # the numpyro model with its static options bound
    run: Any            # jitted (z0, keys, problems, token) -> (sites, stats) for vectorized/sequential
    run_chain: Any      # (z0, key, problem, token) -> (sites, stats), single chain (for pmap)
    potential: Any      # jitted (params, problem) -> (pe, grad)


@functools.lru_cache(maxsize=16)
def _make_sampler(physics, family, learned, warmup, total, target_accept, chain_method, max_tree_depth,
                  dense_mass, every) -> _Sampler:
    model = functools.partial(nuts_model, physics=physics, family=family, learned=learned)

    def pe_gen(problem):
        return lambda params: potential_energy(model, (problem,), {}, params)

    init_kernel, sample_kernel = hmc(potential_fn_gen=pe_gen, algo="NUTS")

    def init(z0, key, problem):
        return init_kernel(z0, warmup, target_accept_prob=target_accept, max_tree_depth=max_tree_depth,
                           dense_mass=dense_mass, model_args=(problem,), rng_key=key)

    def step(state, problem):
        return sample_kernel(state, model_args=(problem,))

    def collect(s):
        return s.z, {"diverging": s.diverging, "n_steps": s.num_steps, "acceptance_rate": s.accept_prob,
                     "energy": s.energy, "lp": -s.potential_energy, "step_size": s.adapt_state.step_size}

    def tick(i, token):
        jax.lax.cond((i + 1) % every == 0, lambda: jax.debug.callback(_Progress.tick, token, every), lambda: None)

    def scan_chains(state, problem, stepper, token):
        def body(s, i):
            s = stepper(s, problem)
            tick(i, token)
            return s, collect(s)
        return jax.lax.scan(body, state, jnp.arange(total))[1]

    def run_chain(z0, key, problem, token):
        return scan_chains(init(z0, key, problem), problem, step, token)

    def run_problem(args, token):
        z0, keys, problem = args
        if chain_method == "vectorized":
            state = jax.vmap(init, in_axes=(0, 0, None))(z0, keys, problem)
            out = scan_chains(state, problem, jax.vmap(step, in_axes=(0, None)), token)
            return jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), out)     # (C, T, ...)
        return jax.lax.map(lambda a: run_chain(a[0], a[1], problem, token), (z0, keys))

    run = jax.jit(lambda z0, keys, problems, token: jax.lax.map(lambda a: run_problem(a, token),
                                                                  (z0, keys, problems)))
    potential = jax.jit(jax.vmap(jax.vmap(jax.value_and_grad(lambda params, pr: pe_gen(pr)(params)),
                                          in_axes=(0, None)), in_axes=(0, 0)))
    return _Sampler(model=model, run=run, run_chain=run_chain, potential=potential)


#: Compiled samplers by (sampler, argument signature), least recently used dropped after 16.
_COMPILED: collections.OrderedDict = collections.OrderedDict()


def _compile(sampler: _Sampler, *args):
    """``sampler.run`` compiled for ``args``' shapes, reused by later calls with the same ones."""
    key = (sampler, repr(jax.tree.map(lambda x: (x.shape, str(x.dtype)), args)))
    if key in _COMPILED:
        _COMPILED.move_to_end(key)
        return _COMPILED[key]
    compiled = _COMPILED[key] = sampler.run.lower(*args).compile()
    if len(_COMPILED) > 16:
        _COMPILED.popitem(last=False)
    return compiled


def _stack(problems: Sequence[NutsProblem]) -> NutsProblem:
    shapes = {jax.tree.map(jnp.shape, p).__repr__() for p in problems}
    if len(shapes) != 1:
        raise ValueError("sample_nuts: all problems must have the same shapes (rows and parameters) to be batched.")
    return jax.tree.map(lambda *x: jnp.stack(x), *problems)


def _site_shapes(p: int, learned: Sequence[str]) -> dict:
    out = {"z": (p,), "u": ()}
    for f in learned:
        out["v_" + f] = ()
    return out


def _init_points(problems: NutsProblem, sampler, B: int, C: int, p: int, learned: Sequence[str], seed: int,
                 axis_names: Sequence[str]) -> dict:
    """Overdispersed, finite initial points; a clear error if the LM estimate itself is not finite."""
    shapes = _site_shapes(p, learned)
    zero = {k: jnp.zeros((B, 1) + s) for k, s in shapes.items()}
    pe0, g0 = sampler.potential(zero, problems)
    pe0 = np.asarray(pe0)[:, 0]
    g_ok = np.asarray(jnp.all(jnp.stack([jnp.all(jnp.isfinite(v), axis=tuple(range(2, v.ndim)))
                                         for v in jax.tree.leaves(g0)]), axis=0))[:, 0]
    for b in range(B):
        if not (np.isfinite(pe0[b]) and g_ok[b]):
            pr = jax.tree.map(lambda x: x[b], problems)
            raise ValueError(_nonfinite_message(pr, sampler.model, axis_names[b], learned, p))
    rng = np.random.default_rng(seed)
    z0 = {k: rng.uniform(-INIT_RADIUS, INIT_RADIUS, (B, C) + s) for k, s in shapes.items()}
    for _ in range(6):
        pe, g = sampler.potential(jax.tree.map(jnp.asarray, z0), problems)
        ok = np.isfinite(np.asarray(pe))
        for v in jax.tree.leaves(g):
            ok &= np.asarray(jnp.all(jnp.isfinite(v), axis=tuple(range(2, v.ndim))))
        if ok.all():
            break
        for k in z0:
            z0[k][~ok] *= 0.5
    else:
        for k in z0:
            z0[k][~ok] = 0.0
    return jax.tree.map(jnp.asarray, z0)


def _nonfinite_message(problem: NutsProblem, model_fn, axis_name: str, learned: Sequence[str], p: int) -> str:
    """Which term of the log-density is not finite at the LM estimate (z = u = 0)."""
    params = {k: jnp.zeros(s) for k, s in _site_shapes(p, learned).items()}
    bad = []
    try:
        _, tr = log_density(model_fn, (problem,), {}, params)
        for name, site in tr.items():
            if site["type"] == "deterministic" and not np.all(np.isfinite(np.asarray(site["value"]))):
                bad.append(f"'{name}' = {np.asarray(site['value'])}")
            elif site["type"] == "sample":
                lp = np.asarray(site["fn"].log_prob(site["value"]))
                if not np.all(np.isfinite(lp)):
                    bad.append(f"the likelihood '{name}' ({int(np.sum(~np.isfinite(lp)))} non-finite row(s))"
                               if site.get("is_observed") else f"the prior term '{name}'")
    except Exception as e:  # pragma: no cover - the message is the product here
        bad.append(f"evaluating the model ({type(e).__name__}: {e})")
    what = "; ".join(bad) if bad else "the gradient of the log-density"
    return (f"NUTS: the log-density is not finite at the initial point (the LM estimate) on axis {axis_name}: "
            f"{what} is not finite. Check that the fit converged with finite parameters, that the training rows "
            f"have no non-finite values, and that the priors are positive and finite.")


def sample_nuts(problems: Sequence[NutsProblem], physics: PhysicsModel, *, likelihood: str = "gaussian",
                learned: Sequence[str] | bool = (), chains: int = 4, warmup: int = 1000, draws: int = 1000,
                target_accept: float = 0.8, chain_method: str = "vectorized", seed: int = 0, progress: bool = False,
                max_tree_depth: int = 10, dense_mass: bool = False, names: Sequence[str] | None = None) -> NutsDraws:
    """Run NUTS on independent problems (axes, or repeated simulations) in one compiled program.

    The problems are mapped over sequentially inside one ``jit`` and their chains are
    vectorised (``jax.vmap``, the default), mapped (``"sequential"``) or spread over devices
    (``"parallel"``, ``jax.pmap``; needs ``numpyro.set_host_device_count(chains)`` before
    JAX starts, else it falls back to sequential with a warning). Each problem adapts its own
    step size and diagonal mass matrix. Compiled programs are cached per model, settings
    and shapes, so repeated calls compile once. ``learned`` names the family shape fields
    to sample (``True``: all with a prior); the others stay at the problems' ``shape`` values.

    Args:
      problems: :class:`NutsProblem` s of equal shapes (see :func:`build_problem`).
      physics: the model whose ``predict`` the problems were built for.
      names: labels for error messages (default the axis names or problem indices).
    Returns:
      :class:`NutsDraws`.
    """
    for w in check_settings(chains=chains, warmup=warmup, draws=draws, target_accept=target_accept,
                            chain_method=chain_method):
        warnings.warn(w, NutsWarning, stacklevel=2)
    learned = learned_shape(likelihood, learned)
    problems = list(problems)
    B, p = len(problems), int(problems[0].theta_hat.shape[-1])
    names = list(names) if names is not None else [str(i) for i in range(B)]
    stacked = _stack(problems)
    method = chain_method
    if method == "parallel" and (chains < 2 or jax.local_device_count() < chains):
        if chains >= 2:
            warnings.warn(f"chain_method = \"parallel\" needs {chains} devices but JAX sees "
                          f"{jax.local_device_count()}; call numpyro.set_host_device_count({chains}) before JAX "
                          f"starts to run chains on separate CPU cores. Running the chains sequentially instead.",
                          NutsWarning, stacklevel=2)
        method = "sequential"
    total = warmup + draws
    every = max(1, total // 50)
    key = (physics, likelihood, learned, int(warmup), int(total), float(target_accept), method,
           int(max_tree_depth), bool(dense_mass), every)
    sampler = _make_sampler(*key) if _hashable(key) else _make_sampler.__wrapped__(*key)

    z0 = _init_points(stacked, sampler, B, chains, p, learned, seed, names)
    keys = jax.random.split(jax.random.PRNGKey(seed), B * chains).reshape(B, chains, -1)

    from tqdm.auto import tqdm
    n_ticks = B * total * (chains if method != "vectorized" else 1)
    bar = tqdm(total=n_ticks - n_ticks % every if every > 1 else n_ticks, desc=f"NUTS {B}x{chains} chains",
               unit="it", disable=not progress, leave=False)
    seconds = {}
    with _Progress.open(bar) as token_id:
        token = jnp.asarray(token_id, jnp.int32)
        t = time.perf_counter()
        if method == "parallel":
            pm = jax.pmap(sampler.run_chain, in_axes=(0, 0, None, None))
            outs = [pm(jax.tree.map(lambda x: x[b], z0), keys[b], jax.tree.map(lambda x: x[b], stacked), token)
                    for b in range(B)]
            sites, stats = jax.tree.map(lambda *x: jnp.stack(x), *outs)
            jax.block_until_ready(stats)
            seconds["compile"] = 0.0                       # pmap compiles on the first call: inside "sampling"
            seconds["sampling"] = time.perf_counter() - t
        else:
            compiled = _compile(sampler, z0, keys, stacked, token)
            seconds["compile"] = time.perf_counter() - t
            t = time.perf_counter()
            sites, stats = compiled(z0, keys, stacked, token)
            jax.block_until_ready(stats)
            seconds["sampling"] = time.perf_counter() - t
    bar.close()

    sites = {k: np.asarray(v) for k, v in sites.items()}
    stats = {k: np.asarray(v) for k, v in stats.items()}
    warm_div = stats["diverging"][:, :, :warmup].sum(axis=-1)
    sites = {k: v[:, :, warmup:] for k, v in sites.items()}
    stats = {k: v[:, :, warmup:] for k, v in stats.items()}
    stats["tree_depth"] = np.ceil(np.log2(stats["n_steps"] + 1.0)).astype(np.int64)
    constrained = jax.jit(jax.vmap(lambda s, pr: jax.vmap(jax.vmap(lambda q: constrain(pr, q, learned)))(s)))(
        jax.tree.map(jnp.asarray, sites), stacked)
    return NutsDraws(
        sites=sites, theta=np.asarray(constrained["theta"]), sigma=np.asarray(constrained["sigma"]),
        shape={f: np.asarray(constrained[f]) for f in learned}, stats=stats, warmup_divergences=warm_div,
        seconds=seconds,
    )

