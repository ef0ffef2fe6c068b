"""Job configuration: TOML validated into typed, frozen objects.

Unknown keys and wrong types are :class:`ConfigError` naming the key, the value and the
valid choices. ``--set key=value`` overrides are applied before validation; the value is
parsed as a TOML literal (``uq.n_params=100``, ``split.kind="by_run"``) and falls back to
a plain string (``data.path=my.csv``). Setting ``data.path`` replaces whatever data source
the file names.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import re
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, ClassVar, Union

from bayesmag._src.core.data import TIME_UNITS
from bayesmag._src.core.likelihoods import LIKELIHOODS
from bayesmag._src.core.network import ACTIVATIONS, VALIDATION_KINDS
from bayesmag._src.core.physics import T0_DEFAULT
from bayesmag._src.core.predictor import FUSIONS
from bayesmag._src.pipeline import settings as S

__all__ = ["Config", "ConfigError", "load_config", "config_from_dict", "apply_overrides", "to_toml",
           "DataConfig", "SplitConfig", "packaged_configs_dir", "resolve_config_path", "PhysicsConfig", "UQConfig",
           "OutputConfig", "NetworkConfig", "NutsConfig", "CertificateConfig", "MeasurementConfig",
           "config_error"]


class ConfigError(ValueError):
    """A configuration problem; the message names the key and the fix."""


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Where the recording comes from: a named dataset, a CSV path, or the built-in simulator."""

    source: str | None = None           # "belsten2023" | "simulated"
    path: str | None = None             # canonical CSV (or mapped with `columns`)
    temperature_unit: str = "C"
    field_unit: str | None = None       # declared unit of the file's field (nT/mT/G converted; uT trusted); None: uT, checked
    time_unit: str = "s"                # unit of the file's time column (ms, us, min, h converted to seconds)
    columns: dict = dataclasses.field(default_factory=dict)
    simulate: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class SplitConfig:
    kind: str = "random"                # random | by_run | time_blocks | none
    test_fraction: float = 0.1
    seed: int = 0
    test_runs: list = dataclasses.field(default_factory=list)
    n_blocks: int = 1


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    t0: Union[float, str] = T0_DEFAULT  # reference temperature (C), or "mean" (training mean; the one default)
    temperature_terms: bool = True
    extra_terms: list = dataclasses.field(default_factory=list)
    covariance: str = "white"           # white | ar1 | newey_west


@dataclasses.dataclass(frozen=True)
class UQConfig:
    method: str = "auto"                # auto (analytic where exact, else psqmc) | psqmc | mc | analytic
    n_params: int = 500
    n_qmc: int = 1000
    sigma_in: Union[str, list] = "auto"  # "auto", [sd_bx, sd_by, sd_bz, sd_T], or a 4x4 covariance
    level: float = 0.95
    seed: int = 0
    chunk_size: int = 256
    residual_term: bool = True          # add the fit's unexplained residual variance (false = the paper's total)
    transfer: str = "loro"              # between-session sd for new recordings: "loro" (leave one run out) | "hierarchical" (per-run random effects, Laplace; docs/sessions.md) | "hierarchical_nuts" (the same by NUTS) | "off"
    reference_sd: Union[float, list] = 0.0   # the reference magnetometer's own standard uncertainty, uT (or per axis)
    transfer_likelihood: str = "gaussian"    # hierarchical transfer: "gaussian" | "student_t" | "laplace" (per run, docs/sessions.md)
    transfer_df: Union[float, str] = 4.0     # its Student-t degrees of freedom (> 2), or "learned" (a posterior over a grid)
    transfer_uninformed: str = "pooled"      # hierarchical: effects < 3 runs inform: "pooled" (as the learned ones) | "prior" | "fixed" (no change)
    transfer_networks: str = "none"          # "by_run_folds": the hybrid transfer part includes the network's own new-session error (docs/sessions.md)
    transfer_check: str = "loro"             # hierarchical: an axis whose model spread is > 2x leave-one-run-out's uses loro's sd ("loro") or only warns ("warn")


