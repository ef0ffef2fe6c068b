"""Accuracy, calibration and sharpness metrics for any predictions."""

from bayesmag._src.core.metrics import DEFAULT_LEVELS as DEFAULT_LEVELS
from bayesmag._src.core.metrics import calibration_curve as calibration_curve
from bayesmag._src.core.metrics import coverage as coverage
from bayesmag._src.core.metrics import crps as crps
from bayesmag._src.core.metrics import interval_width as interval_width
from bayesmag._src.core.metrics import mae as mae
from bayesmag._src.core.metrics import nll as nll
from bayesmag._src.core.metrics import paired_test as paired_test
from bayesmag._src.core.metrics import pit as pit
from bayesmag._src.core.metrics import rmse as rmse
from bayesmag._src.core.metrics import score as score
from bayesmag._src.core.metrics import score_per_axis as score_per_axis
from bayesmag._src.core.metrics import summarize as summarize

__all__ = ["rmse", "mae", "coverage", "interval_width", "nll", "crps", "pit",
           "calibration_curve", "paired_test", "score", "score_per_axis", "summarize", "DEFAULT_LEVELS"]
