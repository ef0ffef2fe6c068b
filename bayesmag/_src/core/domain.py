"""The calibration's training domain, and which rows of a recording fall outside it.

A calibration extrapolates outside the inputs it was fitted on (the Belsten recordings
without run 6 never saw temperatures above 25 C: predictions at 40-66 C are off by tens of
uT while the model's own uncertainty stays small). Rows outside the per-input ranges of the
training data (with a small margin) are flagged, and the job reports their count.

The domain is dynamic too: a sensor read while the field or its temperature changes fast
lags and smears (timing offsets, thermal lag), which a calibration fitted on slow changes has
not seen. The rates |dB/dt| per channel and |dT/dt| are computed within each run (rows in time
order, differences to both time neighbours, the larger kept) and flagged above the training
maximum (with the same margin).
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["Domain", "rates", "REASONS", "REASON_CODES", "budget_row_mask", "budget_rows_note"]

_NAMES = ("bx_meas", "by_meas", "bz_meas", "temperature")
_RATE_NAMES = ("dbx_dt", "dby_dt", "dbz_dt", "dT_dt")
#: Reason of every column of :meth:`Domain.outside`.
REASONS = ("field_range",) * 3 + ("temperature",) + ("field_rate",) * 3 + ("temperature_rate",)
#: Bit of every reason in the numeric ``in_domain_reason`` column of ``bayesmag apply`` output.
REASON_CODES = {"field_range": 1, "temperature": 2, "field_rate": 4, "temperature_rate": 8,
                "magnitude": 16}      # magnitude: a field calibration's predicted |B| outside training's
#: Floor of the margin on the rate limits: 0.5 uT/s for the field, 0.05 C/s for temperature.
RATE_FLOOR = (0.5, 0.5, 0.5, 0.05)


def _box(x: np.ndarray, margin: float, floor: float):
    lo, hi = x.min(axis=0), x.max(axis=0)
    pad = margin * (hi - lo) + floor
    return tuple(map(float, lo - pad)), tuple(map(float, hi + pad))


def rates(data) -> np.ndarray:
    """(n, 4) |dBx/dt|, |dBy/dt|, |dBz/dt| (uT/s) and |dT/dt| (C/s) of the measured inputs.

    Within each run, rows in time order; each row gets the larger absolute difference quotient
    to its two time neighbours (0 for a run of one row). Rows of a run that share a timestamp (whole-second stamps
    of a 4 Hz logger) are first spread evenly up to the next stamp, as :func:`load_belsten` does
    (:func:`~bayesmag._src.core.data.spread_duplicate_times`): skipped, they made the step across a second
    boundary a change over 1 s instead of 0.25 s, and the rates up to 4x too low.
    """
    x = np.column_stack([data.b_meas, data.temperature]).astype(np.float64)
    t = np.asarray(_spread(data).time, np.float64)
    out = np.zeros_like(x)
    for r in np.unique(data.run):
        idx = np.flatnonzero(data.run == r)
        idx = idx[np.argsort(t[idx], kind="stable")]
        if idx.size < 2:
            continue
        dt = np.diff(t[idx])
        with np.errstate(divide="ignore", invalid="ignore"):
            q = np.where(dt[:, None] > 0, np.abs(np.diff(x[idx], axis=0)) / dt[:, None], 0.0)
        q = np.nan_to_num(q, nan=np.inf)                # a non-finite input makes its neighbours' rates infinite
        r_rate = np.zeros((idx.size, 4))
        r_rate[1:] = q
        r_rate[:-1] = np.maximum(r_rate[:-1], q)
        out[idx] = r_rate
    return out


@dataclasses.dataclass(frozen=True)
class Domain:
    """Training ranges, widened by ``margin`` of the span (floor 0.5 uT / 0.5 C).

    ``low``/``high``: inputs (Bx, By, Bz measured in uT, T in C). ``out_low``/``out_high``:
    the reference field (uT) seen in training; a calibrated value outside it is extrapolation
    in field space even when each measured input is inside its own range. ``rate_high``: the
    largest |dB/dt| per channel (uT/s) and |dT/dt| (C/s) seen within training runs, times
    ``1 + margin`` plus :data:`RATE_FLOOR` (None: rates not checked).
    """

    low: tuple[float, float, float, float]
    high: tuple[float, float, float, float]
    margin: float = 0.05
    out_low: tuple[float, float, float] | None = None
    out_high: tuple[float, float, float] | None = None
    rate_high: tuple[float, float, float, float] | None = None
    step: float | None = None      # the training rows' median sampling step within runs (s), the rates' time unit

    @classmethod
    def from_data(cls, data, *, margin: float = 0.05, rates: bool = True) -> "Domain":
        """The domain of ``data``'s rows; ``rates``: also the rate limits (only for rows with times)."""
        lo, hi = _box(np.column_stack([data.b_meas, data.temperature]), margin, 0.5)
        olo = ohi = None
        if data.b_ref is not None:
            olo, ohi = _box(data.b_ref, margin, 0.5)
        rh = step = None
        if rates and getattr(data, "time_given", True):     # rows without times: no rates (per row index is not per s)
            rmax = _rates(data).max(axis=0)
            rh = tuple(float(v) for v in rmax * (1 + margin) + np.asarray(RATE_FLOOR))
            step = sampling_step(data)
        return cls(lo, hi, margin, olo, ohi, rh, step)

    def step_note(self, data, ratio: float = 3.0) -> str | None:
        """A warning when ``data``'s median sampling step differs from training's by more than ``ratio`` (either
        way): the rate limits are per second, so a time column in other units (ms) or absent (rows counted as 1 s
        apart) misreads them; None otherwise, or without rate limits or a step."""
        if self.rate_high is None or not self.step or not getattr(data, "time_given", True):
            return None
        k = repeated_stamps(data)
        if k:
            return (f"{k} of {data.n} rows share their timestamp with another row of their run (whole-second stamps "
                    f"of a faster logger?): the rate checks (in_domain_reason field_rate / temperature_rate) spread "
                    f"them evenly up to the run's next stamp, as the Belsten loader does. Give each row its own time "
                    f"to check the rates on the real ones.")
        new = sampling_step(data)
        if not new or 1 / ratio <= new / self.step <= ratio:
            return None
        return (f"The recording's median time step is {new:.4g} s, {new / self.step:.3g}x the training's "
                f"({self.step:.4g} s). The rate checks (in_domain_reason field_rate / temperature_rate) compare "
                f"|dB/dt| and |dT/dt| per second, so a time column in other units (ms?) or missing (rows are then "
                f"1 s apart) flags the wrong rows. Check that the time column is in seconds.")

    def outside(self, data, calibrated: np.ndarray | None = None) -> np.ndarray:
        """(n, 4) boolean, or (n, 8) with rate limits: input j of row i lies outside the training range.

        Columns: Bx, By, Bz, T values, then (with ``rate_high``) their rates; the reason of every
        column is in :data:`REASONS`. With ``calibrated`` (n, 3), a row whose calibrated field
        leaves the training reference range is marked on the field columns too.
        """
        x = np.column_stack([data.b_meas, data.temperature])
        out = (x < np.asarray(self.low)) | (x > np.asarray(self.high))
        if calibrated is not None and self.out_low is not None:
            c = np.asarray(calibrated)
            out[:, :3] |= (c < np.asarray(self.out_low)) | (c > np.asarray(self.out_high))
        if self.rate_high is not None:
            out = np.concatenate([out, _rates(data) > np.asarray(self.rate_high)], axis=1)
        return out

    @staticmethod
    def reasons(out: np.ndarray) -> np.ndarray:
        """(n,) strings from :meth:`outside`'s result: the reasons a row is out of domain, joined
        by ``;`` in the order ``field_range, temperature, field_rate, temperature_rate`` ('' inside)."""
        out = np.asarray(out, bool)
        names = np.array(REASONS[:out.shape[1]])
        order = ("field_range", "temperature", "field_rate", "temperature_rate")
        hit = {k: out[:, names == k].any(axis=1) for k in order}
        res = np.full(out.shape[0], "", dtype=object)
        for k in order:
            res[hit[k]] = np.where(res[hit[k]] == "", k, res[hit[k]] + ";" + k)
        return res

    def summary(self, data, calibrated: np.ndarray | None = None) -> dict:
        out = self.outside(data, calibrated)
        rows = out.any(axis=1)
        names = (_NAMES + _RATE_NAMES)[:out.shape[1]]
        s = {
            "n_rows": int(data.n), "n_outside": int(rows.sum()), "fraction_outside": float(rows.mean()),
            "by_input": {n: int(c) for n, c in zip(names, out.sum(axis=0))},
            "training_ranges": {n: [lo, hi] for n, lo, hi in zip(_NAMES, self.low, self.high)},
        }
        if self.rate_high is not None:
            s["training_rate_limits"] = dict(zip(_RATE_NAMES, self.rate_high))
            s["by_reason"] = {k: int(v) for k, v in
                              zip(*np.unique(self.reasons(out)[rows].astype(str), return_counts=True))}
        return s

    def warning(self, data, calibrated: np.ndarray | None = None) -> str | None:
        s = self.summary(data, calibrated)
        if s["n_outside"] == 0:
            return None
        which = ", ".join(f"{k} ({v} rows)" for k, v in s["by_input"].items() if v)
        return (f"{s['n_outside']} of {s['n_rows']} test rows ({s['fraction_outside']:.0%}) lie outside the "
                f"training domain in {which}: their predictions are extrapolation and their intervals may be far "
                f"too narrow. Train on data that covers them.")


