"""Thresholds, defaults and choice lists shared by the NUTS modules (the bottom of the package)."""

from __future__ import annotations

__all__ = ["RHAT_MAX", "ESS_MIN", "MEAN_DIFF_TOL", "SD_RATIO_RANGE", "MIN_DRAWS", "MIN_CHAINS",
           "DEFAULT_PRIOR_SCALE", "INIT_RADIUS", "EBFMI_MIN", "CHAIN_METHODS", "PARAMETRISATIONS", "NutsWarning"]

#: Largest acceptable rank-normalised split R-hat (Vehtari et al. 2021).
RHAT_MAX = 1.01
#: Smallest acceptable bulk and tail ESS (Vehtari et al. 2021: 100 per chain with 4 chains).
ESS_MIN = 400
#: Largest |mean_NUTS - theta_LM| / sd_LM for "Laplace approximation adequate". The Monte
#: Carlo error of a posterior mean is ~1/sqrt(ESS) = 0.05 sd at ESS 400, so 0.2 is 4 MCSE.
MEAN_DIFF_TOL = 0.2
#: Acceptable sd_NUTS / sd_LM. The MC error of an sd at ESS 400 is ~1/sqrt(2*400) = 3.5%.
SD_RATIO_RANGE = (0.9, 1.1)
#: Fewer draws per chain than this (or fewer than 2 chains) make R-hat/ESS unreliable: warning.
MIN_DRAWS = 100
MIN_CHAINS = 2
#: Default prior sd of each physics parameter, in LM standard errors.
DEFAULT_PRIOR_SCALE = 100.0
#: Initial points: whitened coordinates drawn uniformly in [-INIT_RADIUS, INIT_RADIUS] (as
#: numpyro's init_to_uniform), overdispersed against the unit-scale whitened posterior.
INIT_RADIUS = 2.0
#: E-BFMI below this signals poor exploration of the energy distribution (Betancourt 2016).
EBFMI_MIN = 0.3
#: How chains run: one vmapped program, mapped one after another, or one device each.
CHAIN_METHODS = ("vectorized", "parallel", "sequential")
#: Coordinates NUTS samples (module docstring of :mod:`bayesmag._src.pipeline.nuts`).
PARAMETRISATIONS = ("whitened", "scaled")


class NutsWarning(UserWarning):
    """A NUTS result that should not be trusted as it stands; the message names the fix."""
