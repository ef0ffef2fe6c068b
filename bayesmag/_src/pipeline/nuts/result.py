"""The result of a NUTS run and its ``metrics.json`` block."""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any

import numpy as np

from bayesmag._src.core.fit import PhysicsFit
from bayesmag._src.pipeline.nuts.constants import ESS_MIN, MEAN_DIFF_TOL, RHAT_MAX, SD_RATIO_RANGE

__all__ = ["NutsResult"]


@dataclasses.dataclass(frozen=True)
class NutsResult:
    """A NUTS run of a physics fit: InferenceData, summary table, cross-check, warnings, timings.

    Attributes:
      idata: ``arviz.InferenceData`` with groups posterior (``theta`` [axis, parameter],
        ``sigma`` [axis], learned shape fields such as ``df`` [axis]), sample_stats (ArviZ's
        [chain, draw] layout for the joint sampler, per-axis values as ``<stat>_axis``;
        :data:`~bayesmag._src.pipeline.nuts.idata.JOINT_STATS`), log_likelihood and
        posterior_predictive (``b_ref`` [row, axis], the same thinned draws), observed_data
        and constant_data (the LM estimate and covariance).
      summary: pandas DataFrame, one row per (axis, parameter): mean, sd, HDI, MCSE,
        bulk/tail ESS, R-hat, and the LM value/sd with the standardised differences.
      crosscheck: per axis, the NUTS-vs-LM comparison (:func:`crosscheck`).
      verdicts: per axis, one line.
      warnings: problems found, each naming the fix.
      seconds: ``compile``, ``sampling``, ``postprocess``, ``total``.
      settings: the sampler settings and prior description.
    """

    idata: Any
    summary: Any
    crosscheck: dict
    verdicts: dict
    warnings: tuple
    seconds: dict
    settings: dict
    fit: PhysicsFit | None = None

    @property
    def axes(self) -> tuple[str, ...]:
        return tuple(str(a) for a in self.idata.posterior.axis.values)

    def loo(self, axis: str | None = None):
        """PSIS-LOO of all sampled axes together, or of one ``axis`` (:func:`~bayesmag.loo`)."""
        from bayesmag._src.pipeline.nuts.compare import loo       # compare does not import this module
        return loo(self.idata, axis=axis)

    def metrics(self) -> dict:
        """The ``"nuts"`` block of metrics.json."""
        out = {"settings": self.settings, "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
               "axes": {}, "warnings": list(self.warnings), "thresholds": {
                   "rhat_max": RHAT_MAX, "ess_min": ESS_MIN, "mean_diff_tol_lm_sd": MEAN_DIFF_TOL,
                   "sd_ratio_range": list(SD_RATIO_RANGE)}}
        elpd_total = 0.0
        for ax in self.axes:
            c = self.crosscheck[ax]
            block = {k: c[k] for k in ("max_rhat", "min_ess_bulk", "min_ess_tail", "divergences",
                                      "max_abs_mean_diff_lm_sd", "max_abs_mean_diff_parameter", "sd_ratio_min",
                                      "sd_ratio_max", "whitened_eigenvalue_range", "max_corr_diff", "ebfmi_min",
                                      "max_tree_depth_fraction", "verdict", "adequate")}
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    lo = self.loo(ax)
                block["elpd_loo"] = float(lo.elpd_loo)
                block["elpd_loo_se"] = float(lo.se)
                block["p_loo"] = float(lo.p_loo)
                block["pareto_k_above_0.7"] = int(np.sum(np.asarray(lo.pareto_k) > 0.7))
                elpd_total += float(lo.elpd_loo)
            except Exception as e:  # pragma: no cover - LOO is a by-product; never fail the job on it
                block["elpd_loo"] = None
                block["elpd_loo_error"] = str(e)
            out["axes"][ax] = block
        out["elpd_loo_total"] = elpd_total
        return out