_rates = rates


def sampling_step(data) -> float | None:
    """The median positive time step between consecutive rows of the same run (s), repeated stamps spread
    (:func:`rates`); None without one."""
    from bayesmag._src.core.physics import median_step
    data = _spread(data)
    return median_step(data.time, data.run)


def repeated_stamps(data) -> int:
    """How many rows share their timestamp with an earlier row of their run."""
    t, run = np.asarray(data.time, np.float64), np.asarray(data.run).reshape(-1)
    o = np.lexsort((t, run))
    return int(np.sum((np.diff(t[o]) == 0) & (run[o][1:] == run[o][:-1])))


def _spread(data):
    """``data`` with its repeated stamps spread (:func:`~bayesmag._src.core.data.spread_duplicate_times`), or itself."""
    if data.n < 2 or not repeated_stamps(data):
        return data
    from bayesmag._src.core.data import spread_duplicate_times
    return spread_duplicate_times(data)


def budget_row_mask(outside: np.ndarray) -> np.ndarray:
    """The test rows the certificate's budget averages over: those inside the calibration domain (its U is stated
    for them only), all rows where none is inside. ``outside``: the (n, k) flags of :meth:`Domain.outside`."""
    inside = ~np.asarray(outside).any(axis=1)
    return inside if inside.any() else np.ones_like(inside)


def budget_rows_note(outside: np.ndarray) -> str:
    """Which test rows :func:`budget_row_mask` keeps, in words (``metrics["uq"]["budget_rows"]``; the report says it).

    Example:
      >>> budget_rows_note(np.array([[False], [True], [False]]))
      '2 in-domain test rows of 3'
    """
    inside = ~np.asarray(outside).any(axis=1)
    n, k = int(inside.size), int(inside.sum())
    return (f"all {n} test rows (all in domain)" if k == n else f"{k} in-domain test rows of {n}" if k
            else f"all {n} test rows (none in domain)")
