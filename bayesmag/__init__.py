"""bayesmag: calibrate 3-axis magnetometers against a reference, with trustworthy uncertainty.

The public API is re-exported here explicitly; the implementation lives in ``bayesmag._src``.
Submodules ``bayesmag.likelihoods``, ``bayesmag.metrics`` and ``bayesmag.simulate`` are public too.

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
import os as _os
import warnings as _warnings

import jax as _jax

#: Whether ``import bayesmag`` switched JAX to float64 (``BAYESMAG_ENABLE_X64`` not "0").
X64_AT_IMPORT = _os.environ.get("BAYESMAG_ENABLE_X64", "1").strip().lower() not in ("0", "false", "no", "off")
if X64_AT_IMPORT:
    _jax.config.update("jax_enable_x64", True)


class Float64Warning(UserWarning):
    """A bayesmag computation that needs float64 ran with JAX in float32."""


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
        if not x64_enabled():
            _warnings.warn(f"bayesmag.{fn.__name__} runs with JAX in float32 (BAYESMAG_ENABLE_X64=0 and no "
                           f"`with bayesmag.enable_x64():`); its results are float32 approximations.",
                           Float64Warning, stacklevel=2)
        return fn(*args, **kwargs)
    return wrapper

from ._src.config import Config as Config, ConfigError as ConfigError, load_config as load_config
from ._src.data import (
    CalibrationData as CalibrationData,
    DataError as DataError,
    Split as Split,
    load_belsten as load_belsten,
    load_csv as load_csv,
    make_split as make_split,
    validate as validate,
    write_csv as write_csv,
)
from ._src.datasets import fetch_dataset as fetch_dataset, find_dataset as find_dataset, load_dataset as load_dataset
from ._src.fit import (
    LMSolution as LMSolution,
    PhysicsFit as PhysicsFit,
    covariance as covariance,
    fit_physics as fit_physics,
    identifiability as identifiability,
    levenberg_marquardt as levenberg_marquardt,
)
from ._src.artifact import ArtifactError as ArtifactError, Calibration as Calibration, load as load
from ._src.discover import DiscoverOptions as DiscoverOptions, DiscoveryResult as DiscoveryResult, discover as discover
from ._src.job import JobError as JobError, run_job as run_job
from ._src.hybrid import HybridPrediction as HybridPrediction, fuse as fuse
from ._src.network import (
    MCPrediction as MCPrediction,
    NetworkSpec as NetworkSpec,
    ResidualNetwork as ResidualNetwork,
    fit_residual_network as fit_residual_network,
    mc_predict as mc_predict,
)
from ._src.nuts import (  # the package bayesmag._src.nuts
    NutsResult as NutsResult,
    compare_models as compare_models,
    crosscheck as crosscheck,
    loo as loo,
    parse_priors as parse_priors,
    run_nuts as run_nuts,
)
from ._src.physics import (
    EXTRA_TERMS as EXTRA_TERMS,
    Inputs as Inputs,
    InputTransform as InputTransform,
    PhysicsModel as PhysicsModel,
    Term as Term,
    ThermoAffine as ThermoAffine,
    inputs_from_data as inputs_from_data,
)
from ._src.catalogue import (  # the discovery catalogue: model extensions, registered in EXTRA_TERMS
    CATALOGUE as CATALOGUE,
    AxisQuadratic as AxisQuadratic,
    CrossAxisQuadratic as CrossAxisQuadratic,
    CubicNonlinearity as CubicNonlinearity,
    Hysteresis as Hysteresis,
    OffsetDrift as OffsetDrift,
    TemperatureQuadratic as TemperatureQuadratic,
    ThermalLag as ThermalLag,
    TimingOffset as TimingOffset,
)
from ._src.physics_uq import (
    PhysicsUQ as PhysicsUQ,
    estimate_input_noise as estimate_input_noise,
    physics_uncertainty as physics_uncertainty,
    sobol_normal as sobol_normal,
)

from . import likelihoods as likelihoods, metrics as metrics, simulate as simulate

# float64 entry points warn when called in float32 (see the module docstring)
fit_physics = _needs_x64(fit_physics)
physics_uncertainty = _needs_x64(physics_uncertainty)
run_nuts = _needs_x64(run_nuts)
run_job = _needs_x64(run_job)
discover = _needs_x64(discover)
levenberg_marquardt = _needs_x64(levenberg_marquardt)

__version__ = "0.1.0"

__all__ = [
    "likelihoods", "metrics", "simulate", "enable_x64", "x64_enabled", "Float64Warning", "X64_AT_IMPORT",
    "HybridPrediction", "fuse", "MCPrediction", "NetworkSpec", "ResidualNetwork", "fit_residual_network", "mc_predict",
    "CATALOGUE", "AxisQuadratic", "CrossAxisQuadratic", "CubicNonlinearity", "Hysteresis", "OffsetDrift",
    "TimingOffset",
    "NutsResult", "compare_models", "crosscheck", "loo", "parse_priors", "run_nuts",
    "ArtifactError", "Calibration", "load", "DiscoverOptions", "DiscoveryResult", "discover",
    "CalibrationData", "Config", "ConfigError", "DataError", "EXTRA_TERMS", "Inputs", "InputTransform", "JobError",
    "LMSolution", "PhysicsFit", "PhysicsModel", "PhysicsUQ", "Split", "Term", "TemperatureQuadratic", "ThermalLag",
    "ThermoAffine", "covariance", "estimate_input_noise", "fetch_dataset", "find_dataset", "fit_physics",
    "identifiability", "inputs_from_data", "levenberg_marquardt", "load_belsten", "load_config", "load_csv",
    "load_dataset", "make_split", "physics_uncertainty", "run_job", "sobol_normal", "validate", "write_csv",
]
