"""The job's NUTS stage (application layer): ``[nuts]`` settings in, ``metrics["nuts"]`` and files out."""

from __future__ import annotations

import dataclasses

from .config import config_error
from .nuts import NutsResult, check_settings, parse_priors, run_nuts

__all__ = ["run_nuts_stage"]


def run_nuts_stage(cfg, fit, train, *, progress: bool = False) -> NutsResult:
    """The job's NUTS stage (``[nuts] enabled = true``): priors and settings from ``[nuts]``, then sample.

    Returns the :class:`NutsResult`; :func:`~bayesmag._src.job.run_job` adds its metrics and files.
    """
    n = cfg.nuts
    keys = [f.name for f in dataclasses.fields(n)]
    try:
        priors = parse_priors(n.priors, fit.param_names, likelihood=n.likelihood)
    except ValueError as e:
        raise config_error(e, "nuts", keys) from None
    try:       # impossible settings are config errors; too-small ones become warnings in run_nuts
        check_settings(chains=n.chains, warmup=n.warmup, draws=n.draws, target_accept=n.target_accept,
                       chain_method=n.chain_method)
    except ValueError as e:
        raise config_error(e, "nuts", keys) from None
    return run_nuts(train, fit, chains=n.chains, warmup=n.warmup, draws=n.draws, target_accept=n.target_accept,
                    chain_method=n.chain_method, likelihood=n.likelihood, priors=priors, seed=n.seed,
                    progress=progress)
