"""bayesmag: calibrate 3-axis magnetometers against a reference, with trustworthy uncertainty.

The public API is re-exported here explicitly; the implementation lives in ``bayesmag._src``.
Submodules ``bayesmag.likelihoods``, ``bayesmag.metrics`` and ``bayesmag.simulate`` are public too.

Names are imported on first use (PEP 562), so ``import bayesmag`` and the command line start
without loading NumPyro, ArviZ or the discovery machinery a job may not need.
"""

import importlib as _importlib

import jax as _jax

# The physics fit and its uncertainty need float64; the residual network casts to float32 itself.
_jax.config.update("jax_enable_x64", True)

from ._src.cache import configure_compile_cache as configure_compile_cache  # noqa: E402

# Cold start: reuse compiled code across processes (off: BAYESMAG_COMPILE_CACHE=0 or [output] compile_cache = false).
configure_compile_cache()

__version__ = "0.1.0"

#: public name -> module in bayesmag._src that defines it
_EXPORTS = {
    "config": ("Config", "ConfigError", "load_config"),
    "data": (
        "CalibrationData", "DataError", "Split", "load_belsten", "load_csv", "make_split", "validate",
        "write_csv",
    ),
    "datasets": ("fetch_dataset", "find_dataset", "load_dataset"),
    "fit": ("LMSolution", "PhysicsFit", "covariance", "fit_physics", "identifiability", "levenberg_marquardt"),
    "frames": ("from_frame", "prediction_frame", "read_parquet", "to_frame"),
    "calibrator": ("Calibrator",),
    "export": ("ExportError", "export_run"),
    "artifact": ("ArtifactError", "Calibration", "load"),
    "discover": ("DiscoverOptions", "DiscoveryResult", "discover"),
    "job": ("JobError", "run_job"),
    "hybrid": ("HybridPrediction", "fuse"),
    "network": ("MCPrediction", "NetworkSpec", "ResidualNetwork", "fit_residual_network", "mc_predict"),
    "nuts": ("NutsResult", "compare_models", "crosscheck", "loo", "parse_priors", "run_nuts"),
    "physics": (
        "EXTRA_TERMS", "Inputs", "InputTransform", "PhysicsModel", "Term", "ThermoAffine", "inputs_from_data",
    ),
    "catalogue": (
        "CATALOGUE", "AxisQuadratic", "CrossAxisQuadratic", "CubicNonlinearity", "Hysteresis", "OffsetDrift",
        "TemperatureQuadratic", "ThermalLag", "TimingOffset", "RunOffset",
    ),
    "physics_uq": ("PhysicsUQ", "estimate_input_noise", "physics_uncertainty", "sobol_normal"),
}
_WHERE = {name: mod for mod, names in _EXPORTS.items() for name in names}
_SUBMODULES = ("likelihoods", "metrics", "simulate")


def __getattr__(name):
    if name in _SUBMODULES:
        return _importlib.import_module(f".{name}", __name__)
    mod = _WHERE.get(name)
    if mod is None:
        raise AttributeError(f"module 'bayesmag' has no attribute {name!r}")
    if name in ("EXTRA_TERMS", "CATALOGUE"):
        _importlib.import_module("._src.catalogue", __name__)      # registers the catalogue's terms
    value = getattr(_importlib.import_module(f"._src.{mod}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_WHERE) | set(_SUBMODULES))


__all__ = [  # noqa: F822 (resolved lazily by __getattr__)
    "likelihoods", "metrics", "simulate", "configure_compile_cache", "Calibrator", "ExportError", "export_run",
    "from_frame", "prediction_frame", "read_parquet", "to_frame", "HybridPrediction", "fuse", "MCPrediction",
    "NetworkSpec", "ResidualNetwork", "fit_residual_network", "mc_predict", "CATALOGUE", "AxisQuadratic",
    "CrossAxisQuadratic", "CubicNonlinearity", "Hysteresis", "OffsetDrift", "RunOffset", "TimingOffset", "NutsResult",
    "compare_models", "crosscheck", "loo", "parse_priors", "run_nuts", "ArtifactError", "Calibration", "load",
    "DiscoverOptions", "DiscoveryResult", "discover", "CalibrationData", "Config", "ConfigError", "DataError",
    "EXTRA_TERMS", "Inputs", "InputTransform", "JobError", "LMSolution", "PhysicsFit", "PhysicsModel",
    "PhysicsUQ", "Split", "Term", "TemperatureQuadratic", "ThermalLag", "ThermoAffine", "covariance",
    "estimate_input_noise", "fetch_dataset", "find_dataset", "fit_physics", "identifiability",
    "inputs_from_data", "levenberg_marquardt", "load_belsten", "load_config", "load_csv", "load_dataset",
    "make_split", "physics_uncertainty", "run_job", "sobol_normal", "validate", "write_csv",
]
