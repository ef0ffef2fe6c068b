r"""A saved field calibration applied to new readings: calibrated field, magnitude interval, training domain.

A field calibration (against a scalar reference or the Earth's field) determines the calibrated vector up to the
gauge rotation (:mod:`~bayesmag._src.core.field`), so what it can promise a new recording is the *magnitude*:
the Laplace predictive sd of :math:`\lVert B\rVert` (parameters plus reading noise) times the run's cross-conformal
scale c (:func:`~bayesmag._src.pipeline.field_stage.magnitude_interval_scale`), and the training domain it was
scored in (the ranges of :func:`~bayesmag._src.pipeline.field_stage.field_domain_check`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.stats

from bayesmag._src.core.field import FieldFit

__all__ = ["FieldCalibration", "FIELD_FORMAT", "FIELD_FORMAT_VERSION", "DOMAIN_KEYS", "range_flags", "content_sha256"]

FIELD_FORMAT = "bayesmag-field-calibration"
FIELD_FORMAT_VERSION = 1
#: The training ranges a field calibration keeps (already widened by the domain margin), in this order.
DOMAIN_KEYS = ("bx_meas", "by_meas", "bz_meas", "temperature", "magnitude")


def content_sha256(doc: dict) -> str:
    """sha256 of a JSON document in canonical form (sorted keys, no spaces, floats by ``repr``): the same numbers
    give the same digest whichever writer indented the file."""
    import hashlib
    import json
    return hashlib.sha256(json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def range_flags(u, t, magnitude, ranges: dict, valid=None, half_width=None) -> tuple[np.ndarray, dict]:
    """``(reason, hits)`` of every row against the training ``ranges`` (:data:`DOMAIN_KEYS` -> ``(low, high)``,
    already widened): ``hits`` maps ``field_range`` (a reading Bx, By or Bz outside its range), ``temperature`` and
    ``magnitude`` to boolean rows; ``reason`` joins each row's hits with ``;`` ('' inside). Rows not ``valid`` are
    never flagged. ``magnitude`` is the predicted |B| and ``half_width`` (n,) its interval's half-width: a row is
    flagged ``magnitude`` when its whole interval lies outside the training magnitudes (the true |B| is then, at the
    interval's level, a field training did not see); without ``half_width``, when the predicted |B| does. (A
    constant-field calibration's training magnitudes are one value: without the interval every row whose error
    exceeded the 0.5 uT margin was flagged, i.e. exactly its worst-calibrated rows.)"""
    x = np.column_stack([np.asarray(u, np.float64), np.asarray(t, np.float64), np.asarray(magnitude, np.float64)])
    n = x.shape[0]
    valid = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    hw = np.zeros(n) if half_width is None else np.nan_to_num(np.asarray(half_width, np.float64).reshape(n))
    hits = {"field_range": np.zeros(n, bool), "temperature": np.zeros(n, bool), "magnitude": np.zeros(n, bool)}
    for j, key in enumerate(DOMAIN_KEYS):
        a, b = ranges[key]
        w = hw if key == "magnitude" else 0.0
        hits["field_range" if j < 3 else key] |= valid & ((x[:, j] + w < a) | (x[:, j] - w > b))
    reason = np.full(n, "", dtype=object)
    for k, h in hits.items():
        reason[h] = np.where(reason[h] == "", k, reason[h] + ";" + k)
    return reason, hits


@dataclasses.dataclass(frozen=True)
class FieldCalibration:
    """A field fit with what its run measured: the conformal scale of its magnitude sd, level, training ranges.

    ``ranges`` maps each of :data:`DOMAIN_KEYS` to ``(low, high)`` (uT, C), already widened by the run's margin;
    ``reference_column`` names the recording's scalar-magnetometer column the fit read (None: a constant field or
    a vector reference), so a new recording holding it can be scored. ``transfer_sd`` is the between-session sd of
    the magnitude (uT; :func:`~bayesmag._src.pipeline.field_stage.magnitude_transfer`) and ``transfer_method`` how
    it was estimated (``"leave_one_run_out"``); None: the run estimated none (too few sessions, or
    ``[uq] transfer = "off"``, or a file written before field calibrations had one).

    Example:
      >>> from bayesmag.simulate import simulate_field
      >>> from bayesmag.field import Scalar, fit_field
      >>> c = simulate_field("dance", n=400, seed=0)
      >>> fit = fit_field(c.data.b_meas, c.data.temperature, c.f_ref, Scalar())
      >>> cal = FieldCalibration(fit, 1.0, 0.95, {k: (-1e3, 1e3) for k in DOMAIN_KEYS})
      >>> p = cal.predict(c.data.b_meas, c.data.temperature)
      >>> bool(np.mean(np.abs(p["magnitude"] - c.f_ref) <= p["magnitude_upper"] - p["magnitude"]) > 0.9)
      True
    """

    fit: FieldFit
    interval_scale: float = 1.0
    level: float = 0.95
    ranges: dict = dataclasses.field(default_factory=dict)
    reference_column: str | None = None
    transfer_sd: float | None = None
    transfer_method: str | None = None

    @property
    def train_max_ut(self) -> float:
        """The largest |reading component| (uT) of the training ranges: the unit checks compare new readings with it."""
        return max(abs(v) for k in DOMAIN_KEYS[:3] for v in self.ranges[k])

    def __repr__(self) -> str:
        return (f"FieldCalibration({self.fit!r}, interval_scale={self.interval_scale:.4g}, level={self.level:g}, "
                f"reference_column={self.reference_column!r}, transfer_sd={self.transfer_sd!r})")

    def predict(self, u, t, *, level: float | None = None, chunk_size: int = 200_000,
                field_unit: str | None = None, new_session: bool = True, warn: bool = True) -> dict:
        """Calibrated field (n, 3) in the gauge frame, its magnitude with sd and interval, and the domain flags.

        ``u`` (n, 3) readings in uT, ``t`` (n,) temperatures in C. Rows with a non-finite reading or temperature get
        NaN and ``valid`` False; the interval's lower end is clipped at 0. ``in_domain_reason`` joins
        ``field_range`` (a reading outside training's), ``temperature`` and ``magnitude`` (the predicted magnitude
        outside the training reference magnitudes) with ``;``; '' inside (or invalid). The readings are checked
        against the training field as ``bayesmag apply`` checks them (nT, mT or gauss refused, kelvin refused:
        :class:`~bayesmag.DataError`); ``field_unit="uT"`` declares a genuine field far below the training one.
        ``new_session`` (default True: a recording given to a saved calibration is a new session) adds the
        between-session sd :attr:`transfer_sd` to ``magnitude_total`` (``magnitude_transfer``; 0 without one);
        False predicts rows of the training sessions. ``warn`` (default True) raises what ``bayesmag apply`` prints as
        WARNING lines as :class:`~bayesmag.CalibrationWarning`: no between-session term for a new session
        (:meth:`no_transfer_warning`), rows outside the training domain.
        """
        u, t = np.asarray(u, np.float64), np.asarray(t, np.float64)
        if u.ndim != 2 or u.shape[1] != 3:
            raise ValueError(f"readings must be an (n, 3) array of Bx, By, Bz (uT), got shape {u.shape}"
                             + (" (transposed? pass u.T)" if u.ndim == 2 and u.shape[0] == 3 else ""))
        if t.ndim != 1 or t.shape[0] != u.shape[0]:
            raise ValueError(f"temperatures must be an (n,) array with one value per reading ({u.shape[0]} rows), "
                             f"got shape {t.shape}")
        level = self.level if level is None else float(level)
        if not 0 < level < 1:
            raise ValueError(f"level {level} must be in (0, 1)")
        n = u.shape[0]
        valid = np.isfinite(u).all(axis=1) & np.isfinite(t)
        if field_unit not in (None, "uT"):
            raise ValueError(f"field_unit = {field_unit!r}; the readings must be in uT (convert them), and "
                             f"field_unit = 'uT' declares a field far below the training one")
        if valid.any() and self.ranges:
            from bayesmag._src.core.data import CalibrationData, check_units
            check_units(CalibrationData(u[valid], t[valid], None, field_unit=field_unit), train_max_ut=self.train_max_ut,
                        origin="the readings given to FieldCalibration.predict", fix="Convert the readings to uT",
                        declare="field_unit='uT'", temperature_fix="Subtract 273.15")
        out = {k: np.full((n, 3) if k == "calibrated" else n, np.nan) for k in
               ("calibrated", "magnitude", "magnitude_epistemic", "magnitude_noise", "magnitude_transfer",
                "magnitude_total", "magnitude_lower", "magnitude_upper")}
        tau = float(self.transfer_sd or 0.0) if new_session else 0.0
        z = float(scipy.stats.norm.ppf(0.5 + level / 2))
        rows = np.flatnonzero(valid)
        for lo in range(0, rows.size, chunk_size):
            r = rows[lo:lo + chunk_size]
            pm = self.fit.predict_magnitude(u[r], t[r])
            total = np.sqrt((self.interval_scale * pm["total"]) ** 2 + tau**2)
            out["calibrated"][r] = self.fit.calibrate(u[r], t[r])
            out["magnitude"][r] = pm["mean"]
            out["magnitude_epistemic"][r] = pm["epistemic"]
            out["magnitude_noise"][r] = pm["noise"]
            out["magnitude_transfer"][r] = tau
            out["magnitude_total"][r] = total
            out["magnitude_lower"][r] = np.maximum(pm["mean"] - z * total, 0.0)      # a magnitude is >= 0
            out["magnitude_upper"][r] = pm["mean"] + z * total
        reason, hits = (range_flags(u, t, out["magnitude"], self.ranges, valid, z * out["magnitude_total"])
                        if self.ranges else (np.full(n, "", dtype=object), {}))
        out.update(valid=valid, in_domain=valid & (reason == ""), in_domain_reason=reason, level=level)
        if warn:
            import warnings

            from bayesmag._src.core.data import CalibrationWarning, user_stacklevel
            texts = [self.no_transfer_warning()] if new_session and self.transfer_sd is None else []
            n_out = int((valid & (reason != "")).sum())
            if n_out:
                kinds = {k: int(h.sum()) for k, h in hits.items()}
                texts.append(f"{n_out} of {n} rows lie outside the calibration's training domain (in_domain=false; "
                             + ", ".join(f"{k} {v}" for k, v in kinds.items() if v)
                             + "): their values are extrapolation and their intervals may be far too narrow."
                             + ("" if self.ranges else " (This calibration holds no training ranges: built without "
                                "them, every row counts as inside.)"))
            elif not self.ranges:
                texts.append("this FieldCalibration holds no training ranges (built without them): every row is "
                             "marked in_domain; load a run's calibration (bayesmag.load_field) to have them checked.")
            for t_ in texts:
                warnings.warn(t_, CalibrationWarning, stacklevel=user_stacklevel())
        return out

    def no_transfer_warning(self) -> str:
        """Why this calibration's magnitude intervals hold no between-session term, as ``apply`` says it."""
        return ("this field calibration holds no between-session (transfer) term (its run held fewer than 3 sessions "
                "(runs) whose rows overlap, or set [uq] transfer = \"off\", or it was written before field "
                "calibrations had one): the magnitude intervals cover only the error within the session it was "
                "fitted in and can be far too narrow for a new recording (simulated vehicles whose hard iron moves "
                "0.3 uT between flights: one or two training flights covered 20-89 % of new flights). Calibrate on "
                "3 or more recorded sessions that overlap in field and temperature to estimate it.")

    def to_json(self) -> dict:
        """``field_params.json``: the fit's :meth:`~bayesmag._src.core.field.FieldFit.to_json` plus ``predictive``,
        and ``content_sha256``, the sha256 of the rest (:func:`content_sha256`): :meth:`from_json` refuses a file
        whose numbers were edited (a value that passes every range check would otherwise be applied)."""
        doc = self._doc()
        return {**doc, "content_sha256": content_sha256(doc)}

    def _doc(self) -> dict:
        return {"format": FIELD_FORMAT, "format_version": FIELD_FORMAT_VERSION, **self.fit.to_json(),
                "predictive": {"interval_scale": self.interval_scale, "level": self.level,
                               "domain_ranges": {k: [float(v) for v in self.ranges[k]] for k in self.ranges},
                               "scalar_column": self.reference_column,
                               "transfer": None if self.transfer_sd is None else
                               {"sd": float(self.transfer_sd), "method": self.transfer_method}}}

    @classmethod
    def from_json(cls, doc: dict) -> "FieldCalibration":
        """Read :meth:`to_json`'s document back; ``ValueError`` naming the key for anything missing or malformed."""
        fit = FieldFit.from_json(doc)
        v = doc.get("format_version")
        if doc.get("format") != FIELD_FORMAT or "predictive" not in doc:
            raise ValueError("field_params.json has no 'predictive' section (written before bayesmag could apply a "
                             "field calibration): re-run `bayesmag run` on the field config")
        if isinstance(v, bool) or not isinstance(v, int) or v > FIELD_FORMAT_VERSION:
            raise ValueError(f"field_params.json has format_version {v!r}; this bayesmag reads "
                             f"{FIELD_FORMAT_VERSION} (a newer file: upgrade bayesmag)")
        p = doc["predictive"]
        try:
            scale, level = float(p["interval_scale"]), float(p["level"])
            ranges = {k: (float(p["domain_ranges"][k][0]), float(p["domain_ranges"][k][1])) for k in DOMAIN_KEYS}
        except (KeyError, TypeError, ValueError, IndexError) as e:
            raise ValueError(f"field_params.json: 'predictive' must hold interval_scale, level and domain_ranges "
                             f"{list(DOMAIN_KEYS)} ({e!r})") from None
        if not (np.isfinite(scale) and 0 < scale <= 100 and 0 < level < 1):
            raise ValueError(f"field_params.json: interval_scale {scale} must be in (0, 100] (a conformal scale is "
                             f"about 1) and level {level} in (0, 1)")
        bad = [k for k, (a, b) in ranges.items() if not (np.isfinite(a) and np.isfinite(b) and a < b)]
        if bad:
            raise ValueError(f"field_params.json: domain_ranges {bad} must be finite [low, high] with low < high")
        column = p.get("scalar_column")
        tr = p.get("transfer")          # absent in files written before the field calibration had one: none
        if tr is not None:
            sd = tr.get("sd") if isinstance(tr, dict) else None
            if (isinstance(sd, bool) or not isinstance(sd, (int, float)) or not np.isfinite(sd) or sd < 0
                    or not isinstance(tr.get("method"), str)):
                raise ValueError(f"field_params.json: 'predictive.transfer' must be null or {{\"sd\": a finite number "
                                 f">= 0 (uT), \"method\": a string}}, got {tr!r}")
            tr = (float(sd), tr["method"])
        # the gains fit_field now refuses (a declared field off by a factor: H for F, a unit; or a degenerate fit) in
        # a file written before that check: applying it would scale every field by the same wrong factor
        from bayesmag._src.core.field import FIELD_SCALE_REFUSE, GAIN_REFUSE, judge_gains
        meas = fit.model.measurement
        g = judge_gains(fit)
        if g["verdict"] == "refuse":
            declared = (f"field F = {meas.field:g} uT" if getattr(meas, "field", None) is not None else
                        "scalar reference" if meas.name == "scalar" else "field (fitted)")
            raise ValueError(f"field_params.json: the gains (singular values of S) "
                             f"{', '.join(f'{v:.3g}' for v in g['gains'])} (overall {g['overall']:.3g}) are not a "
                             f"magnetometer's (overall {FIELD_SCALE_REFUSE[0]:.3g}-{FIELD_SCALE_REFUSE[1]:g}, each "
                             f"{GAIN_REFUSE[0]:g}-{GAIN_REFUSE[1]:g}, diagonal positive): the run's declared {declared} "
                             f"was probably wrong (H given for the total intensity F, or another unit) or its fit "
                             f"degenerate; re-run `bayesmag run` with the site's total intensity F in uT")
        cal = cls(fit, scale, level, ranges, column if isinstance(column, str) and column else None,
                  *(tr or (None, None)))
        stated = doc.get("content_sha256")      # files written before it have none: read as they are
        if stated is not None and stated != content_sha256({k: v for k, v in doc.items() if k != "content_sha256"}):
            raise ValueError("field_params.json was edited or damaged after the run wrote it: its content no longer "
                             f"matches its content_sha256 ({str(stated)[:12]}...); a calibration is never applied "
                             "from a changed file. Re-run `bayesmag run` on the field config (or restore the file).")
        return cal
