"""Checks on the whole finding set: drop-one refits, identified coefficients, plausible parameters.

* :func:`drop_one`: forward selection judges each term against the terms chosen *before* it;
  here every selected term must still pass the acceptance criteria against the model with all
  the *other* selected terms (a drifting offset taken up by a temperature curvature early on
  loses that support once the drift term is in). The weakest failing term is removed and the
  check repeats.
* :func:`identified`: inside a term, coefficients with |value| < T_IDENT standard errors
  (Newey-West, on the stacked linear fit) are removed one at a time, weakest first; they are
  reported as not identified by these data, never as findings.
* :func:`lag_or_smoothing`: a thermal lag must fit better than a *zero-phase* smoothing of
  the temperature log with the same time constant (block z >= Z_DISTINCT). Heat flow delays
  the temperature the die sees; smoothing the log's noise does not delay anything, so when
  the symmetric filter explains as much, the gain is noise reduction, not a lag.
* :func:`implausible`: a fitted nonlinear parameter outside the entry's physical range
  (:meth:`~bayesmag._src.core.catalogue.Entry.implausible`) removes the named effect.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from bayesmag._src.core.catalogue import Setting, ThermalLag
from bayesmag._src.core.fit import covariance
from bayesmag._src.core.physics import InputTransform
from bayesmag._src.pipeline.discover.diagnostics import block_z
from bayesmag._src.pipeline.discover.frame import Extension, lstsq
from bayesmag._src.pipeline.discover.options import T_IDENT
from bayesmag._src.pipeline.discover.search import cv_residuals, row_loss, compare

__all__ = ["drop_one", "identified", "implausible", "ZeroPhaseSmoothing", "lag_or_smoothing"]


def drop_one(designs, selected: tuple, folds3, blocks, n_eff_fn, progress=None):
    """(kept, dropped: list of (extension, score)) after drop-one checks of the whole set."""
    dropped = []
    current = tuple(selected)
    while current:
        e_full, r_full, _, k_full = cv_residuals(designs, current, [None], folds3)
        n_eff = n_eff_fn(r_full)
        worst = None
        for ext in current:
            others = tuple(x for x in current if x != ext)
            e_wo, r_wo, _, k_wo = cv_residuals(designs, others, [None], folds3)
            s = compare((ext.name, ext.frame, ext.slot), ext, e_full, r_full, k_full, e_wo, r_wo, k_wo, blocks,
                        n_eff, designs.n, 1, designs)
            if not s.accepted and (worst is None or s.z < worst[1].z):
                worst = (ext, s)
        if worst is None:
            break
        dropped.append(worst)
        current = tuple(x for x in current if x != worst[0])
        if progress:
            progress(f"drop-one: {worst[0].name} removed (z = {worst[1].z:.2f} given the others)")
    return current, dropped


def identified(designs, selected: tuple, run: np.ndarray):
    """(selected with unidentified coefficients removed, list of removed coefficient records)."""
    removed = []
    current = list(selected)
    run3 = np.concatenate([run + a * (int(run.max()) + 1) for a in range(3)])
    for _ in range(50):
        X = designs.matrix(tuple(current))
        beta = lstsq(X, designs.y)
        r = designs.y - X @ beta
        cov, _ = covariance(X, r, method="newey_west", run=run3)
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
        i = X.shape[1] - sum(e.n_linear for e in current if e.frame != "whole")
        worst = None
        for j, e in enumerate(current):
            if e.frame == "whole":
                continue
            t = np.abs(beta[i:i + e.n_linear]) / np.maximum(se[i:i + e.n_linear], 1e-300)
            if e.n_linear > 1 and t.min() < T_IDENT and (worst is None or t.min() < worst[2]):
                m = int(np.argmin(t))
                worst = (j, m, float(t[m]), float(beta[i + m]), float(se[i + m]))
            i += e.n_linear
        if worst is None:
            break
        j, m, t, val, sd = worst
        e = current[j]
        cols = e.setting.cols if e.setting.cols is not None else tuple(range(len(e.component.param_names())))
        removed.append({"effect": e.name, "frame": e.frame, "slot": e.slot, "parameter": e.param_names[m],
                        "value": val, "se": sd, "t": t})
        current[j] = e.with_cols(tuple(c for k, c in enumerate(cols) if k != m))
    return tuple(current), removed


def implausible(ext: Extension, value: float, ctx) -> str | None:
    """Why the fitted nonlinear ``value`` of a whole-sensor extension is not its physics (or None)."""
    return ext.component.implausible(value, ctx)


@dataclasses.dataclass(frozen=True)
class ZeroPhaseSmoothing(InputTransform):
    """The logged temperature smoothed forward and backward by a first-order filter (time
    constant exp(log_tau) s, restarted at run boundaries): same smoothing as a thermal lag, no delay."""

    tau0: float = 30.0
    name: ClassVar[str] = "temperature_smoothing"

    def param_names(self):
        return ("log_tau",)

    def init_params(self, axis):
        return np.array([np.log(self.tau0)])

    def __call__(self, params, inputs):
        fwd = ThermalLag()(params, inputs)
        rev = inputs._replace(t=fwd.t[::-1], time=-inputs.time[::-1], run=inputs.run[::-1], b=inputs.b[::-1])
        back = ThermalLag()(params, rev)
        return inputs._replace(t=back.t[::-1])


def lag_or_smoothing(designs, kept: tuple, lag: Extension, folds3, blocks) -> tuple[float, float]:
    """(block z that the lag beats zero-phase smoothing out of sample, tau of the best smoothing)."""
    others = tuple(e for e in kept if e != lag)
    taus = np.exp(lag.setting.nl) * np.array([0.25, 0.5, 1.0, 2.0, 4.0])
    opts = [Extension(Setting(ZeroPhaseSmoothing(tau0=float(t)), nl=float(np.log(t))), "whole") for t in taus]
    e_lag, _, _, _ = cv_residuals(designs, kept, [None], folds3)
    e_sm, _, chosen, _ = cv_residuals(designs, others, opts, folds3)
    z = block_z(row_loss(e_sm, designs.n) - row_loss(e_lag, designs.n), blocks)
    return z, float(np.exp(chosen.setting.nl))

