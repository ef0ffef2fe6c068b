"""bayesmag: calibrate 3-axis magnetometers against a reference, with trustworthy uncertainty.

The public API is re-exported here explicitly; the implementation lives in ``bayesmag._src``.
Submodules ``bayesmag.likelihoods``, ``bayesmag.metrics`` and ``bayesmag.simulate`` are public too.
"""

import jax as _jax

# The physics fit and its uncertainty need float64; the residual network casts to float32 itself.
_jax.config.update("jax_enable_x64", True)

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
from ._src.nuts import (
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
    RunOffset as RunOffset,
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

__version__ = "0.1.0"

__all__ = [
    "likelihoods", "metrics", "simulate",
    "HybridPrediction", "fuse", "MCPrediction", "NetworkSpec", "ResidualNetwork", "fit_residual_network", "mc_predict",
    "CATALOGUE", "AxisQuadratic", "CrossAxisQuadratic", "CubicNonlinearity", "Hysteresis", "OffsetDrift", "RunOffset",
    "TimingOffset",
    "NutsResult", "compare_models", "crosscheck", "loo", "parse_priors", "run_nuts",
    "ArtifactError", "Calibration", "load", "DiscoverOptions", "DiscoveryResult", "discover",
    "CalibrationData", "Config", "ConfigError", "DataError", "EXTRA_TERMS", "Inputs", "InputTransform", "JobError",
    "LMSolution", "PhysicsFit", "PhysicsModel", "PhysicsUQ", "Split", "Term", "TemperatureQuadratic", "ThermalLag",
    "ThermoAffine", "covariance", "estimate_input_noise", "fetch_dataset", "find_dataset", "fit_physics",
    "identifiability", "inputs_from_data", "levenberg_marquardt", "load_belsten", "load_config", "load_csv",
    "load_dataset", "make_split", "physics_uncertainty", "run_job", "sobol_normal", "validate", "write_csv",
]
