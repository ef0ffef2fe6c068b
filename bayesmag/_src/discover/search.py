"""Catalogue search: every registered entry, in every frame it can act in, scored out of sample.

A *group* is one catalogue entry in one place: a sensor channel (``frame="sensor"``), one
calibrated output (``"output"``) or the whole sensor (``"whole"``, transforms). Its options
are the entry's own grid (:meth:`~bayesmag._src.catalogue.Entry.grid`); per fold the option
with the least *training* error is used, so the choice is part of what is cross-validated.
A group is accepted if, against the current model, it

* lowers the out-of-sample loss (sum over the three outputs, each weighted by 1 / its noise
  floor) with a one-sided block z >= Z_MIN (:func:`~.diagnostics.block_z`),
* removes at least MIN_GAIN of the out-of-sample mean square of the output it helps most, and
* lowers the BIC computed with the effective sample size by at least DBIC_MIN.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .. import catalogue as C
from .diagnostics import block_z
from .frame import Designs, Extension, solve_sym
from .options import DBIC_MIN, MIN_GAIN, Z_DISTINCT, Z_MIN

__all__ = ["Score", "groups", "cv_residuals", "score_group", "forward", "bic"]


@dataclasses.dataclass
class Score:
    """Out-of-sample evidence for one group against a reference model."""

    key: tuple                   # (entry name, frame, slot)
    ext: Extension               # the option chosen on all rows
    e_oos: np.ndarray            # (3n,) out-of-sample weighted residuals
    gain: float                  # best per-output fraction of the OOS mean square removed
    gain_total: float
    z: float
    dbic: float
    n_params: int

    @property
    def accepted(self) -> bool:
        return self.z >= Z_MIN and self.gain >= MIN_GAIN and self.dbic <= -DBIC_MIN


def groups(ctx: C.SearchContext, names, has: set) -> dict:
    """(name, frame, slot) -> list of Extension options, for every entry whose requirements ``has`` meets."""
    out = {}
    for name in names:
        cls = C.CATALOGUE[name]
        if not set(cls.requires) <= has:
            continue
        if cls.scope == "sensor":
            out[(name, "whole", None)] = [Extension(s, "whole") for s in cls.grid(ctx, None)]
            continue
        for frame in ("sensor", "output"):
            for c in range(3):
                out[(name, frame, c)] = [Extension(s, frame, c) for s in cls.grid(ctx, c)]
    return out


def _fold_stats(X, y, folds3, fold_ids):
    """Per fold (beta, training SSE), and beta on all rows, by normal equations on column-scaled
    X; rows are sorted by fold once so each fold is a contiguous slice (no copies per fold)."""
    order = np.argsort(folds3, kind="stable")
    bounds = np.searchsorted(folds3[order], np.append(fold_ids, fold_ids[-1] + 1))
    s = np.sqrt((X * X).sum(0))
    s = np.where(s > 0, s, 1.0)
    Xs, ys = X[order] / s, y[order]
    parts = [(Xs[a:b].T @ Xs[a:b], Xs[a:b].T @ ys[a:b], float(ys[a:b] @ ys[a:b])) for a, b in zip(bounds[:-1], bounds[1:])]
    G = sum(p[0] for p in parts)
    c = sum(p[1] for p in parts)
    yy = sum(p[2] for p in parts)
    out = []
    for Gt, ct, yt in parts:
        Gk, ck = G - Gt, c - ct
        b = solve_sym(Gk, ck)
        sse = (yy - yt) - 2 * float(b @ ck) + float(b @ Gk @ b)
        out.append((b / s, sse))
    b = solve_sym(G, c)
    return out, b / s, yy - 2 * float(b @ c) + float(b @ G @ b)


def cv_residuals(designs: Designs, current: tuple, options: list, folds3: np.ndarray):
    """(out-of-sample residuals (3n,), in-sample residuals (3n,), chosen option, n columns); per
    fold the option with the least training SSE; in sample the option with the least SSE."""
    y = designs.y
    fold_ids = np.unique(folds3)
    mats = [designs.matrix(current + ((o,) if o is not None else ())) for o in options]
    fits = [_fold_stats(X, y, folds3, fold_ids) for X in mats]
    e = np.empty_like(y)
    for j, k in enumerate(fold_ids):
        te = folds3 == k
        m = int(np.argmin([f[0][j][1] for f in fits]))
        e[te] = y[te] - mats[m][te] @ fits[m][0][j][0]
    best = int(np.argmin([f[2] for f in fits]))
    r_best = y - mats[best] @ fits[best][1]
    return e, r_best, options[best], mats[best].shape[1]


def bic(sse: float, n_eff: float, k: int) -> float:
    return n_eff * math.log(max(sse, 1e-300) / max(n_eff, 1.0)) + k * math.log(max(n_eff, 2.0))


def row_loss(e: np.ndarray, n: int) -> np.ndarray:
    return (e.reshape(3, n) ** 2).sum(0)


def compare(key, ext, e_new, r_new, k_new, e_ref, r_ref, k_ref, blocks, n_eff, n, n_options) -> Score:
    d = row_loss(e_ref, n) - row_loss(e_new, n)
    per_ref = (e_ref.reshape(3, n) ** 2).sum(1)
    per_gain = (per_ref - (e_new.reshape(3, n) ** 2).sum(1)) / np.maximum(per_ref, 1e-300)
    extra = (1 if ext.frame == "whole" else 0) + (1 if n_options > 1 else 0)
    k_eff = k_new + extra
    dbic = bic(float(r_new @ r_new), n_eff, k_eff) - bic(float(r_ref @ r_ref), n_eff, k_ref)
    return Score(key, ext, e_new, float(per_gain.max()), float(d.sum() / per_ref.sum()), block_z(d, blocks), dbic,
                 k_eff - k_ref)


def score_group(designs, current, key, options, folds3, blocks, ref, n_eff) -> Score:
    """Score of adding group ``key`` (its ``options``) to ``current``; ``ref`` = (e, r, k) of ``current``."""
    e, r, chosen, k = cv_residuals(designs, current, options, folds3)
    return compare(key, chosen, e, r, k, *ref, blocks, n_eff, designs.n, len(options))


def forward(designs, cands: dict, folds3, blocks, ref, n_eff_fn, max_terms: int, progress=None):
    """Forward selection; returns (selected extensions, steps). Each step adds the accepted
    group with the largest total gain; an output-frame group only if it beats the same entry's
    best sensor-frame group by block z >= Z_DISTINCT (the physics happens in a channel)."""
    current, steps = (), []
    used = set()
    while len(current) < max_terms:
        n_eff = n_eff_fn(ref[1])
        scores = []
        for key, opts in cands.items():
            if key in used or (key[1] == "whole" and any(k[0] == key[0] for k in used)):
                continue
            scores.append(score_group(designs, current, key, opts, folds3, blocks, ref, n_eff))
        ok = [s for s in scores if s.accepted]
        if progress:
            progress(f"step {len(current) + 1}: {len(scores)} candidate groups scored, {len(ok)} accepted")
        if not ok:
            break
        best = max(ok, key=lambda s: s.gain_total)
        if best.key[1] == "output":
            twins = [s for s in ok if s.key[0] == best.key[0] and s.key[1] == "sensor"]
            if twins:
                twin = max(twins, key=lambda s: s.gain_total)
                z = block_z(row_loss(twin.e_oos, designs.n) - row_loss(best.e_oos, designs.n), blocks)
                if z < Z_DISTINCT:
                    best = twin
        alts = [s for s in ok if s is not best and s.key[0] != best.key[0]
                and block_z(row_loss(s.e_oos, designs.n) - row_loss(best.e_oos, designs.n), blocks) < Z_DISTINCT]
        steps.append({"score": best, "alternatives": alts, "e_before": ref[0]})
        chosen = best.ext
        if chosen.frame == "whole":
            # refine the nonlinear value around the grid point (in sample), so later steps do not
            # pick up the misfit of a coarse grid (e.g. per-run offsets after a lag of the wrong tau)
            chosen = _refine(designs, current, chosen, folds3)
        current = current + (chosen,)
        used.add(best.key)
        e, r, _, k = cv_residuals(designs, current, [None], folds3)
        ref = (e, r, k)
    return current, steps, ref


def _refine(designs, current, ext, folds3, rounds: int = 2, max_moves: int = 8):
    """The whole-sensor extension with its nonlinear value refined by in-sample SSE on finer grids.

    Each round scans 9 values across +-step around the current value; while the best lies on
    the edge of that window the window is moved (at most ``max_moves`` times), so a value beyond
    the coarse grid (e.g. a thermal lag longer than the grid's top) is bracketed before the step
    shrinks. A value left at a window edge leaves a misfit (for a lag: proportional to dT/dt,
    whose mean differs between runs) that later steps would otherwise take up as per-run offsets."""
    is_log = ext.name == "thermal_lag"
    step = 0.35 if is_log else 0.25 * max(abs(ext.setting.nl), 1e-3)
    for _ in range(rounds):
        for _ in range(max_moves):
            centre = ext.setting.nl
            vals = centre + step * np.linspace(-1, 1, 9)
            opts = [Extension(dataclasses.replace(ext.setting, nl=float(v)), "whole") for v in vals]
            _, _, ext, _ = cv_residuals(designs, current, opts, folds3)
            if vals[0] < ext.setting.nl < vals[-1]:
                break
        step /= 4
    return ext
