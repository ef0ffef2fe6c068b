"""Deep ensembles: :class:`NetworkEnsemble` and how MC passes are split over its members."""

from __future__ import annotations

from typing import NamedTuple

from bayesmag._src.core.network.spec import NetworkSpec

__all__ = ['NetworkEnsemble', 'ensemble_passes']


class NetworkEnsemble(NamedTuple):
    """Deep ensemble of ``K`` trained :class:`ResidualNetwork` of one spec (e.g. the job's cross-conformal
    fold networks), predicted together by :func:`mc_predict` with the passes split over the members."""

    members: tuple

    @property
    def spec(self) -> NetworkSpec:
        return self.members[0].spec



def ensemble_passes(passes: int, members: int) -> tuple[int, ...]:
    """MC passes per member: ``passes // members`` each, the first ``passes % members`` members one more
    (100 over 5: 20 each; 101 over 5: 21, 20, 20, 20, 20), and never fewer than 2 (a member's sample
    variance needs 2): below ``2 * members`` passes every member runs 2, ``2 * members`` in all."""
    if members < 1 or passes < 2:
        raise ValueError(f"an ensemble needs at least 1 member and 2 passes, got {members} and {passes}.")
    return tuple(max(2, passes // members + (k < passes % members)) for k in range(members))

