"""Batched LAPACK calls on the CPU lowered one matrix at a time, so that jaxlib 0.10.x / 0.11.0 cannot deadlock.

Those jaxlib releases split a batched LAPACK call (a vmapped Cholesky, triangular solve, LU, ...) into pieces over
JAX's CPU thread pool, and the pool thread that made the call blocks until the pieces finish. When as many such
calls run at once as the pool has threads (two independent vmapped solves in one program on a 2-core machine), every
pool thread waits for pieces no thread is left to run, and the process hangs for good (CI hung for 90 minutes in
``tests/test_hierarchical.py``; gdb: every pool thread in ``jax::ParallelBatchMap`` < ``lapack_dtrsm_ffi``,
``BlockingCounter::Wait``). A call on one matrix has nothing to split.

:func:`install` replaces the CPU lowering of every ``jax.lax.linalg`` primitive that has one with a rule that lowers
a batched call as ``lax.map`` over the matrices, each an unbatched call of the original rule (an unbatched call
keeps the original rule as it is). LAPACK computes every matrix of a batched call by the same routine on the same
numbers, so each call's result is bit-identical (``tests/test_lapack_guard.py``); a whole program can differ in the
last bits where XLA lays out the code around the loop differently (about 1e-13 relative in the hierarchical
transfer). The price is a loop step per matrix (a few microseconds). It applies to programs compiled after it,
bayesmag's and the caller's; the pool keeps its threads. ``import bayesmag`` installs it for the affected jaxlib
releases, and falls back to a one-thread pool if JAX's internals it uses are not there (``bayesmag/__init__.py``;
docs/architecture.md, "Global state").
"""

from __future__ import annotations

import math

__all__ = ["install", "installed"]

#: Rank of the first operand's core (matrix) part, where it is not 2 (the diagonals of a tridiagonal solve).
_FIRST_CORE_RANK = {"tridiagonal_solve": 1}

_INSTALLED: list[str] = []


def _one_matrix_at_a_time(prim, original, core_rank: int):
    """A lowering rule for ``prim``: ``original`` for one matrix, ``lax.map`` of ``original`` over a batch."""
    from jax import lax
    from jax._src.interpreters import mlir

    def rule(ctx, *args, **params):
        nb = len(ctx.avals_in[0].shape) - core_rank
        batch = tuple(ctx.avals_in[0].shape[:nb])
        if nb <= 0 or not all(isinstance(d, int) for d in batch) or math.prod(batch) <= 1:
            return original(ctx, *args, **params)          # one matrix, or symbolic batch sizes (jax.export)
        size = math.prod(batch)

        def mapped(*xs, **_):
            flat = tuple(x.reshape((size,) + x.shape[nb:]) for x in xs)
            outs = lax.map(lambda ops: prim.bind(*ops, **params), flat)
            if prim.multiple_results:
                return [o.reshape(batch + o.shape[1:]) for o in outs]
            return outs.reshape(batch + outs.shape[1:])

        return mlir.lower_fun(mapped, multiple_results=prim.multiple_results)(ctx, *args, **params)

    return rule


def install() -> list[str]:
    """Lower batched CPU LAPACK calls one matrix at a time (idempotent); the names of the primitives it covers."""
    if _INSTALLED:
        return list(_INSTALLED)
    from jax._src.interpreters import mlir
    from jax._src.lax import linalg

    cpu = mlir._platform_specific_lowerings["cpu"]
    for name in sorted(dir(linalg)):
        prim = getattr(linalg, name)
        entry = cpu.get(prim) if name.endswith("_p") else None
        if entry is None:
            continue
        mlir.register_lowering(prim, _one_matrix_at_a_time(prim, entry.rule, _FIRST_CORE_RANK.get(prim.name, 2)),
                               platform="cpu", inline=entry.inline)
        _INSTALLED.append(prim.name)
    return list(_INSTALLED)


def installed() -> list[str]:
    """The primitives whose batched CPU calls are lowered one matrix at a time (empty before :func:`install`)."""
    return list(_INSTALLED)