@dataclasses.dataclass(frozen=True)
class NetworkConfig(S.NetworkSettings):
    """``[network]``: the library's :class:`~bayesmag._src.pipeline.settings.NetworkSettings` (names,
    defaults and checks written once, there) plus the job's switch ``enabled`` (``false`` runs the
    physics stage only)."""

    #: spec fields set per network by the job, not by the table
    internal: ClassVar[tuple[str, ...]] = ("likelihood", "n_in")
    #: spec settings whose job default differs from the library's NetworkSpec (honest by default, issue #13)
    job_defaults: ClassVar[tuple[str, ...]] = ("validation",)

    enabled: bool = False
    likelihoods: list = dataclasses.field(default_factory=lambda: ["gaussian"])

    def settings(self) -> S.NetworkSettings:
        """The library settings (no ``enabled`` switch)."""
        kw = {f.name: getattr(self, f.name) for f in dataclasses.fields(S.NetworkSettings)}
        return S.NetworkSettings(**{**kw, "likelihoods": tuple(self.likelihoods)})

    def table(self) -> dict:
        """The ``[network]`` table (no internal fields)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in self.internal}


@dataclasses.dataclass(frozen=True)
class NutsConfig:
    """Full-Bayesian cross-check of the physics posterior with NumPyro NUTS."""

    enabled: bool = False
    chains: int = 4
    warmup: int = 1000
    draws: int = 1000
    target_accept: float = 0.8
    chain_method: str = "vectorized"    # vectorized | parallel | sequential
    likelihood: str = "gaussian"        # observation model: a family of bayesmag.likelihoods
    priors: dict = dataclasses.field(default_factory=dict)
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class StudyConfig:
    """The simulation study (``bayesmag study``): one simulated data set per size."""

    sizes: list = dataclasses.field(default_factory=lambda: [50000, 100000, 200000, 500000])
    #: per-size [network] overrides, e.g. {"500000" = {batch_size = 2048, max_epochs = 40}}
    per_size: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class CertificateConfig:
    """``[certificate]``: who and what the certificate (``report.md``) names; one line of text each."""

    dut: str = ""                       # device under test: make, model, serial number
    reference: str = ""                 # reference instrument: make, model, serial, its own certificate
    operator: str = ""                  # who ran the calibration (optional)


@dataclasses.dataclass(frozen=True)
class OutputConfig:
    figures: bool = True
    progress: bool = True
    compile_cache: Union[bool, str] = "auto"   # JAX persistent compilation cache (cache.py): "auto" = on from the
                                                # command line, the caller's setting from Python; true / false for this job


@dataclasses.dataclass(frozen=True)
class MeasurementConfig:
    """``[measurement]``: what the recording knows about the true field (docs/field.md). ``kind = "vector"``
    is the reference-magnetometer calibration; ``scalar`` and ``constant`` run the field calibration."""

    kind: str = "vector"                # vector | scalar | constant
    field: Union[float, str] = "free"   # constant: the site's field magnitude in uT (e.g. IGRF/WMM), or "free"
    scalar_column: str = ""             # scalar with data.path: the CSV column of the reference magnitude per row, uT
    reference_sd: float = 0.0           # scalar: the reference magnitude's own noise sd, uT (0: negligible)
    temperature_terms: Union[bool, str] = "auto"   # "auto": on when the training temperature spans >= 1 C
    covariance: str = "white"           # white | ar1 (residual autocorrelation)
    min_magnitude: float = 0.0          # drop rows whose reference magnitude is below this (a scalar sensor's range), uT
    interval_calibration: str = "conformal"   # magnitude intervals: "conformal" (scale from time-block folds) | "none"
    conformal_folds: int = 5            # at most this many cross-conformal folds (refits) of the training rows
    heading_check: bool = True          # simulated campaigns: heading error on the level test rows
    compare_vector: bool = True         # with a vector reference in the data: compare the 18 invariants
    exports: list = dataclasses.field(default_factory=lambda: ["json", "c-header", "magcal", "px4", "ardupilot"])
    simulate: dict = dataclasses.field(default_factory=dict)   # data.source = "field_simulated": simulate_field args


@dataclasses.dataclass(frozen=True)
class Config:
    """A whole job: data, split, physics, uncertainty, network and output settings."""

    name: str = "bayesmag"
    data: DataConfig = dataclasses.field(default_factory=DataConfig)
    split: SplitConfig = dataclasses.field(default_factory=SplitConfig)
    physics: PhysicsConfig = dataclasses.field(default_factory=PhysicsConfig)
    uq: UQConfig = dataclasses.field(default_factory=UQConfig)
    network: NetworkConfig = dataclasses.field(default_factory=NetworkConfig)
    nuts: NutsConfig = dataclasses.field(default_factory=NutsConfig)
    discover: dict = dataclasses.field(default_factory=dict)   # validated by bayesmag discover (DiscoverOptions)
    study: StudyConfig = dataclasses.field(default_factory=StudyConfig)
    output: OutputConfig = dataclasses.field(default_factory=OutputConfig)
    certificate: CertificateConfig = dataclasses.field(default_factory=CertificateConfig)
    measurement: MeasurementConfig = dataclasses.field(default_factory=MeasurementConfig)

    def settings(self, *, nuts_priors=None) -> S.CalibrationSettings:
        """The library settings of this job (:func:`~bayesmag.calibrate`): physics, UQ, the network
        (when enabled, with its cross-conformal plan from ``[split]``) and NUTS (when enabled, with
        ``nuts_priors`` parsed by :func:`~bayesmag.parse_priors`)."""
        from bayesmag._src.pipeline.conformal import conformal_plan

        p, u = self.physics, self.uq
        physics = S.PhysicsSettings(t0=p.t0, temperature_terms=p.temperature_terms,
                                    extra_terms=tuple(p.extra_terms), covariance=p.covariance)
        uq = S.UQSettings(method=u.method, n_params=u.n_params, n_qmc=u.n_qmc, sigma_in=u.sigma_in, level=u.level,
                          seed=u.seed, chunk_size=u.chunk_size, residual_term=u.residual_term, transfer=u.transfer,
                          reference_sd=u.reference_sd, transfer_likelihood=u.transfer_likelihood,
                          transfer_df=u.transfer_df, transfer_uninformed=u.transfer_uninformed,
                          transfer_networks=u.transfer_networks, transfer_check=u.transfer_check)
        network = conformal = nuts = None
        if self.network.enabled:
            network = self.network.settings()
            if network.interval_calibration == "conformal":
                conformal = S.ConformalPlan(*conformal_plan(self.split, network))
        if self.nuts.enabled:
            n = self.nuts
            nuts = S.NutsSettings(chains=n.chains, warmup=n.warmup, draws=n.draws, target_accept=n.target_accept,
                                  chain_method=n.chain_method, likelihood=n.likelihood, priors=nuts_priors, seed=n.seed)
        return S.CalibrationSettings(physics=physics, uq=uq, network=network, nuts=nuts, conformal=conformal)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["network"] = dataclasses.asdict(self.network)
        for k in NetworkConfig.internal:
            d["network"].pop(k)
        return d


_CHOICES = {
    "split.kind": ("random", "by_run", "time_blocks", "none"),
    "physics.covariance": S.COVARIANCES,
    "uq.method": S.UQ_METHODS,
    "data.temperature_unit": ("C", "K"),
    "data.time_unit": tuple(TIME_UNITS),
    "data.field_unit": ("uT", "nT", "mT", "G"),
    "network.interval_calibration": S.INTERVAL_CALIBRATIONS,
    "uq.transfer": S.TRANSFER_METHODS,
    "uq.transfer_likelihood": S.TRANSFER_LIKELIHOODS,
    "uq.transfer_uninformed": S.TRANSFER_UNINFORMED,
    "uq.transfer_networks": S.TRANSFER_NETWORKS,
    "uq.transfer_check": S.TRANSFER_CHECKS,
    "measurement.kind": ("vector", "scalar", "constant"),
    "measurement.covariance": ("white", "ar1"),
    "measurement.interval_calibration": ("conformal", "none"),
}


def _choices(path: str) -> tuple | None:
    """The valid values of a key: the library's own lists (registries are read when asked, so a
    family or activation registered after import is valid too)."""
    if path in _CHOICES:
        return _CHOICES[path]
    if path == "network.activation":
        return tuple(ACTIVATIONS)
    if path == "network.validation":
        return VALIDATION_KINDS
    if path == "network.fusion":
        return FUSIONS
    if path == "nuts.chain_method":
        from bayesmag._src.pipeline.nuts import CHAIN_METHODS
        return CHAIN_METHODS
    if path == "nuts.likelihood":
        return tuple(LIKELIHOODS)
    return None


def config_error(e: Exception, section: str, keys=()) -> ConfigError:
    """A library ``ValueError`` as a :class:`ConfigError` naming the key path in ``[section]``.

    The library names its own parameters (``width = 0 must be at least 1``, ``Lower 'width'``);
    a message that starts with a known key becomes ``Config key 'section.key' = ...`` and
    quoted keys become ``'section.key'``; anything else is prefixed with ``[section]``.
    """
    msg = str(e)
    keys = sorted(set(keys), key=len, reverse=True)
    for k in keys:
        msg = msg.replace(f"'{k}'", f"'{section}.{k}'")
    m = re.match(r"([A-Za-z_][\w.\[\]'\"]*) = ", msg)
    if m and m.group(1).split(".")[0].split("[")[0] in keys:
        return ConfigError(f"Config key '{section}.{m.group(1)}' = {msg[m.end():]}")
    if m and not keys:
        return ConfigError(f"Config key '{section}.{m.group(1)}' = {msg[m.end():]}")
    first = re.match(r"(\w+)\b", msg)
    if first and first.group(1) in keys:
        return ConfigError(f"Config key '{section}.{first.group(1)}'{msg[first.end():]}")
    return ConfigError(f"[{section}] {msg}")


def _type_ok(value: Any, tp: Any) -> bool:
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        return any(_type_ok(value, a) for a in typing.get_args(tp))
    if tp is type(None):
        return value is None
    if tp is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp in (str, bool, list, dict):
        return isinstance(value, tp)
    return True


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    return "none" if tp is type(None) else getattr(tp, "__name__", str(tp))


def _build(cls, raw: dict, prefix: str):
    if not isinstance(raw, dict):
        raise ConfigError(f"[{prefix}] must be a table; got {raw!r}.")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.name not in getattr(cls, "internal", ())}
    kwargs = {}
    for key, value in raw.items():
        path = f"{prefix}.{key}" if prefix else key
        if key not in fields:
            raise ConfigError(f"Unknown config key '{path}'. Valid keys{' in [' + prefix + ']' if prefix else ''}: "
                              f"{sorted(fields)}.")
        tp = hints[key]
        if dataclasses.is_dataclass(tp):
            kwargs[key] = _build(tp, value, path)
            continue
        if not _type_ok(value, tp):
            raise ConfigError(f"Config key '{path}' = {value!r} has the wrong type: expected {_type_name(tp)}.")
        choices = _choices(path)
        if choices is not None and value not in choices:
            raise ConfigError(f"Config key '{path}' = {value!r} is not valid; it must be one of {list(choices)}.")
        kwargs[key] = float(value) if tp is float else value
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except ValueError as e:            # the library's own check, e.g. NetworkSpec: name the key path
        raise config_error(e, prefix, fields) from None


#: Smallest valid value of integer keys (a seed is a non-negative integer; counts and sizes are positive).
_INT_MIN = {
    "split.seed": 0, "split.n_blocks": 1, "uq.seed": 0, "uq.chunk_size": 1, "uq.n_params": 2, "uq.n_qmc": 2,
    "network.seed": 0, "network.hidden_layers": 0, "network.width": 1, "network.batch_size": 1,
    "network.max_epochs": 1, "network.patience": 1, "network.mc_passes": 1, "network.lr_plateau_patience": 1,
    "network.fourier_features": 0, "nuts.seed": 0, "nuts.chains": 1, "nuts.warmup": 0, "nuts.draws": 1,
}


def _numbers(x):
    if isinstance(x, bool):
        return
    if isinstance(x, (int, float)):
        yield x
    elif isinstance(x, (list, tuple)):
        for v in x:
            yield from _numbers(v)


def _check_numbers(cfg: Config) -> None:
    """Every number in a section is finite; integer keys respect :data:`_INT_MIN`."""
    for section in ("split", "physics", "uq", "network", "nuts", "output"):
        block = getattr(cfg, section)
        for f in dataclasses.fields(block):
            key, value = f"{section}.{f.name}", getattr(block, f.name)
            if any(not math.isfinite(v) for v in _numbers(value)):
                raise ConfigError(f"Config key '{key}' = {value!r} must be finite (no nan or inf).")
            lo = _INT_MIN.get(key)
            if lo is not None and value < lo:
                raise ConfigError(f"Config key '{key}' = {value!r} must be at least {lo}.")


def _check_measurement(m: MeasurementConfig) -> None:
    if isinstance(m.field, str) and m.field != "free":
        raise ConfigError(f"Config key 'measurement.field' = {m.field!r} must be a magnitude in uT or \"free\".")
    if not isinstance(m.field, str) and not 0 < m.field < 1e6:
        raise ConfigError(f"Config key 'measurement.field' = {m.field!r} must be a positive magnitude in uT.")
    if not isinstance(m.field, str):
        try:                          # the same plausibility check as the library's (nT or gauss typed as uT)
            from bayesmag._src.core.measurement import measurement_from_spec
            measurement_from_spec("constant", m.field)
        except ValueError as e:
            raise ConfigError(f"Config key 'measurement.field': {e}") from None
    if isinstance(m.temperature_terms, str) and m.temperature_terms != "auto":
        raise ConfigError(f"Config key 'measurement.temperature_terms' = {m.temperature_terms!r} must be true, "
                          "false or \"auto\".")
    if m.min_magnitude < 0:
        raise ConfigError(f"Config key 'measurement.min_magnitude' = {m.min_magnitude} must be >= 0 uT.")
    if m.conformal_folds < 2:
        raise ConfigError(f"Config key 'measurement.conformal_folds' = {m.conformal_folds} must be at least 2.")
    if not 0 <= m.reference_sd < 1e3:
        raise ConfigError(f"Config key 'measurement.reference_sd' = {m.reference_sd} must be a noise sd >= 0 uT.")
    if m.reference_sd and m.kind != "scalar":
        raise ConfigError(f"Config key 'measurement.reference_sd' = {m.reference_sd} is only read by kind = \"scalar\" "
                          f"(kind is {m.kind!r}); remove it or set measurement.kind = \"scalar\".")
    if m.scalar_column and m.kind != "scalar":
        raise ConfigError(f"Config key 'measurement.scalar_column' = {m.scalar_column!r} is only read by "
                          f"kind = \"scalar\" (kind is {m.kind!r}); remove it or set measurement.kind = \"scalar\".")
    from bayesmag._src.app.formats import FORMATS
    bad = [f for f in m.exports if f not in FORMATS]
    if bad:
        raise ConfigError(f"Config key 'measurement.exports' has unknown format(s) {bad}; valid: {list(FORMATS)}.")
_MAX_SD, _MAX_REFERENCE_SD = S.MAX_SD, S.MAX_REFERENCE_SD        # larger sds are typos


#: ``uq.transfer`` of a field calibration: leave one run out on the magnitude, or none.
FIELD_TRANSFER_METHODS = ("loro", "off")

#: Keys of a vector calibration that a field calibration (``[measurement] kind`` "constant" / "scalar") does not
#: read, with the key it reads instead (None: nothing does). A value other than the default is refused: it was
#: silently ignored (``physics.temperature_terms = false`` still fitted thermal terms; ``uq.reference_sd`` left the
#: scalar fit unweighted, the key read is ``measurement.reference_sd``).
_FIELD_INSTEAD = {
    "physics.temperature_terms": "measurement.temperature_terms", "physics.covariance": "measurement.covariance",
    "physics.extra_terms": None, "uq.reference_sd": "measurement.reference_sd", "uq.method": None,
    "uq.n_params": None, "uq.n_qmc": None, "uq.sigma_in": None, "uq.residual_term": None, "uq.chunk_size": None,
    "uq.transfer_df": None, "uq.transfer_uninformed": None, "uq.transfer_check": None, "network.enabled": None,
}


def _refuse_vector_keys(cfg: Config) -> None:
    defaults = {"physics": PhysicsConfig(), "uq": UQConfig(), "network": NetworkConfig()}
    bad = [k for k in _FIELD_INSTEAD
           if getattr(getattr(cfg, k.split(".")[0]), k.split(".")[1]) != getattr(defaults[k.split(".")[0]],
                                                                                    k.split(".")[1])]
    if bad:
        instead = [f"{_FIELD_INSTEAD[k]} instead of {k}" for k in bad if _FIELD_INSTEAD[k]]
        raise ConfigError(f"Config key(s) {bad} belong to a vector calibration; a field calibration (measurement.kind "
                          f"= {cfg.measurement.kind!r}) does not read them (its uncertainty is the Laplace posterior of "
                          f"the magnitude fit, its model the thermo-affine one, no network; docs/field.md)"
                          + (f". Set {', '.join(instead)}" if instead else "") + ". Remove them.")


def _check_semantics(cfg: Config) -> None:
    _check_numbers(cfg)
    _check_measurement(cfg.measurement)
    if isinstance(cfg.output.compile_cache, str) and cfg.output.compile_cache != "auto":
        raise ConfigError(f"Config key 'output.compile_cache' = {cfg.output.compile_cache!r} must be true, false or \"auto\".")
    if cfg.measurement.scalar_column and cfg.data.path is None:
        raise ConfigError(f"Config key 'measurement.scalar_column' = {cfg.measurement.scalar_column!r} names a CSV "
                          "column, but [data] names no 'path'; give data.path (a CSV with that column).")
    field_job = cfg.measurement.kind != "vector" or cfg.data.source == "field_simulated"
    if field_job:                           # keys the field job does not read are refused, not silently dropped
        if cfg.uq.transfer not in FIELD_TRANSFER_METHODS:
            raise ConfigError(f"Config key 'uq.transfer' = {cfg.uq.transfer!r}: a field calibration (measurement.kind "
                              f"= {cfg.measurement.kind!r}) estimates its between-session term by leave-one-run-out "
                              f"of the magnitude; valid: {list(FIELD_TRANSFER_METHODS)} (the session model is the "
                              f"vector calibration's, docs/field.md).")
        unused = [f"uq.{k}" for k, default in (("transfer_likelihood", "gaussian"), ("transfer_networks", "none"))
                  if getattr(cfg.uq, k) != default]
        if unused:
            raise ConfigError(f"Config key(s) {unused} set a vector calibration's between-session (transfer) model; "
                              f"a field calibration (measurement.kind = {cfg.measurement.kind!r}) does not read them "
                              f"(its term is uq.transfer = \"loro\" or \"off\", docs/field.md). Remove them.")
        _refuse_vector_keys(cfg)
    elif not str(cfg.uq.transfer).startswith("hierarchical"):    # read by the session model only: never ignored
        unused = [f"uq.{k}" for k, default in (("transfer_likelihood", "gaussian"), ("transfer_df", 4.0),
                                               ("transfer_uninformed", "pooled"), ("transfer_check", "loro"))
                  if getattr(cfg.uq, k) != default]
        if unused:
            raise ConfigError(f"Config key(s) {unused} set the hierarchical session model; uq.transfer = "
                              f"{cfg.uq.transfer!r} does not read them (they apply with uq.transfer = \"hierarchical\" "
                              f"or \"hierarchical_nuts\"). Remove them, or set uq.transfer = \"hierarchical\".")
    d = cfg.data
    if d.source is not None and d.path is not None:
        raise ConfigError("[data] names both 'source' and 'path'; give one.")
    if d.source is None and d.path is None:
        raise ConfigError("[data] needs 'source' (\"belsten2023\" or \"simulated\") or 'path' (a CSV file).")
    if not 0 < cfg.split.test_fraction < 1:
        raise ConfigError(f"Config key 'split.test_fraction' = {cfg.split.test_fraction} must be in (0, 1).")
    if cfg.uq.n_params < 2 or cfg.uq.n_qmc < 2:
        raise ConfigError("Config keys 'uq.n_params' and 'uq.n_qmc' must be at least 2.")
    if not 0 < cfg.uq.level < 1:
        raise ConfigError(f"Config key 'uq.level' = {cfg.uq.level} must be in (0, 1).")
    if isinstance(cfg.physics.t0, str) and cfg.physics.t0 != "mean":
        raise ConfigError(f"Config key 'physics.t0' = {cfg.physics.t0!r} must be a number or \"mean\".")
    if not isinstance(cfg.physics.t0, str) and not (-273.15 <= float(cfg.physics.t0) <= 1000.0):
        raise ConfigError(f"Config key 'physics.t0' = {cfg.physics.t0!r} is not a reference temperature in C (it must "
                          f"lie in [-273.15, 1000]); use the calibration's typical temperature, or \"mean\" (the "
                          f"training mean).")
    s = cfg.uq.sigma_in
    if isinstance(s, str) and s != "auto":
        raise ConfigError(f"Config key 'uq.sigma_in' = {s!r} must be \"auto\", 4 standard deviations or a 4x4 matrix.")
    if isinstance(s, list) and not (len(s) == 4 and (all(isinstance(v, (int, float)) for v in s)
                                                     or all(isinstance(r, list) and len(r) == 4 for r in s))):
        raise ConfigError("Config key 'uq.sigma_in' must be 4 standard deviations [Bx, By, Bz, T] or a 4x4 matrix.")
    for key in ("dut", "reference", "operator"):
        v = getattr(cfg.certificate, key)
        if "\n" in v or "\r" in v or len(v) > 200:
            raise ConfigError(f"Config key 'certificate.{key}' = {v[:60]!r}... must be one line of at most 200 "
                              f"characters (e.g. \"Acme AMR-3 s/n 0042\").")
    if isinstance(s, list) and all(isinstance(v, (int, float)) for v in s):
        bad = [v for v in s if isinstance(v, bool) or not 0 <= v <= _MAX_SD]
        if bad:
            raise ConfigError(f"Config key 'uq.sigma_in' = {s!r} holds {bad[0]!r}: each standard deviation "
                              f"[Bx, By, Bz (uT), T (C)] must be >= 0 and at most {_MAX_SD:g}.")
    tdf = cfg.uq.transfer_df
    if tdf != "learned" and (isinstance(tdf, bool) or not isinstance(tdf, (int, float)) or not 2 < tdf < 1e6):
        raise ConfigError(f"Config key 'uq.transfer_df' = {tdf!r} must be a number > 2 (Student-t degrees of freedom "
                          "with a finite variance; e.g. 4) or \"learned\".")
    if tdf == "learned" and cfg.uq.transfer == "hierarchical_nuts" and cfg.uq.transfer_likelihood == "student_t":
        raise ConfigError("Config key 'uq.transfer_df' = \"learned\" is fitted on the Laplace path only: set "
                          "uq.transfer = \"hierarchical\" or give uq.transfer_df a number > 2.")
    if cfg.uq.transfer.startswith("hierarchical"):
        from bayesmag._src.core.catalogue import CATALOGUE
        names = [e if isinstance(e, str) else e.get("name") if isinstance(e, dict) else None
                 for e in cfg.physics.extra_terms]
        bound = [n for n in names if n in CATALOGUE and getattr(CATALOGUE[n], "localised", None) == "run"]
        if bound:
            raise ConfigError(f"Config key 'physics.extra_terms' holds {bound[0]!r}, which fits offsets of particular "
                              f"training runs as fixed parameters; uq.transfer = {cfg.uq.transfer!r} models every "
                              f"run's offset as a random effect. Use one: drop {bound[0]!r}, or set "
                              f"uq.transfer = \"loro\".")
    if cfg.uq.transfer_networks == "by_run_folds" and (cfg.uq.transfer == "off" or not cfg.network.enabled):
        raise ConfigError("Config key 'uq.transfer_networks' = \"by_run_folds\" adds the network's new-session error to "
                          "the hybrid transfer part: it needs network.enabled = true and uq.transfer other than \"off\" "
                          f"(got {cfg.network.enabled} and {cfg.uq.transfer!r}); set it to \"none\" or change those.")
    r = cfg.uq.reference_sd
    if not (isinstance(r, (int, float)) and r >= 0 or isinstance(r, list) and len(r) == 3
            and all(isinstance(v, (int, float)) and v >= 0 for v in r)):
        raise ConfigError(f"Config key 'uq.reference_sd' = {r!r} must be a standard uncertainty >= 0 in uT, or 3 of them.")
    if any(v > _MAX_REFERENCE_SD for v in (r if isinstance(r, list) else [r])):
        raise ConfigError(f"Config key 'uq.reference_sd' = {r!r} is not a plausible standard uncertainty of a "
                          f"reference magnetometer: it must be at most {_MAX_REFERENCE_SD:g} uT (typical: 0.001-1).")
    if d.source == "simulated":
        from bayesmag._src.core.simulate import check_simulate_config
        try:
            check_simulate_config(d.simulate)
        except (ValueError, TypeError) as e:
            raise ConfigError(f"[data.simulate] {e}") from None


def config_from_dict(raw: dict) -> Config:
    """Validate a plain dict (parsed TOML) into a :class:`Config`."""
    cfg = _build(Config, raw, "")
    _check_semantics(cfg)
    return cfg


def _parse_value(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_overrides(raw: dict, overrides: list[str]) -> dict:
    """Apply ``key.sub=value`` overrides to a raw config dict (returns a new dict)."""
    raw = copy.deepcopy(raw)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"--set {item!r} must look like key=value, e.g. --set uq.n_params=100.")
        key, text = item.split("=", 1)
        parts = key.strip().split(".")
        node = raw
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {key}: '{p}' is not a table.")
        node[parts[-1]] = _parse_value(text.strip())
        if parts == ["data", "path"]:
            raw["data"].pop("source", None)          # a path replaces any named source
            raw["data"].pop("simulate", None)
        if parts == ["data", "source"]:
            raw["data"].pop("path", None)
    return raw


def read_config_dict(path: str | Path, overrides: list[str] = ()) -> dict:
    """The raw TOML dict of a config file with ``--set`` overrides applied (data paths made relative to it)."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"Config file {path} does not exist.")
    if path.is_dir():
        raise ConfigError(f"Config {path} is a folder; give a TOML config file (e.g. configs/quickstart.toml).")
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except UnicodeDecodeError:
        raise ConfigError(f"Config {path} is not a text file (not UTF-8); give a TOML config file.") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path} is not valid TOML: {e}") from None
    raw = apply_overrides(raw, list(overrides))
    data = raw.get("data", {})
    if isinstance(data, dict) and data.get("path"):
        p = Path(data["path"]).expanduser()
        if not p.is_absolute() and not p.exists() and (path.parent / p).exists():
            data["path"] = str(path.parent / p)   # relative to the config file
    return raw


