"""bayesmag: calibrate 3-axis magnetometers against a reference, with trustworthy uncertainty.

The public API is re-exported here explicitly; the implementation lives in ``bayesmag._src``.
Submodules ``bayesmag.likelihoods``, ``bayesmag.metrics`` and ``bayesmag.simulate`` are public too.

Names are imported on first use (PEP 562), so ``import bayesmag`` and the command line start
without loading NumPyro, ArviZ or the discovery machinery a job may not need.

.. warning:: **float64.** ``import bayesmag`` switches JAX to 64-bit floats for the whole
   process (``jax_enable_x64``), because the physics fit, its uncertainty and NUTS are
   float64 computations (the residual network casts to float32 itself). To keep your own
   JAX code in float32, set the environment variable ``BAYESMAG_ENABLE_X64=0`` before the
   import: your JAX state is then left alone, and you scope float64 to bayesmag calls with
   ``with bayesmag.enable_x64(): ...``. Run without float64, the entry points
   (``fit_physics``, ``physics_uncertainty``, ``run_nuts``, ``run_job``, ...) warn with
   :class:`Float64Warning`: they compute, but in float32 (docs/architecture.md shows what
   that changes).
"""

import functools as _functools
import importlib as _importlib
import os as _os
import sys as _sys
import warnings as _warnings


def _started_as_command() -> bool:
    """Whether this process is the ``bayesmag`` command (console script or ``python -m bayesmag...``)."""
    argv = list(getattr(_sys, "orig_argv", []))
    if "-m" in argv[:-1] and argv[argv.index("-m") + 1].split(".")[0] == "bayesmag":
        return True
    return _os.path.basename(_sys.argv[0]).lower() in ("bayesmag", "bayesmag.exe", "bayesmag-script.py")


# The command's linear algebra is on small matrices (LM normal equations, (n, 24) Jacobians), where
# OpenBLAS's threads only contend with each other and with JAX: one (3040, 24) SVD took 170 ms with
# them on a busy 2-core machine, 2.5 ms without. Set before NumPy loads OpenBLAS; never overrides the
# user's own setting, and a library import (``import bayesmag`` in a notebook) is left alone.
if _started_as_command() and "numpy" not in _sys.modules:
    _os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _lapack_pool_deadlocks() -> bool:
    """Whether the installed jaxlib splits a batched LAPACK call (a vmapped Cholesky or triangular solve) over
    its intra-op thread pool and blocks a pool thread until the pieces finish: 0.10.x and 0.11.0 (the path is
    in the 0.10.0 source and compiled out of open-source builds from 0.11.1). When as many such calls run at
    once as the pool has threads, every thread waits for pieces no thread is left to run: the process hangs
    for good (two on this 2-core machine; CI hung 90 minutes in tests/test_hierarchical.py)."""
    try:
        from importlib.metadata import version
        major, minor, patch = (int("".join(c for c in p if c.isdigit()) or 0) for p in version("jaxlib").split(".")[:3])
    except Exception:
        return False
    return (major, minor) == (0, 10) or (major, minor, patch) == (0, 11, 0)


def _cpu_client_created() -> bool:
    """Whether JAX has created its backends (after which the pool size and the dispatch mode are fixed)."""
    xb = _sys.modules.get("jax._src.xla_bridge")
    return bool(getattr(xb, "_backends", None))


#: ``BAYESMAG_CPU_THREADS``: unset (default) lowers batched LAPACK calls one matrix at a time where the jaxlib would
#: deadlock (:mod:`bayesmag._src.core.lapack_guard`); ``"one"`` sizes JAX's CPU pool to one thread instead (the fix
#: before; one core per computation); ``"default"`` leaves JAX as it is (and the hang possible with those jaxlibs).
_CPU_THREADS = _os.environ.get("BAYESMAG_CPU_THREADS", "").strip().lower()
_JAXLIB_SPLITS = _CPU_THREADS != "default" and _lapack_pool_deadlocks()
_NPROC_SET = bool(_os.environ.get("PJRT_NPROC") or _os.environ.get("NPROC"))
_POOL_NEEDS_ONE_THREAD = _JAXLIB_SPLITS and _CPU_THREADS == "one" and not _NPROC_SET
#: Whether ``import bayesmag`` sized JAX's CPU thread pool to one thread (``PJRT_NPROC=1``) and made its CPU
#: computations run on the calling thread: only with ``BAYESMAG_CPU_THREADS=one``, for the jaxlib releases of
#: :func:`_lapack_pool_deadlocks`, if no ``PJRT_NPROC``/``NPROC`` is set, and before JAX creates its CPU client (it
#: reads both once). The cost: one core per computation (second run of paper_hybrid 9.9 -> 13.8 s on 2 cores).
CPU_POOL_AT_IMPORT = _POOL_NEEDS_ONE_THREAD and not _cpu_client_created()
#: Whether ``import bayesmag`` made batched LAPACK calls on the CPU run one matrix at a time
#: (:mod:`bayesmag._src.core.lapack_guard`): the jaxlib releases of :func:`_lapack_pool_deadlocks`, unless
#: ``BAYESMAG_CPU_THREADS`` is "one" or "default". JAX keeps its thread pool; programs compiled after the import
#: (bayesmag's and the caller's) are covered, whenever JAX's client was created.
LAPACK_GUARD_AT_IMPORT = _JAXLIB_SPLITS and _CPU_THREADS != "one"

