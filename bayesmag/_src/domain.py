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


@dataclasses.dataclass(frozen=True)
class Domain:
    """Per-input [low, high] ranges of (Bx, By, Bz) in uT and T in C, widened by ``margin`` of the span."""

    low: tuple[float, float, float, float]
    high: tuple[float, float, float, float]
    margin: float = 0.05

    @classmethod
    def from_data(cls, data, *, margin: float = 0.05) -> "Domain":
        x = np.column_stack([data.b_meas, data.temperature])
        lo, hi = x.min(axis=0), x.max(axis=0)
        pad = margin * (hi - lo) + np.array([0.5, 0.5, 0.5, 0.5])     # absolute floor: 0.5 uT, 0.5 C
        return cls(tuple(map(float, lo - pad)), tuple(map(float, hi + pad)), margin)

    def outside(self, data) -> np.ndarray:
        """(n, 4) boolean: input j of row i lies outside the training range."""
        x = np.column_stack([data.b_meas, data.temperature])
        return (x < np.asarray(self.low)) | (x > np.asarray(self.high))

    def summary(self, data) -> dict:
        out = self.outside(data)
        rows = out.any(axis=1)
        return {
            "n_rows": int(data.n), "n_outside": int(rows.sum()), "fraction_outside": float(rows.mean()),
            "by_input": {n: int(c) for n, c in zip(_NAMES, out.sum(axis=0))},
            "training_ranges": {n: [lo, hi] for n, lo, hi in zip(_NAMES, self.low, self.high)},
        }

    def warning(self, data) -> str | None:
        s = self.summary(data)
        if s["n_outside"] == 0:
            return None
        which = ", ".join(f"{k} ({v} rows)" for k, v in s["by_input"].items() if v)
        return (f"{s['n_outside']} of {s['n_rows']} test rows ({s['fraction_outside']:.0%}) lie outside the "
                f"training domain in {which}: their predictions are extrapolation and their intervals may be far "
                f"too narrow. Train on data that covers them.")
