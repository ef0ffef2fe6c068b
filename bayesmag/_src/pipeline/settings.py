"""The library's settings for :func:`~bayesmag.calibrate`: plain frozen values, no TOML.

The application's config (``bayesmag._src.app.config``) converts its tables into these
(:meth:`~bayesmag.Config.settings`); a script builds them directly::

    >>> s = CalibrationSettings(physics=PhysicsSettings(t0=0.0), uq=UQSettings(method="analytic"))
    >>> s.network is None and s.nuts is None
    True

Every default is written once, here (the config's defaults are these ones).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Union

import numpy as np

from bayesmag._src.core.data import AXES
from bayesmag._src.core.likelihoods import LIKELIHOODS
from bayesmag._src.core.network import NetworkSpec
from bayesmag._src.core.physics import T0_DEFAULT, PhysicsModel, resolve_t0
from bayesmag._src.core.predictor import FUSIONS, UQOptions

__all__ = ["PhysicsSettings", "UQSettings", "sigma_in_matrix", "NetworkSettings", "NutsSettings", "ConformalPlan", "CalibrationSettings",
           "COVARIANCES", "UQ_METHODS", "TRANSFER_METHODS", "TRANSFER_LIKELIHOODS", "TRANSFER_UNINFORMED", "TRANSFER_CHECKS",
           "TRANSFER_NETWORKS", "INTERVAL_CALIBRATIONS"]

COVARIANCES = ("white", "ar1", "newey_west")
UQ_METHODS = ("auto", "psqmc", "mc", "analytic")
TRANSFER_METHODS = ("loro", "hierarchical", "hierarchical_nuts", "off")
TRANSFER_LIKELIHOODS = ("gaussian", "student_t", "laplace")
TRANSFER_UNINFORMED = ("pooled", "prior", "fixed")
TRANSFER_CHECKS = ("loro", "warn")
TRANSFER_NETWORKS = ("none", "by_run_folds")
#: Largest plausible input-noise sd (uT or C) and reference-magnetometer sd (uT); larger ones are typos.
MAX_SD = 1e4
MAX_REFERENCE_SD = 1e3


def _one_of(name: str, value, valid) -> None:
    if not isinstance(value, str) or value not in valid:
        raise ValueError(f"{name} = {value!r} is not valid; it must be one of {list(valid)}.")


def _number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def _at_least(name: str, value, lo: int) -> None:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < lo:
        raise ValueError(f"{name} = {value!r} must be an integer of at least {lo}.")
INTERVAL_CALIBRATIONS = ("conformal", "none")


@dataclasses.dataclass(frozen=True)
class PhysicsSettings:
    """The physics model and its fit.

    ``t0``: reference temperature (C) of the thermal terms, or ``"mean"`` (the default,
    :data:`~bayesmag._src.core.physics.T0_DEFAULT`): the training rows' mean, resolved once by
    :meth:`model` (:func:`~bayesmag._src.core.physics.resolve_t0`); ``extra_terms``: catalogue
    names or ``{name = ..., field = value}`` tables (:func:`~bayesmag._src.core.catalogue.make_extra`);
    ``covariance``: ``"white"``, ``"ar1"`` or ``"newey_west"``.
    """

    t0: Union[float, str] = T0_DEFAULT
    temperature_terms: bool = True
    extra_terms: tuple = ()
    covariance: str = "white"

    def __post_init__(self):
        """The checks of the config's ``[physics]`` keys, so a script's settings are refused as a config's are."""
        if isinstance(self.t0, str):
            if self.t0 != "mean":
                raise ValueError(f"t0 = {self.t0!r} must be a number (C) or \"mean\".")
        elif not _number(self.t0) or not -273.15 <= float(self.t0) <= 1000.0:
            raise ValueError(f"t0 = {self.t0!r} is not a reference temperature in C (it must lie in [-273.15, 1000]); "
                             f"use the calibration's typical temperature, or \"mean\" (the training mean).")
        _one_of("covariance", self.covariance, COVARIANCES)

    def model(self, train) -> PhysicsModel:
        """The physics model for the training rows ``train`` (T0 resolved here, once).

        Raises:
            ValueError: an unknown or badly specified extra term (the message names it).
        """
        from bayesmag._src.core.catalogue import make_extra

        t0 = resolve_t0(self.t0, train.temperature)
        extra = tuple(make_extra(s, t0=t0) for s in self.extra_terms)
        return PhysicsModel.paper(t0=t0, temperature=self.temperature_terms, extra=extra)