def packaged_configs_dir() -> Path:
    """The shipped configs: ``bayesmag/configs`` when installed, the repository's ``configs/`` in a checkout."""
    here = Path(__file__).resolve().parents[2]     # bayesmag/_src/app/config.py -> bayesmag/
    for d in (here / "configs", here.parent / "configs"):
        if d.is_dir() and any(d.glob("*.toml")):
            return d
    return here / "configs"


def resolve_config_path(name: str) -> Path:
    """A config file: the path itself, else a packaged config of that name (``"paper_physics"``)."""
    p = Path(name)
    if p.exists():
        return p
    packaged = packaged_configs_dir() / f"{Path(name).name.removesuffix('.toml')}.toml"
    if packaged.exists():
        return packaged
    names = sorted(x.stem for x in packaged_configs_dir().glob("*.toml"))
    raise ConfigError(f"Config file {name} does not exist, and it is not a packaged config; those are: "
                      f"{', '.join(names)}.")


def load_config(path: str | Path, overrides: list[str] = ()) -> Config:
    """Read a TOML config (a path, or a packaged config's name as ``bayesmag run`` takes it: ``"quickstart"``),
    apply ``--set`` overrides and validate it."""
    return config_from_dict(read_config_dict(resolve_config_path(str(path)), overrides))


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {v!r} to TOML")


def to_toml(d: dict, _prefix: str = "") -> str:
    """A small TOML writer for resolved configs (tables, scalars, lists, inline dicts); None is omitted."""
    lines, tables = [], []
    for k, v in d.items():
        if v is None:
            continue
        if isinstance(v, dict) and v and all(not isinstance(x, dict) or True for x in v.values()) and _prefix == "":
            tables.append((k, v))
        else:
            lines.append(f"{k} = {_toml_value(v)}")
    out = "\n".join(lines)
    for k, v in tables:
        body = "\n".join(f"{kk} = {_toml_value(vv)}" for kk, vv in v.items() if vv is not None)
        out += f"\n\n[{k}]\n{body}"
    return out.strip() + "\n"
