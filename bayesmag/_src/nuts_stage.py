"""The job's NUTS stage (application layer): ``[nuts]`` settings in, ``metrics["nuts"]`` and files out."""

from __future__ import annotations

import dataclasses
import time

from .config import config_error
from .nuts import NutsResult, check_settings, parse_priors, run_nuts, write_nuts_outputs

__all__ = ["run_nuts_stage"]


def run_nuts_stage(cfg, result: dict, train, timings: dict, *, progress: bool = False) -> NutsResult:
    """The job's NUTS stage (``[nuts] enabled = true``): sample, add ``metrics["nuts"]``, register the writer."""
    n = cfg.nuts
    fit = result["fit"]
    t = time.perf_counter()
    try:
        priors = parse_priors(n.priors, fit.param_names, likelihood=n.likelihood)
    except ValueError as e:
        raise config_error(e, "nuts", [f.name for f in dataclasses.fields(n)]) from None
    try:       # impossible settings are config errors; too-small ones become warnings in run_nuts
        check_settings(chains=n.chains, warmup=n.warmup, draws=n.draws, target_accept=n.target_accept,
                       chain_method=n.chain_method)
    except ValueError as e:
        raise config_error(e, "nuts", [f.name for f in dataclasses.fields(n)]) from None
    res = run_nuts(train, fit, chains=n.chains, warmup=n.warmup, draws=n.draws, target_accept=n.target_accept,
                   chain_method=n.chain_method, likelihood=n.likelihood, priors=priors, seed=n.seed,
                   progress=progress)
    timings["nuts"] = time.perf_counter() - t
    result["nuts"] = res
    result["metrics"]["nuts"] = res.metrics()
    if res.warnings:
        result["metrics"].setdefault("warnings", []).extend(res.warnings)
    figures = cfg.output.figures
    result.setdefault("writers", []).append(lambda staging: write_nuts_outputs(res, staging, figures=figures))
    return res