@dataclasses.dataclass(frozen=True)
class UQSettings:
    """How the physics uncertainty is propagated and composed.

    ``method``/``n_params``/``n_qmc``/``seed``/``chunk_size``: :func:`~bayesmag.physics_uncertainty`
    (``"auto"`` by default, :data:`~bayesmag._src.core.physics_uq.DEFAULT_METHOD`: the one default
    method wherever bayesmag predicts); ``sigma_in``:
    ``"auto"`` (estimated from the training rows), 4 standard deviations ``[bx, by, bz, T]`` or a
    4x4 covariance; ``level``: the central interval's level; ``residual_term``: add the fit's
    residual variance beyond the input noise; ``transfer``: ``"loro"`` (leave one run out),
    ``"hierarchical"`` / ``"hierarchical_nuts"`` (per-run random effects, docs/sessions.md) or ``"off"``; ``reference_sd``: the reference's own standard uncertainty (uT, or 3 of them);
    ``transfer_likelihood`` / ``transfer_df``: the hierarchical model's likelihood, ``"gaussian"``,
    ``"student_t"`` with ``transfer_df`` dof (or ``"learned"``: a posterior on a grid) or ``"laplace"``; ``transfer_uninformed``: ``"pooled"``, ``"prior"`` or ``"fixed"``
    (:func:`~bayesmag._src.pipeline.sessions.hierarchical.with_prior_effects`); ``transfer_check``: ``"loro"`` (an axis
    where the session model's spread is more than twice leave-one-run-out's uses loro's sd) or ``"warn"``
    (:func:`~bayesmag._src.pipeline.sessions.hierarchical.hierarchical_transfer`); ``transfer_networks``:
    ``"none"`` or ``"by_run_folds"`` (the hybrid transfer part includes the network's own new-session error,
    :mod:`~bayesmag._src.pipeline.network_transfer`).
    """

    method: str = UQOptions.method
    n_params: int = UQOptions.n_params
    n_qmc: int = UQOptions.n_qmc
    sigma_in: Union[str, Any] = "auto"
    level: float = 0.95
    seed: int = UQOptions.seed
    chunk_size: int = UQOptions.chunk_size
    residual_term: bool = True
    transfer: str = "loro"
    reference_sd: Union[float, Any] = 0.0
    transfer_likelihood: str = "gaussian"
    transfer_df: Union[float, str] = 4.0
    transfer_uninformed: str = "pooled"
    transfer_networks: str = "none"
    transfer_check: str = "loro"

    def __post_init__(self):
        """The checks of the config's ``[uq]`` keys, so a script's settings are refused as a config's are (a
        misspelled ``transfer`` gave no between-session term and intervals 85-93 % instead of 95 %)."""
        _one_of("method", self.method, UQ_METHODS)
        _one_of("transfer", self.transfer, TRANSFER_METHODS)
        _one_of("transfer_likelihood", self.transfer_likelihood, TRANSFER_LIKELIHOODS)
        _one_of("transfer_uninformed", self.transfer_uninformed, TRANSFER_UNINFORMED)
        _one_of("transfer_check", self.transfer_check, TRANSFER_CHECKS)
        _one_of("transfer_networks", self.transfer_networks, TRANSFER_NETWORKS)
        if not _number(self.level) or not 0 < self.level < 1:
            raise ValueError(f"level = {self.level!r} must be in (0, 1), e.g. 0.95.")
        for name, lo in (("n_params", 2), ("n_qmc", 2), ("seed", 0), ("chunk_size", 1)):
            _at_least(name, getattr(self, name), lo)
        tdf = self.transfer_df
        if tdf != "learned" and (not _number(tdf) or not 2 < tdf < 1e6):
            raise ValueError(f"transfer_df = {tdf!r} must be a number > 2 (Student-t degrees of freedom with a finite "
                             f"variance; e.g. 4) or \"learned\".")
        sig = self.sigma_in
        if isinstance(sig, str):
            if sig != "auto":
                raise ValueError(f"sigma_in = {sig!r} must be \"auto\", 4 standard deviations [Bx, By, Bz, T] or a "
                                 f"4x4 covariance.")
        else:
            arr = np.asarray(sig, dtype=object)
            if arr.shape not in ((4,), (4, 4)) or not all(_number(v) and np.isfinite(v) for v in arr.ravel()):
                raise ValueError(f"sigma_in = {sig!r} must be \"auto\", 4 standard deviations [Bx, By, Bz, T] or a "
                                 f"4x4 covariance of finite numbers.")
            if arr.shape == (4,) and not all(0 <= v <= MAX_SD for v in arr):
                raise ValueError(f"sigma_in = {sig!r}: each standard deviation [Bx, By, Bz (uT), T (C)] must be >= 0 "
                                 f"and at most {MAX_SD:g}.")
        r = self.reference_sd
        rs = list(np.ravel(np.asarray(r, dtype=object)))
        if not (len(rs) in (1, 3) and all(_number(v) and 0 <= v <= MAX_REFERENCE_SD for v in rs)):
            raise ValueError(f"reference_sd = {r!r} must be a standard uncertainty >= 0 in uT, or 3 of them, at most "
                             f"{MAX_REFERENCE_SD:g} uT (a reference magnetometer's: typically 0.001-1).")

    def options(self) -> UQOptions:
        """The :class:`~bayesmag._src.core.predictor.UQOptions` a :class:`Predictor` keeps."""
        return UQOptions(method=self.method, n_params=self.n_params, n_qmc=self.n_qmc, seed=self.seed,
                         chunk_size=self.chunk_size)

    def sigma_in_matrix(self, train) -> tuple[np.ndarray, str]:
        """The (4, 4) input-noise covariance and where it came from (:func:`sigma_in_matrix`)."""
        return sigma_in_matrix(self.sigma_in, train)


