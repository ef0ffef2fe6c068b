"""Accuracy, calibration and sharpness metrics for any predictions."""

from ._src.metrics import DEFAULT_LEVELS as DEFAULT_LEVELS
from ._src.metrics import calibration_curve as calibration_curve
from ._src.metrics import coverage as coverage
from ._src.metrics import crps as crps
from ._src.metrics import interval_width as interval_width
from ._src.metrics import mae as mae
from ._src.metrics import nll as nll
from ._src.metrics import paired_test as paired_test
from ._src.metrics import pit as pit
from ._src.metrics import rmse as rmse
from ._src.metrics import score as score
from ._src.metrics import score_per_axis as score_per_axis
from ._src.metrics import summarize as summarize

__all__ = ["rmse", "mae", "coverage", "interval_width", "nll", "crps", "pit",
           "calibration_curve", "paired_test", "score", "score_per_axis", "summarize", "DEFAULT_LEVELS"]
