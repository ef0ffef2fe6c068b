r"""A simulated fleet: sensors drawn from a production population, a few defective units planted.

Sensor ``i`` has true parameters (t0 = 0 convention of :class:`~bayesmag._src.core.simulate.TrueParams`)

.. math::  S = I + \mathrm{diag}(g) + C, \quad g_j \sim N(0, s_g^2),\; C_{jk} \sim N(0, s_c^2)\ (j \ne k),
           \quad K_s \sim N(0, s_{K_s}^2),\; O \sim N(0, s_O^2),\; K_o \sim N(0, s_{K_o}^2),

and its recording is :func:`~bayesmag._src.core.simulate.simulate` with the ``campaign`` design,
seed ``seed * 100_003 + i`` (every draw from the one ``seed``). Defective units get one
:data:`DEFECTS` kind each, added on top of their draw; their ids are the ground truth.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

import numpy as np

from bayesmag._src.core.data import CalibrationData
from bayesmag._src.core.simulate import TrueParams, simulate

__all__ = ["DEFECTS", "FleetTruth", "simulate_fleet"]

#: Defect kinds and what each adds to a unit (fleet-typical spreads in the defaults below).
DEFECTS: Mapping[str, str] = {
    "offset": "O_x += 25 uT (a magnetised part near the sensor)",
    "gain": "S_yy += 0.15 (a 15 % gain error)",
    "cross_axis": "S_xz += 0.08 (a tilted die: 8 % cross-axis coupling)",
    "thermal": "Ko_z += 0.3 uT/C (an offset with 30x the usual temperature coefficient)",
    "noisy": "reading noise x10 (a noisy front end)",
}


@dataclasses.dataclass(frozen=True)
class FleetTruth:
    """Ground truth of a simulated fleet: ``ids``, ``theta`` (N, 3, 8) true parameters, ``noise_sd`` (N,),
    ``defects`` {id: kind} of the planted units."""

    ids: tuple[str, ...]
    theta: np.ndarray
    noise_sd: np.ndarray
    defects: dict

    def to_json(self) -> dict:
        return {"defective": dict(self.defects), "defect_kinds": dict(DEFECTS),
                "noise_sd": dict(zip(self.ids, map(float, self.noise_sd)))}


def simulate_fleet(n_sensors: int = 100, n_rows: int = 5000, *, seed: int = 0, n_defective: int = 5,
                   noise_sd: float = 0.05, gain_sd: float = 0.01, cross_sd: float = 0.005, ks_sd: float = 2e-4,
                   offset_sd: float = 2.0, ko_sd: float = 0.01, rows_spread: float = 0.0,
                   ) -> tuple[list[CalibrationData], FleetTruth]:
    """``n_sensors`` recordings of ``n_rows`` rows (``rows_spread``: lengths uniform in ``n_rows * [1 - spread, 1]``),
    ``n_defective`` of them defective (kinds cycling through :data:`DEFECTS`, units chosen at random).

    Example:
      >>> recs, truth = simulate_fleet(6, 200, seed=1, n_defective=1)
      >>> len(recs), recs[0].n, list(truth.defects.values())
      (6, 200, ['offset'])
    """
    if int(n_sensors) < 1 or int(n_rows) < 20:
        raise ValueError(f"n_sensors must be >= 1 and n_rows >= 20; got {n_sensors!r}, {n_rows!r}.")
    if not 0 <= int(n_defective) <= int(n_sensors):
        raise ValueError(f"n_defective must be in [0, n_sensors = {n_sensors}]; got {n_defective!r}.")
    if not 0 <= rows_spread < 1:
        raise ValueError(f"rows_spread must be in [0, 1); got {rows_spread!r}.")
    N = int(n_sensors)
    rng = np.random.default_rng([int(seed), 27])
    ids = tuple(f"SN{i:05d}" for i in range(N))
    theta = np.zeros((N, 3, 8))
    off = ~np.eye(3, dtype=bool)
    S = np.eye(3) + np.einsum("nj,jk->njk", rng.normal(0, gain_sd, (N, 3)), np.eye(3))
    S = S + np.where(off, rng.normal(0, cross_sd, (N, 3, 3)), 0.0)
    theta[:, :, 0:3] = S
    theta[:, :, 3:6] = rng.normal(0, ks_sd, (N, 3, 3))
    theta[:, :, 6] = rng.normal(0, offset_sd, (N, 3))
    theta[:, :, 7] = rng.normal(0, ko_sd, (N, 3))
    noise = np.full(N, float(noise_sd))
    kinds = list(DEFECTS)
    bad = np.sort(rng.choice(N, size=int(n_defective), replace=False))
    defects = {}
    for k, i in enumerate(bad):
        kind = kinds[k % len(kinds)]
        defects[ids[i]] = kind
        if kind == "offset":
            theta[i, 0, 6] += 25.0
        elif kind == "gain":
            theta[i, 1, 1] += 0.15
        elif kind == "cross_axis":
            theta[i, 0, 2] += 0.08
        elif kind == "thermal":
            theta[i, 2, 7] += 0.3
        else:
            noise[i] *= 10
    lengths = np.full(N, int(n_rows)) if rows_spread == 0 else \
        rng.integers(int(np.ceil(n_rows * (1 - rows_spread))), int(n_rows) + 1, size=N)
    recs = []
    for i in range(N):
        d = simulate(int(lengths[i]), design="campaign", seed=int(seed) * 100_003 + i,
                     params=TrueParams.from_theta(theta[i]), noise_sd=float(noise[i]))
        recs.append(dataclasses.replace(d, source=f"simulated fleet unit {ids[i]} (seed {seed})"))
    return recs, FleetTruth(ids, theta, noise, defects)
