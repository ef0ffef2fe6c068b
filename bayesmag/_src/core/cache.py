"""Cold start: JAX's persistent compilation cache in the user cache folder.

Most of a job's first-run time is XLA compilation. With the cache on, a second run of the same
job (same shapes, same jax/jaxlib, same device) loads the compiled executables from disk
instead. The **command line** switches it on (``bayesmag run``, ``apply``, ``discover``, ...);
**from Python** it stays as the caller left it (off unless asked). Its history: reading entries
back crashed the interpreter (SIGSEGV inside
``jax._src.compilation_cache.get_executable_and_time``, jax/jaxlib 0.10.2 on CPU) in our CI, so
it was made opt-in. The crash was then traced to the test process passing the kernel's limit of
memory mappings (``vm.max_map_count``: every compiled executable maps its code; guarded now by
:func:`release_compiled_if_crowded`), not to the cache, and every packaged vector and field job
ran twice against one fresh cache folder (cold, then reading every entry back) with exit status
0 and identical ``metrics.json`` (``python benchmarks/cache_stress.py``).
Per job: ``[output] compile_cache = true | false`` (``"auto"``, the default, keeps the process's
setting); for every job and every import: the environment variable ``BAYESMAG_COMPILE_CACHE=1``
(``=/some/dir`` another folder, ``=0`` off, also for the command line).
The folder is ``$XDG_CACHE_HOME/bayesmag/jax`` (``~/.cache/bayesmag/jax``) on Linux,
``~/Library/Caches/bayesmag/jax`` on macOS and ``%LOCALAPPDATA%\\bayesmag\\jax`` on Windows.

The setting must be made before the first compilation of the process: JAX opens the cache once.
It is made on first use, not at import (:func:`ensure_compile_cache`: the first public name taken
from ``bayesmag``, the command line, :func:`~bayesmag.calibrate`, :func:`~bayesmag.run_job`), so
``import bayesmag`` alone leaves the process's JAX settings alone; a call of
:func:`configure_compile_cache` before that first use wins.
"""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

__all__ = ["ENV_VAR", "default_cache_dir", "cache_dir_from_env", "configure_compile_cache", "compile_cache_off",
           "compile_cache", "ensure_compile_cache", "release_compiled_if_crowded"]

ENV_VAR = "BAYESMAG_COMPILE_CACHE"
_OFF = ("0", "off", "false", "no")


def default_cache_dir() -> Path:
    """The per-user cache folder for compiled code (platform convention, see the module docstring)."""
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "bayesmag" / "jax"


def cache_dir_from_env(environ: dict | None = None) -> Path | None:
    """The cache folder ``BAYESMAG_COMPILE_CACHE`` asks for: None when unset, empty or off."""
    value = (os.environ if environ is None else environ).get(ENV_VAR, "").strip()
    if value.lower() in _OFF or not value:
        return None
    if value.lower() in ("1", "on", "true", "yes"):
        return default_cache_dir()
    return Path(value).expanduser()


def _env_setting() -> str:
    value = os.environ.get(ENV_VAR, "").strip().lower()
    return "" if not value else ("off" if value in _OFF else "on")


def configure_compile_cache(enabled: bool = True, directory: str | Path | None = None) -> Path | None:
    """Switch JAX's persistent compilation cache on (in ``directory`` or the default) or off.

    A set environment variable wins over ``enabled`` both ways (``BAYESMAG_COMPILE_CACHE=0`` keeps
    it off for every job, ``=1`` or a folder keeps it on). Returns the folder in use, or None when
    off. Every compiled executable is cached, however quick it was to compile: a job compiles many
    small ones.
    """
    import jax

    global _configured
    _configured = True
    env = _env_setting()
    path = None
    if env == "on" or (enabled and env == ""):
        path = Path(directory).expanduser() if directory is not None else (cache_dir_from_env() or default_cache_dir())
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError:                     # read-only home etc.: run without the cache, never fail a job
            path = None
    if path is None:
        jax.config.update("jax_compilation_cache_dir", None)
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


_configured = False


def ensure_compile_cache(default: bool = False) -> None:
    """Switch the cache on at first use when ``BAYESMAG_COMPILE_CACHE`` asks for it, or when it is unset
    and ``default`` (the command line), once per process and unless it was configured already; otherwise
    the process's JAX settings are left alone (the library's first use)."""
    env = _env_setting()
    if not _configured and (env == "on" or (default and env == "")):
        configure_compile_cache()


_CACHE_KEYS = ("jax_enable_compilation_cache", "jax_compilation_cache_dir")


@contextlib.contextmanager
def compile_cache(enabled: bool):
    """The persistent compilation cache on or off inside the block (the environment variable still
    wins), the process's setting restored after: a job run from Python leaves the caller's alone."""
    import jax

    before = {k: jax.config.values[k] for k in _CACHE_KEYS}
    configure_compile_cache(enabled)
    try:
        yield
    finally:
        for k, v in before.items():
            jax.config.update(k, v)


def compile_cache_off():
    """The persistent compilation cache off inside the block (see :func:`compile_cache`)."""
    return compile_cache(False)


def _map_counts() -> tuple[int, int] | None:
    """(memory mappings this process holds, the kernel's limit ``vm.max_map_count``), or None off Linux."""
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f), limit
    except (OSError, ValueError):
        return None


def release_compiled_if_crowded(fraction: float = 0.5) -> bool:
    """Drop JAX's in-memory compiled programs when this process holds over ``fraction`` of the kernel's
    limit of memory mappings; returns whether it did.

    Every XLA:CPU executable maps its code into the process and JAX keeps them cached, so a long-lived
    process that compiles many distinct programs (many jobs of different shapes in one notebook)
    passes ``vm.max_map_count`` (65530 by default on Linux) and the next compilation crashes with
    SIGSEGV (measured in this project's test process: 13.7k mappings after 8 of 35 test modules).
    Called at the start of every job and :func:`~bayesmag.calibrate`; the cost when it acts is
    recompiling what the next job needs. Off Linux it does nothing.
    """
    counts = _map_counts()
    if counts is None or counts[0] < fraction * counts[1]:
        return False
    import gc

    import jax

    jax.clear_caches()
    gc.collect()
    return True
