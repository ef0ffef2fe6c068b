"""Predictive distributions (Gaussian, Laplace, Student-t, and any family you register) behind one interface:
the one registry of observation models for the network, fusion, saved calibrations and NUTS."""

from ._src.likelihoods import LIKELIHOODS as LIKELIHOODS
from ._src.likelihoods import Gaussian as Gaussian
from ._src.likelihoods import Laplace as Laplace
from ._src.likelihoods import Likelihood as Likelihood
from ._src.likelihoods import StudentT as StudentT
from ._src.likelihoods import get_likelihood as get_likelihood
from ._src.likelihoods import moment_match as moment_match
from ._src.likelihoods import sample_by_inversion as sample_by_inversion
from ._src.likelihoods import ShapeParam as ShapeParam
from ._src.likelihoods import unregister as unregister

__all__ = ["Likelihood", "ShapeParam", "Gaussian", "Laplace", "StudentT", "LIKELIHOODS", "get_likelihood",
           "moment_match", "sample_by_inversion", "unregister"]
