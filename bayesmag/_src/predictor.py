r"""The one predictive distribution: physics posterior + residual term + optional network + fusion + family.

A :class:`Predictor` holds everything a fitted calibration needs to predict a recording; its
:meth:`~Predictor.predict` is pure (same inputs, same outputs) and returns a
:class:`Prediction`: the predictive distribution all scores come from, its mean and total sd,
and the named standard deviations it is built from. The job, the simulation study, the
hybrid benchmark and ``bayesmag apply`` (through :class:`~bayesmag._src.artifact.Calibration`)
all predict through it, so what a run reports and what ``apply`` computes from the saved
calibration cannot drift apart.

Composition (:func:`compose`), per row and axis, with physics aleatoric / epistemic sds
:math:`a_p, e_p` (PS-QMC), residual sd :math:`r` (training scatter beyond the propagated input
noise), network aleatoric / epistemic sds :math:`a, e` (MC DropConnect) and transfer sd
:math:`\tau` (between-recording variation, :mod:`~bayesmag._src.transfer`):

* physics only: :math:`N(\bar y_{phys},\; a_p^2 + r^2 + e_p^2 + \tau^2)`;
* network, ``fusion = "moment_match"``: mean :math:`\bar y_{phys} + \mu_{NN}`, variance
  :math:`a^2 + e^2 + e_p^2 + \tau^2`, the network's likelihood family moment-matched to it
  (the network learned :math:`a^2` from residuals that already hold :math:`a_p^2` and :math:`r^2`);
* network, ``fusion = "paper"``: Gaussian with :math:`a_p^2 + a^2 + e^2 + e_p^2 + \tau^2`
  (Shetty & Marndi 2026, sec. 2.5).

The transfer part is absent (not zero-added) when ``transfer_sd`` is None.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import numpy as np

from .likelihoods import Gaussian, Likelihood, moment_match

__all__ = ["FUSIONS", "UQOptions", "Components", "Prediction", "Predictor", "compose", "network_inputs"]

FUSIONS = ("moment_match", "paper")

#: Rows per MC-DropConnect call (bounds memory of the passes on large recordings).
NN_CHUNK = 50_000


def network_inputs(data) -> np.ndarray:
    """The residual network's inputs ``(n, 4)``: measured field (3) and temperature, float64."""
    return np.column_stack([data.b_meas, data.temperature]).astype(np.float64)


@dataclasses.dataclass(frozen=True)
class UQOptions:
    """How the physics uncertainty is propagated (:func:`~bayesmag.physics_uncertainty`)."""

    method: str = "psqmc"
    n_params: int = 500
    n_qmc: int = 1000
    seed: int = 0
    chunk_size: int = 256


class Components(NamedTuple):
    """The separately computed pieces of a prediction: physics UQ and (optional) MC network output."""

    physics: Any                 # PhysicsUQ
    nn: Any = None               # MCPrediction or None


@dataclasses.dataclass(frozen=True)
class Prediction:
    """A predictive distribution over ``(n, 3)`` field values (uT) and the parts it is made of.

    ``parts``: named sds ``(n, 3)`` -- ``aleatoric_physics``, ``epistemic_physics``, and, where
    they enter the total, ``residual_physics``, ``aleatoric_nn``, ``epistemic_nn``, ``transfer``.
    ``in_domain`` / ``domain_reason``: ``(n,)``, set by :meth:`Predictor.predict` when the
    predictor knows its training domain, else None.
    """

    mean: np.ndarray
    dist: Likelihood
    total: np.ndarray
    parts: dict
    fusion: str | None = None
    family: str = "gaussian"
    in_domain: np.ndarray | None = None
    domain_reason: np.ndarray | None = None

    def interval(self, level: float) -> tuple[np.ndarray, np.ndarray]:
        """Central ``level`` interval of :attr:`dist`, float64 ``(lower, upper)``."""
        lo, hi = self.dist.interval(level)
        return np.asarray(lo, np.float64), np.asarray(hi, np.float64)

    def _part(self, name):
        return self.parts.get(name)

    aleatoric_physics = property(lambda self: self._part("aleatoric_physics"))
    epistemic_physics = property(lambda self: self._part("epistemic_physics"))
    residual_physics = property(lambda self: self._part("residual_physics"))
    aleatoric_nn = property(lambda self: self._part("aleatoric_nn"))
    epistemic_nn = property(lambda self: self._part("epistemic_nn"))
    transfer = property(lambda self: self._part("transfer"))