import jax as _jax  # noqa: E402


def _one_pool_thread() -> None:
    """JAX's CPU pool sized to one thread and its computations run on the calling thread (before its client exists)."""
    _os.environ["PJRT_NPROC"] = "1"
    _jax.config.update("jax_cpu_enable_async_dispatch", False)


if CPU_POOL_AT_IMPORT:
    _one_pool_thread()
elif _POOL_NEEDS_ONE_THREAD:         # but JAX's CPU client exists already: too late to size its pool
    _warnings.warn("BAYESMAG_CPU_THREADS=one, but JAX's CPU client was created before `import bayesmag`, with JAX's "
                   "own thread pool: import bayesmag before running any JAX computation, or set PJRT_NPROC=1 before "
                   "starting Python (or unset BAYESMAG_CPU_THREADS: bayesmag then lowers batched linear algebra one "
                   "matrix at a time instead).", RuntimeWarning, stacklevel=2)
if LAPACK_GUARD_AT_IMPORT:
    try:
        from bayesmag._src.core.lapack_guard import install as _install_lapack_guard
        _install_lapack_guard()
    except Exception as _e:          # JAX's lowering registry moved: the one-thread pool instead, where still possible
        LAPACK_GUARD_AT_IMPORT = False
        if not _NPROC_SET and not _cpu_client_created():
            _one_pool_thread()
            CPU_POOL_AT_IMPORT = True
        else:
            _warnings.warn(f"bayesmag could not guard batched linear algebra against this jaxlib's thread-pool hang "
                           f"({type(_e).__name__}: {_e}); set PJRT_NPROC=1 before starting Python.", RuntimeWarning,
                           stacklevel=2)

#: Whether ``import bayesmag`` switched JAX to float64 (``BAYESMAG_ENABLE_X64`` not "0").
X64_AT_IMPORT = _os.environ.get("BAYESMAG_ENABLE_X64", "1").strip().lower() not in ("0", "false", "no", "off")
if X64_AT_IMPORT:
    _jax.config.update("jax_enable_x64", True)


from bayesmag._src.core.precision import Float64Warning as Float64Warning  # noqa: E402


def x64_enabled() -> bool:
    """Whether JAX computes in float64 now (globally or inside :func:`enable_x64`)."""
    return bool(_jax.config.jax_enable_x64)


def enable_x64():
    """Context manager: float64 inside the block only, the caller's JAX setting restored after.

    Example:
        >>> with enable_x64():  # doctest: +SKIP
        ...     fit = fit_physics(train)
    """
    return _jax.enable_x64(True)


def _needs_x64(fn):
    @_functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from bayesmag._src.core.precision import warn_if_float32
        warn_if_float32(fn.__name__)
        return fn(*args, **kwargs)
    return wrapper


from bayesmag._src.core.cache import configure_compile_cache as configure_compile_cache  # noqa: E402
from bayesmag._src.core.cache import ensure_compile_cache as _ensure_compile_cache  # noqa: E402
from bayesmag._src.core.version import __version__ as __version__  # noqa: E402

# Cold start: JAX's persistent compilation cache is opt-in (BAYESMAG_COMPILE_CACHE=1 or
# [output] compile_cache = true): reading it back crashed on CPU in CI (see _src/core/cache.py). It is
# configured on first use -- not at import, so `import bayesmag` leaves the process's JAX settings alone.