def sigma_in_matrix(sigma_in, train) -> tuple[np.ndarray, str]:
    """The (4, 4) input-noise covariance ``sigma_in`` stands for, and where it came from: ``"auto"`` (estimated
    from ``train``), 4 standard deviations, or a 4x4 covariance.

    Raises:
        ValueError: a 4x4 ``sigma_in`` that is not symmetric positive semi-definite.
    """
    s = sigma_in
    if isinstance(s, str) and s == "auto":
        from bayesmag._src.core.physics_uq import estimate_input_noise
        return estimate_input_noise(train), "auto: within-run second differences, 1.4826*MAD/sqrt(6)"
    arr = np.asarray(s, dtype=np.float64)
    if arr.ndim == 1:
        return np.diag(arr**2), "config: standard deviations"
    if not np.allclose(arr, arr.T) or np.linalg.eigvalsh(arr).min() < -1e-12:
        raise ValueError("'sigma_in' as a 4x4 matrix must be symmetric positive semi-definite.")
    return arr, "config: covariance matrix"


@dataclasses.dataclass(frozen=True)
class NetworkSettings(NetworkSpec):
    """The hybrid stage: the :class:`~bayesmag.NetworkSpec` settings shared by every network, plus
    ``likelihoods`` (one network per family; the first is the primary one), ``interval_calibration``
    (``"conformal"``: cross-conformal time-block folds, at most ``conformal_folds`` of them;
    ``"none"``) and ``fusion`` (one of :data:`~bayesmag._src.core.predictor.FUSIONS`). NetworkSpec's
    one-network ``likelihood``, set alone, is read as ``likelihoods=(likelihood,)``; set beside ``likelihoods``
    it must be one of them.

    The stage's default early-stopping rows are held-out time blocks (``validation =
    "time_blocks"``; the bare :class:`NetworkSpec` keeps the paper's ``"random"``).
    """

    likelihoods: tuple = ("gaussian",)
    validation: str = "time_blocks"
    interval_calibration: str = "conformal"
    conformal_folds: int = 5
    fusion: str = "moment_match"

    def __post_init__(self):
        super().__post_init__()
        if self.likelihood != "gaussian":       # NetworkSpec's one-network field: here the family of the networks
            if tuple(self.likelihoods) == ("gaussian",):
                object.__setattr__(self, "likelihoods", (self.likelihood,))    # likelihood="laplace" alone: honoured
            elif self.likelihood not in self.likelihoods:
                raise ValueError(f"likelihood = {self.likelihood!r} is not in likelihoods = {list(self.likelihoods)}: "
                                 f"the hybrid stage trains one network per entry of likelihoods (the first is the "
                                 f"primary one). Name the family there, e.g. likelihoods=({self.likelihood!r},).")
        names = list(self.likelihoods)
        if not names:
            raise ValueError(f"likelihoods = [] is empty; name at least one of {sorted(LIKELIHOODS)}.")
        unknown = [n for n in names if not isinstance(n, str) or n not in LIKELIHOODS]
        if unknown:
            raise ValueError(f"likelihoods = {names} names unknown likelihood(s) {unknown}; each must be one "
                             f"of {sorted(LIKELIHOODS)}.")
        if len(set(names)) != len(names):
            raise ValueError(f"likelihoods = {names} repeats a name.")
        if self.interval_calibration not in INTERVAL_CALIBRATIONS:
            raise ValueError(f"interval_calibration = {self.interval_calibration!r} is not valid; it must be one of "
                             f"{list(INTERVAL_CALIBRATIONS)}.")
        if self.fusion not in FUSIONS:
            raise ValueError(f"fusion = {self.fusion!r} is not valid; it must be one of {list(FUSIONS)}.")
        if self.conformal_folds < 2 or self.conformal_folds * self.validation_fraction >= 1.0:
            raise ValueError(f"conformal_folds = {self.conformal_folds} is not valid with validation_fraction = "
                             f"{self.validation_fraction}: it must be at least 2, and the folds (each one block of "
                             f"validation_fraction of every run) must fit in a run together (folds x fraction < 1).")

    def spec(self, likelihood: str) -> NetworkSpec:
        """The library settings of the network for one ``likelihood``."""
        return NetworkSpec.from_config(self, likelihood)

    def specs(self) -> list[NetworkSpec]:
        """One :class:`NetworkSpec` per likelihood, in order."""
        return [self.spec(name) for name in self.likelihoods]