def compose(physics, nn=None, *, residual_sd=None, fusion: str = "moment_match", family: str = "gaussian",
            df: float | None = None, transfer_sd=None) -> Prediction:
    """The predictive distribution from its computed parts (rules in the module docstring).

    ``physics``: a :class:`~bayesmag.PhysicsUQ`; ``nn``: an MC-DropConnect
    :class:`~bayesmag._src.network.MCPrediction` or None; ``residual_sd``, ``transfer_sd``:
    ``(3,)`` or ``(n, 3)`` sds or None; ``df``: fixed Student-t degrees of freedom (None: the
    network's learned per-row df).
    """
    if fusion not in FUSIONS:
        raise ValueError(f"fusion {fusion!r} is not known; it must be one of {list(FUSIONS)}")
    p_mean = np.asarray(physics.mean, np.float64)
    parts = {"aleatoric_physics": np.asarray(physics.aleatoric), "epistemic_physics": np.asarray(physics.epistemic)}
    tau = None if transfer_sd is None else np.broadcast_to(np.asarray(transfer_sd, np.float64), p_mean.shape)
    if nn is None:
        resid = np.broadcast_to(np.zeros(3) if residual_sd is None else np.asarray(residual_sd, np.float64),
                                p_mean.shape)
        parts["residual_physics"] = resid
        var = physics.aleatoric**2 + resid**2 + physics.epistemic**2
        if tau is not None:
            var = var + tau**2
        mean, dist_fam = p_mean, "gaussian"
        dist = Gaussian(mean, np.sqrt(var))
        fusion = None
    else:
        mean = p_mean + nn.mean
        parts["aleatoric_nn"], parts["epistemic_nn"] = nn.aleatoric, nn.epistemic
        var = nn.aleatoric**2 + nn.epistemic**2 + physics.epistemic**2
        if fusion == "paper":
            var = var + physics.aleatoric**2
        if tau is not None:
            var = var + tau**2
        if fusion == "paper":
            dist_fam, dist = "gaussian", Gaussian(mean, np.sqrt(var))
        else:
            shape = {}
            if family == "student_t":
                shape["df"] = nn.shape["df"] if df is None else df
            dist_fam, dist = family, moment_match(family, mean, var, **shape)
    if tau is not None:
        parts["transfer"] = tau
    return Prediction(mean, dist, np.sqrt(var), parts, fusion, dist_fam)


@dataclasses.dataclass(frozen=True)
class Predictor:
    """Everything needed to predict a recording: a frozen value, :meth:`predict` is pure.

    ``fit``: the physics posterior (a :class:`~bayesmag.PhysicsFit` or the view a saved
    calibration gives); ``sigma_in``: (4, 4) input-noise covariance; ``residual_sd``: (3,)
    residual term; ``network``: trained :class:`~bayesmag._src.network.ResidualNetwork` or None,
    predicted with ``passes`` MC passes from ``network_seed``; ``fusion``: one of
    :data:`FUSIONS`; ``transfer_sd``: (3,) between-recording sd or None; ``domain``: the
    training :class:`~bayesmag._src.domain.Domain` or None; ``uq``: physics UQ settings.
    """

    fit: Any
    sigma_in: np.ndarray
    residual_sd: np.ndarray
    network: Any = None
    passes: int = 100
    network_seed: int = 0
    fusion: str = "moment_match"
    transfer_sd: np.ndarray | None = None
    domain: Any = None
    uq: UQOptions = UQOptions()

    def __post_init__(self):
        if self.fusion not in FUSIONS:
            raise ValueError(f"fusion {self.fusion!r} is not known; it must be one of {list(FUSIONS)}")

    @property
    def family(self) -> str:
        """Likelihood family of the predictive distribution's network part ('gaussian' without one)."""
        return "gaussian" if self.network is None else self.network.spec.likelihood

    def physics_part(self, data, *, progress: bool = False):
        """Physics prediction and its PS-QMC (or analytic) uncertainty for every row of ``data``."""
        from .physics import inputs_from_data
        from .physics_uq import physics_uncertainty

        o = self.uq
        return physics_uncertainty(self.fit, inputs_from_data(data), sigma_in=self.sigma_in, method=o.method,
                                   n_params=o.n_params, n_qmc=o.n_qmc, seed=o.seed, chunk_size=o.chunk_size,
                                   progress=progress)

    def network_part(self, data):
        """MC-DropConnect residual prediction for every row of ``data`` (None without a network)."""
        from .network import mc_predict

        if self.network is None:
            return None
        x = network_inputs(data)
        if x.shape[0] <= NN_CHUNK:
            return mc_predict(self.network, x, passes=self.passes, seed=self.network_seed)
        pieces = [mc_predict(self.network, x[lo:lo + NN_CHUNK], passes=self.passes, seed=self.network_seed)
                  for lo in range(0, x.shape[0], NN_CHUNK)]
        cat = {f: np.concatenate([getattr(p, f) for p in pieces]) for f in ("mean", "aleatoric", "epistemic")}
        return type(pieces[0])(**cat, shape={k: np.concatenate([p.shape[k] for p in pieces])
                                             for k in pieces[0].shape})

    def components(self, data, *, progress: bool = False) -> Components:
        """Physics UQ and the MC network output for every row of ``data``."""
        return Components(self.physics_part(data, progress=progress), self.network_part(data))

    def compose(self, c: Components, *, fusion: str | None = None) -> Prediction:
        """The prediction from already computed components (``fusion`` overrides the predictor's)."""
        spec = None if self.network is None else self.network.spec
        return compose(c.physics, c.nn, residual_sd=self.residual_sd, fusion=fusion or self.fusion,
                       family=self.family, df=None if spec is None else spec.df, transfer_sd=self.transfer_sd)

    def predict(self, data, *, progress: bool = False) -> Prediction:
        """The predictive distribution for every row of ``data`` (no reference needed)."""
        pred = self.compose(self.components(data, progress=progress))
        if self.domain is None:
            return pred
        out = self.domain.outside(data, pred.mean)
        return dataclasses.replace(pred, in_domain=~out.any(axis=1), domain_reason=self.domain.reasons(out))
