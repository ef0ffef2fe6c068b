"""Options of :func:`~bayesmag._src.pipeline.discover.discover` and the thresholds it declares (the bottom of the
discover package: every other module imports its constants from here)."""

from __future__ import annotations

import dataclasses

from scipy import stats as _stats

from bayesmag._src.core import catalogue as C
from bayesmag._src.core.physics import T0_DEFAULT

__all__ = ["DiscoverOptions"]

# --------------------------------------------------------------------------- shared constants (imported by every discover module)

#: One-sided block z-score of the out-of-sample gain needed to accept a candidate (about 44
#: candidate groups per step: p = 2.3e-4 each keeps the clean-data false-finding rate ~1 % per step).
Z_MIN = 3.5
#: Run-localised entries (``Entry.localised == "run"``: one offset per run) are also scored by run
#: (:func:`~bayesmag._src.pipeline.discover.diagnostics.run_contrast`, an F test of the run means of the
#: residual against the scatter of block means within runs). They are their own family of
#: RUN_PLACES tests per step (the entry on 3 sensor channels and 3 outputs), given the same 1 %
#: false-finding budget per step as the block test's family: p <= RUN_FAMILY_ERROR / RUN_PLACES
#: (Bonferroni), i.e. z >= Z_RUN = 2.94. The out-of-sample gain and BIC criteria still apply.
RUN_FAMILY_ERROR = 0.01
RUN_PLACES = 6
Z_RUN = float(_stats.norm.isf(RUN_FAMILY_ERROR / RUN_PLACES))
#: Smallest out-of-sample gain (fraction of the residual mean square of the output axis it
#: helps most) worth reporting.
MIN_GAIN = 0.01
#: BIC (effective n) must drop by at least this much ("very strong" on Kass & Raftery's scale).
DBIC_MIN = 10.0
#: An output-frame term is kept only if it beats the sensor-frame form by this block z.
Z_DISTINCT = 2.0
#: A run-localised finding (a constant per run) is tested within its runs
#: (:func:`~bayesmag._src.pipeline.discover.checks.constant_within_runs`): its columns get a coefficient for each
#: of up to this many pieces of a run (at least 2 CV blocks each); when neighbouring blocks of a run are more alike
#: than in random order (serial contrast z >= Z_DISTINCT) and the pieces predict better out of sample by >=
#: MIN_GAIN, the offset wanders within runs and is reported as unexplained, not named.
PIECES = 8
#: Most extensions in the joint model.
MAX_TERMS = 4
#: A coefficient is reported only if |value| >= T_IDENT standard errors (the rest are not identified).
T_IDENT = 3.0
#: A located mismatch needs a block-permutation p-value <= LOCATE_P ...
LOCATE_P = 0.002
#: ... and must hold at least this fraction of the residual variance.
LOCATE_FRACTION = 0.02
#: Structure left after the final model is reported as unexplained above this share of the residual variance.
UNEXPLAINED_FRACTION = 0.05
#: Residuals with lag-1 autocorrelation above this ...
RHO_STRUCTURE = 0.5
#: ... and variance above this multiple of the high-frequency noise floor hold structure.
FLOOR_RATIO = 2.0
#: Permutations for the locate p-values (smallest attainable p = 1/(N_PERM+1)).
N_PERM = 499
#: Candidates fitted on fewer training rows than this many per parameter are skipped.
ROWS_PER_PARAM = 10
#: Systematic (type-B) standard uncertainty of a timing offset from linear interpolation of the
#: readings, as a fraction of the sampling step (noise-free simulations: |bias| <= dt/10).
DELTA_SYS_FRACTION = 0.1
#: Bootstrap replicates of the 95 % interval of a thermal lag's tau or a step's time.
N_BOOT_LAG = 200


@dataclasses.dataclass(frozen=True)
class DiscoverOptions:
    """Settings of :func:`discover` (the ``[discover]`` table of a config).

    Attributes:
      candidates: catalogue names to try (default: all of :data:`~bayesmag._src.core.catalogue.CATALOGUE`).
      cv: out-of-sample scheme, ``"time_blocks"`` (contiguous blocks inside every run,
        assigned to ``n_folds`` folds) or ``"by_run"`` (leave one run out).
      n_folds: folds for ``"time_blocks"``.
      block_s: length of a time block in seconds (default: 1/60 of the record, >= 10 rows).
      t0: reference temperature of the base model, or ``"mean"``.
      max_terms: most extensions in the joint model.
      seed: seeds the permutations.
      figures: write figures.
      time_available: whether ``data.time`` holds real time stamps (None: inferred; a time
        column equal to the row index counts as absent).
    """

    candidates: tuple[str, ...] | None = None
    cv: str = "time_blocks"
    n_folds: int = 5
    block_s: float | None = None
    t0: float | str = T0_DEFAULT
    max_terms: int = MAX_TERMS
    seed: int = 0
    figures: bool = True
    time_available: bool | None = None

    def __post_init__(self):
        if self.candidates is not None:
            object.__setattr__(self, "candidates", tuple(self.candidates))
            unknown = sorted(set(self.candidates) - set(C.CATALOGUE))
            if unknown:
                raise ValueError(f"discover candidates {unknown} are not in the catalogue; valid: {sorted(C.CATALOGUE)}.")
        if self.cv not in ("time_blocks", "by_run"):
            raise ValueError(f"discover cv is {self.cv!r}; it must be one of ['time_blocks', 'by_run'].")
        if int(self.n_folds) < 2:
            raise ValueError(f"discover n_folds is {self.n_folds!r}; it must be >= 2.")
        if isinstance(self.t0, str) and self.t0 != "mean":
            raise ValueError(f"discover t0 is {self.t0!r}; it must be a number or 'mean'.")
        if int(self.max_terms) < 1:
            raise ValueError(f"discover max_terms is {self.max_terms!r}; it must be >= 1.")
