"""Model comparison by PSIS-LOO (ArviZ) on NUTS results."""

from __future__ import annotations

import warnings
from typing import Any, Mapping

import numpy as np

from bayesmag._src.pipeline.nuts.idata import arviz

__all__ = ["loo", "compare_models"]


def loo(result, *, axis: str | None = None, pointwise: bool = True):
    """PSIS-LOO (Vehtari et al. 2017) of a :class:`NutsResult` or its InferenceData via ArviZ.

    ``axis`` restricts it to one output axis; by default all sampled axes' rows count as
    observations. The relative efficiency is computed from the posterior draws that the
    (thinned) log-likelihood was evaluated at.

    Returns:
      ``arviz.ELPDData`` (elpd_loo, se, p_loo, pareto_k, ...).
    """
    az = arviz()
    idata = getattr(result, "idata", result)     # a NutsResult or its InferenceData
    ll = idata.log_likelihood
    post = idata.posterior
    if axis is not None:
        if axis not in [str(a) for a in ll.axis.values]:
            raise ValueError(f"loo: axis {axis!r} was not sampled; sampled axes: {[str(a) for a in ll.axis.values]}.")
        ll, post = ll.sel(axis=[axis]), post.sel(axis=[axis])
    kept = post.sel(draw=ll.draw.values)
    n_samples = ll.sizes["chain"] * ll.sizes["draw"]
    if ll.sizes["chain"] > 1:
        ess = az.ess(kept, method="mean")
        reff = float(np.hstack([ess[v].values.ravel() for v in ess.data_vars]).mean() / n_samples)
    else:
        reff = 1.0
    sub = az.InferenceData(posterior=kept, log_likelihood=ll)
    return az.loo(sub, pointwise=pointwise, reff=reff)


def compare_models(models: Mapping[str, Any], *, axis: str | None = None, method: str = "stacking"):
    """Compare physics models fitted to the same rows by PSIS-LOO ELPD (``arviz.compare``).

    Args:
      models: ``{name: NutsResult or InferenceData}``, at least two, with identical observed data.
      axis: compare on one output axis only (default: all sampled axes together).
    Returns:
      the ``arviz.compare`` DataFrame (rank, elpd_loo, p_loo, elpd_diff, weight, se, dse, ...).
    Raises:
      ValueError: fewer than two models, or models observed on different data.
    """
    az = arviz()
    if len(models) < 2:
        raise ValueError(f"compare_models needs at least two models; got {list(models)}.")
    ref_name, ref = None, None
    for name, m in models.items():
        idata = getattr(m, "idata", m)
        obs = idata.observed_data.b_ref
        if axis is not None:
            obs = obs.sel(axis=axis)
        if ref is None:
            ref_name, ref = name, obs
        elif obs.shape != ref.shape or not np.array_equal(obs.values, ref.values):
            raise ValueError(f"compare_models: {name!r} and {ref_name!r} were fitted to different data "
                             f"(observed shapes {obs.shape} vs {ref.shape}); LOO/ELPD compares models on the "
                             f"same rows.")
    elpds = {name: loo(m, axis=axis) for name, m in models.items()}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)       # arviz internals vs pandas 3 deprecations
        warnings.simplefilter("ignore", DeprecationWarning)
        return az.compare(elpds, method=method)

