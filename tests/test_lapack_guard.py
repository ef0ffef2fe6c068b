"""Batched LAPACK on the CPU lowered one matrix at a time (bayesmag/_src/core/lapack_guard.py), installed by
``import bayesmag`` where jaxlib splits a batched call over its thread pool and can deadlock (0.10.x, 0.11.0): the
hang reproduced without it, gone with it, bit-identical results, and the ``BAYESMAG_CPU_THREADS`` choices."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

import bayesmag

SPLITS = bayesmag._lapack_pool_deadlocks()
CORES = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()

# Four independent vmapped solves in one program, each large enough for jaxlib 0.10.2 to split its batch over the
# CPU thread pool: with two pool threads both block waiting for pieces nobody runs (hung 4 of 4 times on the 2-core
# CI machine with JAX's own thread settings; a Cholesky and an LU solve in place of the triangular solve hang too).
_DEADLOCK = """
import sys
import jax, jax.numpy as jnp
{before}
import bayesmag
from jax.scipy.linalg import solve_triangular
op = sys.argv[1]
def one(a, c):
    if op == "triangular_solve":
        return solve_triangular(a, c, lower=True)
    if op == "cholesky":
        return jnp.linalg.cholesky(a @ a.T + 8 * jnp.eye(8))[:, :3] * c
    return jnp.linalg.solve(a + 8 * jnp.eye(8), c)
def g(A, b):
    return sum(jax.vmap(one)(jnp.tanh(A * (k + 1)) + 5 * jnp.eye(8), b * k).sum() for k in range(4))
f = jax.jit(g)
A, b = jnp.tril(jnp.ones((4000, 8, 8))), jnp.ones((4000, 8, 3))
for i in range(int(sys.argv[2])):
    f(A + i, b).block_until_ready()
print(bayesmag.LAPACK_GUARD_AT_IMPORT, bayesmag.CPU_POOL_AT_IMPORT)
"""


def _env(setting: str) -> dict:
    """This process's environment with ``BAYESMAG_CPU_THREADS = setting``, CPU only, no pool size of its own."""
    env = {**os.environ, "BAYESMAG_CPU_THREADS": setting, "JAX_PLATFORMS": "cpu"}
    env.pop("PJRT_NPROC", None)
    env.pop("NPROC", None)
    return env


def _run(setting: str, op: str = "triangular_solve", runs: int = 300, *, before: str = "", timeout: float = 240,
         code: str | None = None):
    code = _DEADLOCK.format(before=before) if code is None else code
    return subprocess.run([sys.executable, "-c", code, op, str(runs)], env=_env(setting),
                          capture_output=True, text=True, timeout=timeout)


# The triangular solve in the default run (the call CI hung on); the Cholesky and LU programs (about 15-30 s each on
# 2 cores) are the same guard, whose lowering of every op is checked by test_a_batched_call_is_a_loop... below.
@pytest.mark.parametrize("op", ["triangular_solve", pytest.param("cholesky", marks=pytest.mark.slow),
                                pytest.param("lu_solve", marks=pytest.mark.slow)])
@pytest.mark.extended
def test_concurrent_batched_lapack_finishes_after_import(op):
    """The default (BAYESMAG_CPU_THREADS unset): JAX keeps its thread pool, batched calls are lowered one matrix at
    a time; the program of four concurrent batched solves runs 300 times (about 4-9 s)."""
    out = _run("", op)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == [str(SPLITS), "False"]


def test_one_pool_thread_is_still_a_choice():
    """BAYESMAG_CPU_THREADS=one: the fix before the guard (JAX's pool sized to one thread), no guard."""
    out = _run("one")
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["False", str(SPLITS)]


@pytest.mark.slow
@pytest.mark.skipif(CORES != 2 or not SPLITS, reason="the hang is checked on 2-core machines with a jaxlib that "
                                                      "splits LAPACK batches")
def test_without_the_guard_the_same_program_hangs():
    """BAYESMAG_CPU_THREADS=default (JAX as it is): the same program hangs on this 2-core machine, so the tests above
    can fail. Slow (it waits out its 20 s timeout by design): it checks the machine, not bayesmag; run with -m slow."""
    with pytest.raises(subprocess.TimeoutExpired):
        _run("default", timeout=20)


@pytest.mark.extended
def test_guard_is_installed_after_jax_already_ran():
    """JAX computed before `import bayesmag`: the guard still covers what is compiled after (no warning); with
    BAYESMAG_CPU_THREADS=one it is too late to size the pool, and bayesmag says so."""
    out = _run("", before="jnp.ones(2).sum().block_until_ready()")
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == [str(SPLITS), "False"] and "RuntimeWarning" not in out.stderr
    out = _run("one", runs=0, before="jnp.ones(2).sum().block_until_ready()")
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["False", "False"]
    assert ("RuntimeWarning" in out.stderr) == SPLITS


