"""The job's NUTS stage (application layer): ``[nuts]`` settings in, ``metrics["nuts"]`` and files out."""

from __future__ import annotations

import dataclasses

from bayesmag._src.app.config import config_error
from bayesmag._src.pipeline.nuts import NutsResult, check_settings, parse_priors, run_nuts

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
    """The job's NUTS stage (``[nuts] enabled = true``): sample with the priors :func:`check_nuts_config` parsed.

    Returns the :class:`NutsResult`; :func:`~bayesmag._src.app.job.run_job` adds its metrics and files.
    Every warning raised while sampling ends up once in ``res.warnings`` (the job prints them and puts
    them in metrics.json), never as a raw Python warning line: the NutsWarnings are there already,
    any other user or runtime warning (e.g. from NumPyro) is added once.
    """
    import warnings

    from bayesmag._src.pipeline.nuts.constants import NutsWarning

    n = cfg.nuts
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = run_nuts(train, fit, chains=n.chains, warmup=n.warmup, draws=n.draws, target_accept=n.target_accept,
                       chain_method=n.chain_method, likelihood=n.likelihood, priors=priors, seed=n.seed,
                       progress=progress)
    found = list(res.warnings)
    for w in caught:             # library deprecation notices are for developers, not a calibration's user
        if not issubclass(w.category, (UserWarning, RuntimeWarning)):
            continue
        msg = str(w.message) if issubclass(w.category, NutsWarning) else f"NUTS ({w.category.__name__}): {w.message}"
        if msg not in found:
            found.append(msg)
    return dataclasses.replace(res, warnings=tuple(dict.fromkeys(found)))