@dataclasses.dataclass(frozen=True)
class NutsSettings:
    """The NUTS cross-check of the physics posterior (:func:`~bayesmag.run_nuts`'s arguments).

    ``priors``: a parsed :class:`~bayesmag._src.pipeline.nuts.NutsPriors`, or None (the defaults).
    """

    chains: int = 4
    warmup: int = 1000
    draws: int = 1000
    target_accept: float = 0.8
    chain_method: str = "vectorized"
    likelihood: str = "gaussian"
    priors: Any = None
    seed: int = 0

    def __post_init__(self):
        """The checks of the config's ``[nuts]`` keys, so a script's settings are refused as a config's are."""
        from bayesmag._src.pipeline.nuts.constants import CHAIN_METHODS
        for name, lo in (("chains", 1), ("warmup", 0), ("draws", 1), ("seed", 0)):
            _at_least(name, getattr(self, name), lo)
        if not _number(self.target_accept) or not 0 < self.target_accept < 1:
            raise ValueError(f"target_accept = {self.target_accept!r} must be in (0, 1), e.g. 0.8.")
        _one_of("chain_method", self.chain_method, CHAIN_METHODS)
        _one_of("likelihood", self.likelihood, tuple(LIKELIHOODS))


@dataclasses.dataclass(frozen=True)
class ConformalPlan:
    """The cross-conformal folds of the hybrid stage: ``folds`` blocks of ``fraction`` of every run
    (:func:`~bayesmag._src.pipeline.conformal.conformal_plan` sizes them from the split)."""

    fraction: float
    folds: int


@dataclasses.dataclass(frozen=True)
class CalibrationSettings:
    """Everything :func:`~bayesmag.calibrate` needs besides the data.

    ``network`` None: physics stage only; ``nuts`` None: no NUTS cross-check; ``conformal``:
    the cross-conformal plan (None: the default plan for a random split,
    ``(validation_fraction, conformal_folds)`` shrunk to fit).
    """

    physics: PhysicsSettings = PhysicsSettings()
    uq: UQSettings = UQSettings()
    network: NetworkSettings | None = None
    nuts: NutsSettings | None = None
    conformal: ConformalPlan | None = None


#: the propagated input noise may exceed the fit's residual sd by this factor before the estimate is doubted
NOISE_EXCESS = 2.0


def input_noise_warning(source: str, aleatoric: np.ndarray, fit) -> str | None:
    """A warning when ``sigma_in = "auto"`` gives a propagated input noise (mean aleatoric sd) over
    :data:`NOISE_EXCESS` times the fit's in-sample residual sd on some axis. The residuals hold that noise, so it
    cannot be larger: the estimate (second differences of the readings) took fast real change of the field between
    samples for noise. On a 4 Hz recording whose field direction random-walks 0.02 rad per sample (noise 0.05 uT) it
    read 0.17-0.37 uT: intervals 1.0-1.4 uT wide around a 0.05 uT RMSE, 100 % coverage, no word."""
    if not str(source).startswith("auto"):
        return None
    alea = np.mean(np.asarray(aleatoric, np.float64), axis=0)
    s = np.sqrt(np.asarray(fit.s2, np.float64))
    bad = [a for a, x, y in zip(AXES, alea, s) if x > NOISE_EXCESS * y]
    if not bad:
        return None
    ratio = ", ".join(f"{a} {x / y:.1f}x" for a, x, y in zip(AXES, alea, s) if a in bad)
    return (f"The input noise estimated from the readings (uq.sigma_in = \"auto\": second differences) propagates to "
            f"more than the fit's own residual sd on axis {', '.join(bad)} ({ratio}): the field changes fast between "
            f"samples, and that change was taken for noise, so the intervals are too wide. Set [uq] sigma_in to the "
            f"sensor's noise (datasheet or a static recording), e.g. sigma_in = [0.05, 0.05, 0.05, 0.01].")
