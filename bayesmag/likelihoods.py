"""Predictive distributions (Gaussian, Laplace, Student-t) behind one interface."""

from ._src.likelihoods import LIKELIHOODS as LIKELIHOODS
from ._src.likelihoods import Gaussian as Gaussian
from ._src.likelihoods import Laplace as Laplace
from ._src.likelihoods import Likelihood as Likelihood
from ._src.likelihoods import StudentT as StudentT
from ._src.likelihoods import get_likelihood as get_likelihood
from ._src.likelihoods import moment_match as moment_match
from ._src.likelihoods import sample_by_inversion as sample_by_inversion

__all__ = ["Likelihood", "Gaussian", "Laplace", "StudentT", "LIKELIHOODS", "get_likelihood",
           "moment_match", "sample_by_inversion"]
