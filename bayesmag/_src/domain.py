"""The calibration's training domain, and which rows of a recording fall outside it.

A calibration extrapolates outside the inputs it was fitted on (the Belsten recordings
without run 6 never saw temperatures above 25 C: predictions at 40-66 C are off by tens of
uT while the model's own uncertainty stays small). Rows outside the per-input ranges of the
training data (with a small margin) are flagged, and the job reports their count.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["Domain"]

_NAMES = ("bx_meas", "by_meas", "bz_meas", "temperature")


def _box(x: np.ndarray, margin: float, floor: float):
    lo, hi = x.min(axis=0), x.max(axis=0)
    pad = margin * (hi - lo) + floor
    return tuple(map(float, lo - pad)), tuple(map(float, hi + pad))


@dataclasses.dataclass(frozen=True)
class Domain:
    """Training ranges, widened by ``margin`` of the span (floor 0.5 uT / 0.5 C).

    ``low``/``high``: inputs (Bx, By, Bz measured in uT, T in C). ``out_low``/``out_high``:
    the reference field (uT) seen in training; a calibrated value outside it is extrapolation
    in field space even when each measured input is inside its own range.
    """

    low: tuple[float, float, float, float]
    high: tuple[float, float, float, float]
    margin: float = 0.05
    out_low: tuple[float, float, float] | None = None
    out_high: tuple[float, float, float] | None = None

    @classmethod
    def from_data(cls, data, *, margin: float = 0.05) -> "Domain":
        lo, hi = _box(np.column_stack([data.b_meas, data.temperature]), margin, 0.5)
        olo = ohi = None
        if data.b_ref is not None:
            olo, ohi = _box(data.b_ref, margin, 0.5)
        return cls(lo, hi, margin, olo, ohi)

    def outside(self, data, calibrated: np.ndarray | None = None) -> np.ndarray:
        """(n, 4) boolean: input j of row i lies outside the training range.

        With ``calibrated`` (n, 3), a row whose calibrated field leaves the training reference
        range is marked on the field columns too.
        """
        x = np.column_stack([data.b_meas, data.temperature])
        out = (x < np.asarray(self.low)) | (x > np.asarray(self.high))
        if calibrated is not None and self.out_low is not None:
            c = np.asarray(calibrated)
            out[:, :3] |= (c < np.asarray(self.out_low)) | (c > np.asarray(self.out_high))
        return out

    def reasons(self, out: np.ndarray) -> np.ndarray:
        """(n,) strings: why each row of :meth:`outside`'s ``out`` is out of domain ('' when inside)."""
        names = np.array(["field_range"] * 3 + ["temperature"] + ["field_rate"] * 3 + ["temperature_rate"])
        out = np.asarray(out, bool)
        res = []
        for row in out:
            hit = list(dict.fromkeys(names[:row.size][row]))
            res.append(";".join(hit))
        return np.array(res, dtype=object)

    def summary(self, data, calibrated: np.ndarray | None = None) -> dict:
        out = self.outside(data, calibrated)
        rows = out.any(axis=1)
        return {
            "n_rows": int(data.n), "n_outside": int(rows.sum()), "fraction_outside": float(rows.mean()),
            "by_input": {n: int(c) for n, c in zip(_NAMES, out.sum(axis=0))},
            "training_ranges": {n: [lo, hi] for n, lo, hi in zip(_NAMES, self.low, self.high)},
        }

    def warning(self, data, calibrated: np.ndarray | None = None) -> str | None:
        s = self.summary(data, calibrated)
        if s["n_outside"] == 0:
            return None
        which = ", ".join(f"{k} ({v} rows)" for k, v in s["by_input"].items() if v)
        return (f"{s['n_outside']} of {s['n_rows']} test rows ({s['fraction_outside']:.0%}) lie outside the "
                f"training domain in {which}: their predictions are extrapolation and their intervals may be far "
                f"too narrow. Train on data that covers them.")
