"""Predictive distributions (Gaussian, Laplace, Student-t, and any family you register) behind one interface:
the one registry of observation models for the network, fusion, saved calibrations and NUTS."""

from bayesmag._src.core.likelihoods import LIKELIHOODS as LIKELIHOODS
from bayesmag._src.core.likelihoods import Gaussian as Gaussian
from bayesmag._src.core.likelihoods import Laplace as Laplace
from bayesmag._src.core.likelihoods import Likelihood as Likelihood
from bayesmag._src.core.likelihoods import StudentT as StudentT
from bayesmag._src.core.likelihoods import get_likelihood as get_likelihood
from bayesmag._src.core.likelihoods import moment_match as moment_match
from bayesmag._src.core.likelihoods import sample_by_inversion as sample_by_inversion
from bayesmag._src.core.likelihoods import ShapeParam as ShapeParam
from bayesmag._src.core.likelihoods import register as register
from bayesmag._src.core.likelihoods import unregister as unregister

__all__ = ["Likelihood", "ShapeParam", "Gaussian", "Laplace", "StudentT", "LIKELIHOODS", "get_likelihood",
           "moment_match", "sample_by_inversion", "register", "unregister"]
