"""Shared fixtures: CPU only, float64 (bayesmag enables it), the real data when available."""

import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# The persistent compilation cache stays off in the tests whatever the caller's environment
# (a cache read crashed CI with SIGSEGV; tests of the cache itself run in subprocesses).
os.environ["BAYESMAG_COMPILE_CACHE"] = "0"

import bayesmag  # noqa: E402,F401  (enables float64)


def _test_compile_cache():
    """JAX's persistent cache in a fresh folder per test process, so a program compiled by one test is read back
    by the next instead of compiled again (the library's jitted closures are built per call, so JAX's in-memory
    caches miss where the HLO is the same). One folder per xdist worker: JAX writes entries without a lock, and a
    reader in another process could see half a file. ``BAYESMAG_TEST_JAX_CACHE=0`` turns it off. The library's
    own setting (``BAYESMAG_COMPILE_CACHE``) stays off: the tests of it run in subprocesses."""
    from bayesmag._src.core.cache import _OFF       # the library's spelling of "off"

    if os.environ.get("BAYESMAG_TEST_JAX_CACHE", "1").strip().lower() in _OFF:
        return None
    import atexit
    import shutil
    import tempfile

    import jax
    path = tempfile.mkdtemp(prefix=f"bayesmag-test-jax-{os.environ.get('PYTEST_XDIST_WORKER', 'main')}-")
    atexit.register(shutil.rmtree, path, ignore_errors=True)
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


TEST_COMPILE_CACHE = _test_compile_cache()

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def _belsten_path():
    d = os.environ.get("BAYESMAG_DATA_DIR")
    if d and (Path(d) / "belsten2023" / "full_data.csv").exists():
        return Path(d) / "belsten2023" / "full_data.csv"
    local = Path(__file__).resolve().parents[2] / "shared" / "data" / "belsten2023" / "full_data.csv"
    if local.exists():
        os.environ.setdefault("BAYESMAG_DATA_DIR", str(local.parent.parent))
        return local
    return None


@pytest.fixture(scope="session")
def belsten():
    """The Belsten (2023) recordings; in CI their absence is a failure, never a skip."""
    p = _belsten_path()
    if p is None:
        if IN_CI:
            pytest.fail("BAYESMAG_DATA_DIR must point at ../shared/data in CI: the real-data tests may not be skipped.")
        pytest.skip("Belsten data not found (set BAYESMAG_DATA_DIR)")
    from bayesmag import load_belsten
    return load_belsten(p)


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after every test module.

    Every XLA:CPU executable maps its code into the process, and JAX keeps them in its caches: one
    process running the whole suite compiled enough programs to pass the kernel's limit of memory
    mappings (``vm.max_map_count``, 65530), after which the next compilation crashed with SIGSEGV
    (inside ``backend_compile_and_load``). Clearing the caches between modules keeps the count
    bounded; the modules only recompile what they use. Where the count can be read (Linux: ``/proc/self/maps``), the
    caches are dropped only once it passes :data:`MAP_LIMIT` (a third of the kernel's limit; one module adds a few
    thousand at most), so the modules after one reuse its compiled programs (the LM fit, the PS-QMC, ...) instead of
    compiling them again.
    """
    yield
    import gc

    import jax
    n = _mappings()
    if n is None or n > MAP_LIMIT:
        jax.clear_caches()
        gc.collect()


#: Memory mappings of the process above which the compiled programs are dropped after a module (kernel limit 65530).
MAP_LIMIT = 20000


def _mappings():
    """The number of memory mappings of this process, or None where /proc/self/maps cannot be read."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return None


def pytest_runtest_logreport(report):
    """With ``BAYESMAG_TEST_TIMES=FILE``: append each test's phase durations to FILE as it ends (``nodeid phase
    seconds``), so a run cut short (a CI time limit) still tells which tests are slow; ``--durations`` prints only
    at the end of a completed run."""
    path = os.environ.get("BAYESMAG_TEST_TIMES")
    if path:
        with open(path, "a") as f:
            f.write(f"{report.nodeid} {report.when} {report.duration:.3f} {report.outcome}\n")
