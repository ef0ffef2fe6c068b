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
* :func:`constant_within_runs`: an entry that declares ``localised = "run"`` claims a constant per
  run (a re-seat of the offset at power-up). When neighbouring blocks of a run are more alike than
  in random order (serial contrast z >= Z_DISTINCT) *and* the same columns with a coefficient per
  piece of each run (:class:`RunPieces`) predict better out of sample by >= MIN_GAIN, the structure
  wanders within runs (a random walk, a drift, a lag) and the per-run term is not the physics.
* :func:`implausible`: a fitted nonlinear parameter outside the entry's physical range
  (:meth:`~bayesmag._src.core.catalogue.Entry.implausible`) removes the named effect.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from bayesmag._src.core.catalogue import Setting, ThermalLag
from bayesmag._src.core.fit import covariance
import jax.numpy as jnp

from bayesmag._src.core.physics import InputTransform, Term
from bayesmag._src.pipeline.discover.diagnostics import block_z, run_pieces, serial_contrast
from bayesmag._src.pipeline.discover.frame import Extension, lstsq
from bayesmag._src.pipeline.discover.options import MIN_GAIN, PIECES, T_IDENT, Z_DISTINCT
from bayesmag._src.pipeline.discover.search import compare, cv_residuals, place_residual, row_loss

__all__ = ["drop_one", "identified", "implausible", "ZeroPhaseSmoothing", "lag_or_smoothing", "RunPieces",
           "WithinRun", "constant_within_runs"]


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



@dataclasses.dataclass(frozen=True)
class RunPieces(Term):
    r"""The columns of a run-localised term with a coefficient per *piece* of each run:
    :math:`F_j(x)\,[\text{piece}(x) = s]` for every used column ``j`` of ``inner`` and piece ``s``.

    ``cuts``: ``(run, time)`` pairs, each starting a new piece of that run (rows at or after the
    time); a run without cuts is one piece. Not a catalogue term: the rival of a per-run constant
    in :func:`constant_within_runs`, as :class:`ZeroPhaseSmoothing` is a thermal lag's."""

    inner: object = None
    cols: tuple | None = None
    cuts: tuple = ()
    pieces: int = 1
    name: ClassVar[str] = "run_pieces"
    degree: ClassVar[int] = 0
    temperature_centred: ClassVar[bool] = True

    def param_names(self):
        names = self.inner.param_names()
        used = [names[i] for i in (self.cols if self.cols is not None else range(len(names)))]
        return tuple(f"{n}_piece{s + 1}" for n in used for s in range(self.pieces))

    def features(self, inputs):
        F = self.inner.features(inputs)
        if self.cols is not None:
            F = F[:, list(self.cols)]
        piece = jnp.zeros(F.shape[0], dtype=jnp.int32)
        for r, t in self.cuts:
            piece = piece + ((inputs.run == r) & (inputs.time >= t)).astype(jnp.int32)
        return jnp.concatenate([F * (piece == s)[:, None] for s in range(self.pieces)], axis=1)


@dataclasses.dataclass(frozen=True)
class WithinRun:
    """Whether a per-run constant holds within its runs. ``z`` (one-sided ``p``): neighbouring blocks of a run are
    more alike than in random order (:func:`~.diagnostics.serial_contrast`, on the residual in the term's place of
    the model with the term); ``gain``: the share of the out-of-sample mean square of the output helped most by
    which the term's columns with a coefficient per piece of each run (:class:`RunPieces`) predict better than
    the constant; ``pieces`` the most pieces of any run."""

    z: float
    p: float
    gain: float
    pieces: int

    @property
    def wanders(self) -> bool:
        """The offset wanders within runs: ``z >= Z_DISTINCT`` and ``gain >= MIN_GAIN``."""
        return self.z >= Z_DISTINCT and self.gain >= MIN_GAIN


def constant_within_runs(designs, kept: tuple, ext: Extension, folds3, blocks, pieces: int = PIECES,
                         seed: int = 0) -> WithinRun | None:
    """Test the per-run constant of a run-localised finding ``ext`` (in the model ``kept``) within its runs;
    None when no run has 4 CV blocks.

    Significance: the serial contrast of the block means of the place's residual (the sensor channel's, mapped
    back through S + Ks Tc, or the output's). Size: the term's columns given a coefficient per piece of each run
    (:func:`~.diagnostics.run_pieces`: up to ``pieces`` pieces of at least 2 whole CV blocks; neighbouring blocks
    lie in different folds, so every held-out block is predicted from its piece's other blocks) against the
    constant, out of sample. A constant per run plus noise: neither. An offset that wanders within runs (a random
    walk, an untested drift or lag): both."""
    time, run = np.asarray(designs.inputs.time, dtype=float), np.asarray(designs.inputs.run)
    piece = run_pieces(blocks, run, pieces)
    if piece.max() == 0:
        return None
    start = np.concatenate([[True], (piece[1:] != piece[:-1]) & (run[1:] == run[:-1])])
    cuts = tuple((int(run[i]), float(time[i])) for i in np.flatnonzero(start & (piece > 0)))
    rival = Extension(Setting(RunPieces(ext.component, ext.setting.cols, cuts, int(piece.max()) + 1)),
                      ext.frame, ext.slot)
    others = tuple(e for e in kept if e != ext)
    e_const, r_in, _, _ = cv_residuals(designs, kept, [None], folds3)
    e_piece, _, _, _ = cv_residuals(designs, others + (rival,), [None], folds3)
    z, p = serial_contrast(place_residual(designs, ext, r_in), blocks, run, seed=seed)
    n = designs.n
    per_c = (e_const.reshape(3, n) ** 2).sum(1)
    gain = float(((per_c - (e_piece.reshape(3, n) ** 2).sum(1)) / np.maximum(per_c, 1e-300)).max())
    return WithinRun(float(z), float(p), gain, int(piece.max()) + 1)