#: public name -> module in bayesmag._src that defines it
_EXPORTS = {
    "app.config": ("Config", "ConfigError", "load_config", "config_from_dict"),
    "core.data": (
        "CalibrationData", "CalibrationWarning", "DataError", "Split", "load_belsten", "load_csv", "make_split", "validate",
        "write_csv",
    ),
    "core.datasets": ("fetch_dataset", "find_dataset", "load_dataset"),
    "core.fit": ("LMSolution", "PhysicsFit", "covariance", "fit_physics", "identifiability", "levenberg_marquardt"),
    "core.frames": ("from_frame", "prediction_frame", "read_parquet", "to_frame"),
    "app.calibrator": ("Calibrator",),
    "pipeline.calibrate": ("CalibrationRun", "calibrate"),
    "pipeline.settings": ("CalibrationSettings", "NetworkSettings", "NutsSettings", "PhysicsSettings", "UQSettings"),
    "pipeline.stages": ("CalibrationError",),
    "core.predictor": ("Prediction", "Predictor"),
    "core.likelihoods": ("register_likelihood",),
    "app.discover_outputs": ("write_discovery",),
    "app.nuts_outputs": ("write_nuts_outputs",),
    "app.export": ("ExportError", "export_run"),
    "app.artifact": ("ArtifactError", "Calibration", "load", "load_field"),
    "pipeline.discover": ("DiscoverOptions", "DiscoveryResult", "discover"),
    "app.job": ("JobError", "run_job"),
    "pipeline.hybrid": ("HybridPrediction", "fuse"),
    "core.network": ("MCPrediction", "NetworkSpec", "ResidualNetwork", "fit_residual_network", "mc_predict"),
    "pipeline.nuts": ("NutsResult", "compare_models", "crosscheck", "loo", "parse_priors", "run_nuts"),
    "core.physics": (
        "T0_DEFAULT", "resolve_t0", "EXTRA_TERMS", "Inputs", "InputTransform", "PhysicsModel", "Term", "ThermoAffine", "inputs_from_data",
    ),
    "core.catalogue": (
        "CATALOGUE", "AxisQuadratic", "CrossAxisQuadratic", "CubicNonlinearity", "Hysteresis", "OffsetDrift", "RunOffset",
        "TemperatureQuadratic", "ThermalLag", "TimingOffset", "register_term",
    ),
    "core.physics_uq": ("PhysicsUQ", "estimate_input_noise", "physics_uncertainty", "sobol_normal"),
}
_WHERE = {name: mod for mod, names in _EXPORTS.items() for name in names}
#: public name -> its name in the defining module
_ALIASES = {"register_likelihood": "register", "register_term": "register"}
_SUBMODULES = ("likelihoods", "metrics", "simulate")
_NEEDS_X64 = ("fit_physics", "physics_uncertainty", "run_nuts", "run_job", "discover", "levenberg_marquardt", "calibrate")


def __getattr__(name):
    if name.startswith("__"):
        raise AttributeError(f"module 'bayesmag' has no attribute {name!r}")
    _ensure_compile_cache()
    if name in _SUBMODULES:
        return _importlib.import_module(f".{name}", __name__)
    mod = _WHERE.get(name)
    if mod is None:
        raise AttributeError(f"module 'bayesmag' has no attribute {name!r}")
    if name in ("EXTRA_TERMS", "CATALOGUE"):
        _importlib.import_module("._src.core.catalogue", __name__)      # registers the catalogue's terms
    value = getattr(_importlib.import_module(f"._src.{mod}", __name__), _ALIASES.get(name, name))
    if name in _NEEDS_X64:                                      # float64 entry points warn in float32
        value = _needs_x64(value)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_WHERE) | set(_SUBMODULES))


__all__ = [  # noqa: F822 (resolved lazily by __getattr__)
    "likelihoods", "metrics", "simulate", "enable_x64", "x64_enabled", "Float64Warning", "X64_AT_IMPORT",
    "configure_compile_cache", "Calibrator", "ExportError", "export_run", "calibrate", "CalibrationRun",
    "CalibrationSettings", "NetworkSettings", "NutsSettings", "PhysicsSettings", "UQSettings", "CalibrationError",
    "Prediction", "Predictor", "register_likelihood", "register_term", "write_discovery", "write_nuts_outputs",
    "T0_DEFAULT", "resolve_t0",
    "from_frame", "prediction_frame", "read_parquet", "to_frame", "HybridPrediction", "fuse", "MCPrediction",
    "NetworkSpec", "ResidualNetwork", "fit_residual_network", "mc_predict", "CATALOGUE", "AxisQuadratic",
    "CrossAxisQuadratic", "CubicNonlinearity", "Hysteresis", "OffsetDrift", "RunOffset", "TimingOffset", "NutsResult",
    "compare_models", "crosscheck", "loo", "parse_priors", "run_nuts", "ArtifactError", "Calibration", "load",
    "load_field", "DiscoverOptions", "DiscoveryResult", "discover", "CalibrationData", "CalibrationWarning", "Config",
    "ConfigError", "DataError",
    "EXTRA_TERMS", "Inputs", "InputTransform", "JobError", "LMSolution", "PhysicsFit", "PhysicsModel",
    "PhysicsUQ", "Split", "Term", "TemperatureQuadratic", "ThermalLag", "ThermoAffine", "covariance",
    "estimate_input_noise", "fetch_dataset", "find_dataset", "fit_physics", "identifiability",
    "inputs_from_data", "levenberg_marquardt", "load_belsten", "load_config", "config_from_dict", "load_csv", "load_dataset",
    "make_split", "physics_uncertainty", "run_job", "sobol_normal", "validate", "write_csv",
]
