"""The ``[nuts]`` table's check (application layer): settings and priors validated once, before any fitting."""

from __future__ import annotations

import dataclasses

from bayesmag._src.app.config import config_error
from bayesmag._src.pipeline.nuts import NutsResult, check_settings, parse_priors

__all__ = ["check_nuts_config", "run_nuts_stage"]


def check_nuts_config(cfg, param_names) -> dict:
    """Validate ``[nuts]`` once, before any fitting: settings and priors; returns the parsed priors.

    Raises :class:`~bayesmag.ConfigError` naming the ``nuts.*`` key.
    """
    n = cfg.nuts
    keys = [f.name for f in dataclasses.fields(n)]
    try:       # impossible settings are config errors; too-small ones become warnings in run_nuts
        check_settings(chains=n.chains, warmup=n.warmup, draws=n.draws, target_accept=n.target_accept,
                       chain_method=n.chain_method)
        return parse_priors(n.priors, tuple(param_names), likelihood=n.likelihood)
    except ValueError as e:
        raise config_error(e, "nuts", keys) from None


def run_nuts_stage(cfg, fit, train, priors, *, progress: bool = False) -> NutsResult:
    """The NUTS stage with ``[nuts]``'s settings and the priors :func:`check_nuts_config` parsed
    (:func:`~bayesmag._src.pipeline.stages.run_nuts_stage`; the job runs it inside :func:`~bayesmag.calibrate`)."""
    from bayesmag._src.pipeline.stages import run_nuts_stage as run
    return run(cfg.settings(nuts_priors=priors).nuts, fit, train, progress=progress)