_OPS = """
import sys, numpy as np
import bayesmag, jax, jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax.lax import linalg as ll
rng = np.random.default_rng(0)
A = jnp.asarray(rng.normal(size=(2, 5, 6, 6)))
S = A @ jnp.swapaxes(A, -1, -2) + 6 * jnp.eye(6)
B = jnp.asarray(rng.normal(size=(2, 5, 6, 3)))
d = jnp.asarray(rng.normal(size=(2, 5, 6))) + 4
ops = {
 "cholesky": lambda: jnp.linalg.cholesky(S),
 "triangular_solve": lambda: jsl.solve_triangular(jnp.linalg.cholesky(S), B, lower=True),
 "lu_solve": lambda: jnp.linalg.solve(A + 6 * jnp.eye(6), B),
 "slogdet": lambda: jnp.linalg.slogdet(A)[1],
 "qr": lambda: jnp.concatenate(jnp.linalg.qr(A), -1),
 "qr_pivoting": lambda: jsl.qr(A, pivoting=True)[1],
 "eigh": lambda: jnp.concatenate([jnp.linalg.eigh(S)[0][..., None], jnp.linalg.eigh(S)[1]], -1),
 "svd": lambda: jnp.concatenate([jnp.linalg.svd(A)[0], jnp.linalg.svd(A)[1][..., None]], -1),
 "eig": lambda: jnp.abs(jnp.linalg.eigvals(A)),
 "schur": lambda: jsl.schur(A)[0],
 "tridiagonal": lambda: ll.tridiagonal(S)[1],
 "tridiagonal_solve": lambda: ll.tridiagonal_solve(d * 0.1, d, d * 0.2, B),
}
np.savez(sys.argv[1], **{k: np.asarray(jax.jit(f)()) for k, f in ops.items()},
         S=np.asarray(S), A=np.asarray(A), B=np.asarray(B))
print(bayesmag.LAPACK_GUARD_AT_IMPORT)
"""


def test_guarded_results_are_bit_identical_to_batched_lapack(tmp_path):
    """Every kind of batched CPU LAPACK call, (2, 5) matrices: with the guard (one matrix at a time) the same bits as
    jaxlib's batched kernel (BAYESMAG_CPU_THREADS=one: no guard), and equal to NumPy's per-matrix results within
    1e-12 where NumPy has the routine."""
    res = {}
    for setting in ("", "one"):
        out = subprocess.run([sys.executable, "-c", _OPS, str(tmp_path / f"r{setting}.npz")], env=_env(setting),
                             capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        assert out.stdout.split() == [str(SPLITS and setting == "")]
        res[setting] = np.load(tmp_path / f"r{setting}.npz")
    g, b = res[""], res["one"]
    for k in g.files:
        np.testing.assert_array_equal(g[k], b[k], err_msg=k)
    S, A, B = g["S"], g["A"], g["B"]
    np.testing.assert_allclose(g["cholesky"], np.linalg.cholesky(S), atol=1e-12)
    np.testing.assert_allclose(g["lu_solve"], np.linalg.solve(A + 6 * np.eye(6), B), atol=1e-12)
    np.testing.assert_allclose(g["eigh"][..., 0], np.linalg.eigvalsh(S), atol=1e-12)
    np.testing.assert_allclose(g["svd"][..., -1], np.linalg.svd(A, compute_uv=False), atol=1e-12)
    np.testing.assert_allclose(g["slogdet"], np.linalg.slogdet(A)[1], atol=1e-12)


@pytest.mark.skipif(not bayesmag.LAPACK_GUARD_AT_IMPORT, reason="the guard is installed for jaxlibs that split")
@pytest.mark.parametrize("jit", [True, False])
def test_a_batched_call_is_a_loop_and_a_single_matrix_is_not(jit):
    """The lowering: a batched Cholesky becomes a while loop of one-matrix calls; one matrix keeps jaxlib's rule."""
    import jax
    import jax.numpy as jnp
    from bayesmag._src.core import lapack_guard

    assert {"cholesky", "triangular_solve", "lu", "eigh", "svd", "geqrf"} <= set(lapack_guard.installed())
    batched = jax.jit(jnp.linalg.cholesky).lower(jnp.eye(3)[None].repeat(4, 0)).as_text()
    single = jax.jit(jnp.linalg.cholesky).lower(jnp.eye(3)).as_text()
    assert "stablehlo.while" in batched and "stablehlo.while" not in single
    f = jax.jit(jnp.linalg.cholesky) if jit else jnp.linalg.cholesky
    m = np.array([[4.0, 2.0], [2.0, 3.0]])
    got = np.asarray(f(jnp.asarray(np.stack([m, 2 * m, 3 * m]))))
    np.testing.assert_allclose(got, np.linalg.cholesky(np.stack([m, 2 * m, 3 * m])), atol=1e-14)


def test_without_the_jax_internals_it_falls_back_to_one_pool_thread():
    """If JAX's lowering registry cannot be patched (its internals moved), `import bayesmag` falls back to the
    one-thread pool (before JAX's client exists): the concurrent batched solves still finish."""
    if not SPLITS:
        pytest.skip("the guard is installed for jaxlibs that split LAPACK batches")
    before = ("from jax._src.interpreters import mlir\n"
              "_real = mlir.register_lowering\n"
              "def _moved(*a, **k): raise AttributeError('moved')\n"
              "mlir.register_lowering = _moved")
    code = _DEADLOCK.format(before=before).replace("import bayesmag\n", "import bayesmag\nmlir.register_lowering = _real\n", 1)
    out = _run("", runs=100, code=code)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["False", "True"]


def test_symbolic_batch_sizes_keep_jaxlibs_rule():
    """A shape-polymorphic export (`jax.export`, batch size symbolic) lowers and runs: a symbolic batch keeps
    jaxlib's own rule (no loop of unknown length)."""
    import jax
    import jax.numpy as jnp
    from jax import export

    exp = export.export(jax.jit(jnp.linalg.cholesky))(
        jax.ShapeDtypeStruct(export.symbolic_shape("b, 3, 3"), jnp.float64))
    m = np.array([[4.0, 2.0, 0.0], [2.0, 3.0, 0.5], [0.0, 0.5, 2.0]])
    got = np.asarray(exp.call(jnp.asarray(np.stack([m, 2 * m]))))
    np.testing.assert_allclose(got, np.linalg.cholesky(np.stack([m, 2 * m])), atol=1e-14)
