"""Calibrations users keep: a versioned, self-contained, non-pickle artifact; load it and apply it.

A run folder holds the calibration as two files:

* ``calibration.json`` -- format name and version, package version, the physics model
  (terms and transforms with their settings), parameter names, the input-noise covariance,
  residual standard deviations, the training domain, the likelihood family, the resolved
  config, and the names of the arrays below;
* ``calibration.npz`` -- numeric arrays (``theta`` (3, p), ``cov`` (3, p, p), ``transfer_sd`` (3,)
  the between-session sd, ``interval_scale`` (3,) the conformal interval factor when the hybrid
  stage set one, and, when the hybrid stage ran, the network weights and standardisation under
  ``network/...`` keys; a deep ensemble of K networks (the job's cross-conformal fold networks)
  under ``network/member<k>/...`` with ``network.members = K`` in the JSON and format version 2),
  written with ``numpy.savez`` (loaded with ``allow_pickle=False``).

Together they describe one :class:`~bayesmag._src.core.predictor.Predictor`: :func:`save_calibration`
writes it, :meth:`Calibration.predictor` rebuilds it, and :meth:`Calibration.predict` only chunks
rows through it.

:func:`load` returns a :class:`Calibration` whose :meth:`~Calibration.predict` is sklearn-like:
it takes a recording (no reference needed) and returns calibrated values with their
uncertainty parts (the ``transfer`` part for a new session included), a central interval, an
``in_domain`` flag and its ``in_domain_reason`` per row.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from bayesmag._src.core.jsonio import write_json
from bayesmag._src.core.data import AXES, CalibrationData
from bayesmag._src.core.domain import Domain
from bayesmag._src.core.frames import frame_io
from bayesmag._src.core.physics import PhysicsModel, ThermoAffine

__all__ = ["Calibration", "save_calibration", "load", "validate_artifact", "ArtifactError", "FORMAT",
           "FORMAT_VERSION"]

FORMAT = "bayesmag.calibration"
FORMAT_VERSION = 1
#: Format version of a calibration whose network is a deep ensemble (``network/member<k>/...``): older
#: bayesmag versions then refuse it by version instead of missing weights. Everything else stays version 1.
ENSEMBLE_FORMAT_VERSION = 2
#: Versions this code reads (older ones listed here once a converter exists).
READABLE_VERSIONS = (1, 2)


class ArtifactError(ValueError):
    """A calibration folder that cannot be loaded; the message says exactly why."""


#: Plausible magnitudes of saved numbers: parameters, noise model and domain ("value"; a gain or offset of
#: 1e8 is already absurd), variances ("variance": cov, s2) and temperatures (C). Larger ones are damage.
_MAX_ABS = {"value": 1e8, "variance": 1e16, "temperature": 1e4, "domain": 1e12}


def _component_registry() -> dict[str, type]:
    from bayesmag._src.core import catalogue  # noqa: F401  (registers catalogue terms)
    from bayesmag._src.core.physics import EXTRA_TERMS
    return {"thermo_affine": ThermoAffine, **EXTRA_TERMS}


def model_to_json(model: PhysicsModel) -> dict:
    def one(c):
        return {"name": c.name, "settings": {f.name: getattr(c, f.name) for f in dataclasses.fields(c)}}
    return {"terms": [one(t) for t in model.terms], "transforms": [one(t) for t in model.transforms]}


def _check_settings(cls, name: str, settings: dict) -> None:
    """Each saved setting of a physics component has its field's type: numbers finite and plausible (``t0`` a
    temperature in C), booleans booleans. Refused with :class:`ArtifactError` naming the setting."""
    if not isinstance(settings, dict):
        raise ArtifactError(f"field 'model' component {name!r}: 'settings' must be a table; got {settings!r}.")
    for f in dataclasses.fields(cls):
        if f.name not in settings or f.default is dataclasses.MISSING:
            continue
        v, key = settings[f.name], f"model.{name}.{f.name}"
        if isinstance(f.default, bool):
            if not isinstance(v, bool):
                raise ArtifactError(f"field '{key}' = {v!r} must be true or false; the file is damaged.")
        elif isinstance(f.default, (int, float)):
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ArtifactError(f"field '{key}' = {v!r} must be a number, not {type(v).__name__}; the file "
                                    f"was edited or is damaged.")
            lo, hi = (-273.15, _MAX_ABS["temperature"]) if f.name == "t0" else (-_MAX_ABS["value"], _MAX_ABS["value"])
            if not (math.isfinite(v) and lo <= v <= hi):
                raise ArtifactError(f"field '{key}' = {v!r} must be finite and within [{lo:g}, {hi:g}]"
                                    + (" (a temperature in C)" if f.name == "t0" else "") + "; the file is damaged.")


def model_from_json(d: dict) -> PhysicsModel:
    reg = _component_registry()

    def build(item):
        name = item["name"]
        if name not in reg:
            raise ArtifactError(f"the calibration uses physics component {name!r}, which this bayesmag does not "
                                f"know (known: {sorted(reg)}); it was written by another bayesmag version: "
                                f"upgrade bayesmag (pip install -U bayesmag) or use the version that wrote it.")
        _check_settings(reg[name], name, item["settings"])
        return reg[name](**item["settings"])
    return PhysicsModel(tuple(build(t) for t in d["terms"]), tuple(build(t) for t in d["transforms"]))


@dataclasses.dataclass(frozen=True)
class Calibration:
    """A fitted calibration: physics parameters and covariance, noise model, domain, optional network."""

    model: PhysicsModel
    theta: np.ndarray
    cov: np.ndarray
    sigma_in: np.ndarray
    residual_sd: np.ndarray
    domain: Domain
    likelihood: str = "gaussian"
    level: float = 0.95
    config: dict = dataclasses.field(default_factory=dict)
    network: dict | None = None          # {"meta": {...}, "arrays": {name: array}} when the hybrid stage ran
    package_version: str = ""
    s2: np.ndarray | None = None
    transfer_sd: np.ndarray | None = None    # (3,) between-session sd added for new recordings
    interval_scale: np.ndarray | None = None  # (3,) conformal interval factor of the hybrid prediction
    sessions: Any = None                      # hierarchical session posterior (row-dependent transfer sd) or None
    network_transfer_sd: np.ndarray | None = None  # (3,) the network's own new-session sd ([uq] transfer_networks)

    @property
    def param_names(self):
        return self.model.param_names

    def __repr__(self) -> str:
        terms = "+".join(c.name for c in self.model.components)
        net = "none"
        if self.network is not None:
            k = self.network["meta"].get("members")
            net = f"ensemble of {k}" if k else "one"
        ver = f", bayesmag {self.package_version}" if self.package_version else ""
        return (f"Calibration({terms}, {self.theta.shape[1]} parameters per axis, likelihood={self.likelihood!r}, "
                f"level={self.level:g}, network={net}{ver})")

    def physics_fit(self):
        """A :class:`~bayesmag.PhysicsFit`-like view for :func:`~bayesmag.physics_uncertainty`."""
        from bayesmag._src.core.fit import PhysicsFit
        s2 = self.s2 if self.s2 is not None else self.residual_sd**2
        empty = ({}, {}, {})
        return PhysicsFit(model=self.model, theta=self.theta, cov=self.cov, s2=s2, n=0,
                          rmse_in_sample=np.full(3, np.nan), result=("converged",) * 3, n_steps=np.zeros(3),
                          covariance_method="", cov_info=empty, diagnostics=empty)

    def _train_noise(self) -> float:
        """The input-noise sd of the measured field (uT, median over the axes) the calibration was fitted with."""
        return float(np.median(np.sqrt(np.maximum(np.diag(np.asarray(self.sigma_in))[:3], 0.0))))

    def _train_max(self) -> float:
        return float(np.maximum(np.abs(np.asarray(self.domain.low[:3])), np.abs(np.asarray(self.domain.high[:3]))).max())

    def predictor(self, *, method: str = "auto", n_params: int = 100, n_qmc: int = 256, seed: int = 0,
                  chunk_size: int = 256):
        """The saved :class:`~bayesmag._src.core.predictor.Predictor` with these physics-UQ settings."""
        from bayesmag._src.core.predictor import Predictor, UQOptions
        net, passes, nseed, fusion = None, 100, 0, "moment_match"
        if self.network is not None:
            meta = self.network["meta"]
            net = network_from_artifact(self.network)
            passes, nseed, fusion = meta["passes"], meta["seed"], meta.get("fusion", "moment_match")
        return Predictor(fit=self.physics_fit(), sigma_in=self.sigma_in, residual_sd=self.residual_sd, network=net,
                         passes=passes, network_seed=nseed, fusion=fusion, transfer_sd=self.transfer_sd,
                         scale=self.interval_scale, domain=self.domain,
                         uq=UQOptions(method, n_params, n_qmc, seed, chunk_size), sessions=self.sessions,
                         network_transfer_sd=self.network_transfer_sd, level=self.level)

    def predict(self, data, *, level: float | None = None, method: str = "auto",
                n_params: int = 100, n_qmc: int = 256, seed: int = 0, chunk_size: int = 100_000,
                new_session: bool = True, progress: bool = False, columns: dict | None = None,
                field_unit: str | None = None, temperature_unit: str = "C",
                check_units: bool = True, check_rates: bool | None = None,
                warn: bool = True) -> "dict[str, np.ndarray] | pandas.DataFrame":
        """Calibrated field and uncertainty for every row of ``data`` (reference columns not needed).

        Args:
          data: :class:`~bayesmag.CalibrationData`, a pandas DataFrame (canonical names or ``columns``),
            or a NumPy array (n, 4) ``bx_meas, by_meas, bz_meas, temperature`` (``data.ARRAY_COLUMNS``).
          level: central interval level in (0, 1) (default: the calibration's).
          field_unit, temperature_unit: declared units (converted to uT and C); by default the
            values are checked to be in uT and C against the training range: nT, mT, gauss and
            kelvin are refused (``frames.as_calibration_data``). ``check_units=False`` skips that
            check for rows the caller checked already (``bayesmag apply``).
          check_rates: check the field and temperature rates against the training domain (reasons
            ``field_rate``, ``temperature_rate``); default: when ``data`` has times (a CalibrationData made
            with times, ``time_given``, or a DataFrame with a ``time`` column), not for a NumPy array (its rows
            have no time: the rates of consecutive rows would be read per row index, not per second).

        Returns:
          A DataFrame for a DataFrame (columns ``x_calibrated, x_lower, ...`` and the flags, the input's
          index); otherwise a dict of (n, 3) arrays ``calibrated, aleatoric_physics, epistemic_physics,
          residual_physics, total, lower, upper`` (plus ``aleatoric_nn, epistemic_nn`` with a network,
          and ``transfer`` when the calibration holds a transfer sd) and (n,) arrays ``in_domain``,
          ``in_domain_reason`` (strings, '' inside) and ``valid``.

          warn: raise what ``bayesmag apply`` prints as WARNING lines, each a :class:`~bayesmag.CalibrationWarning`:
            a new session (``new_session``) without a between-session term (:func:`new_session_notes`) and the
            rows outside the training domain (``apply`` passes False: it prints them itself).

        Rows with non-finite inputs are not dropped: their outputs are NaN and ``valid`` is False.
        Every chunk is predicted by :meth:`predictor`. ``new_session`` (default True: ``data`` is a
        new recording) adds the transfer part; False treats the rows as from the training sessions.
        """
        from bayesmag._src.core.frames import as_calibration_data, is_frame, prediction_frame

        if level is not None:
            from bayesmag._src.core.predictor import check_level
            level = check_level(level)
        if is_frame(data):
            index = data.index
            if check_rates is None:
                check_rates = (columns or {}).get("time", "time") in data.columns
            out = self.predict(as_calibration_data(data, columns=columns, field_unit=field_unit,
                                                   temperature_unit=temperature_unit, train_max_ut=self._train_max(),
                                                   what="the data given to predict",
                                                   train_noise_ut=self._train_noise()),
                               level=level, method=method, n_params=n_params, n_qmc=n_qmc, seed=seed,
                               chunk_size=chunk_size, new_session=new_session, progress=progress, check_units=False,
                               check_rates=check_rates, warn=warn)
            return prediction_frame(out, index)
        if check_rates is None:
            check_rates = isinstance(data, CalibrationData) and data.time_given
        if check_units or not isinstance(data, CalibrationData):
            data = as_calibration_data(data, columns=columns, field_unit=field_unit, temperature_unit=temperature_unit,
                                       train_max_ut=self._train_max(), what="the data given to predict",
                                       train_noise_ut=self._train_noise())
        level = self.level if level is None else level
        n = data.n
        x = np.column_stack([data.b_meas, data.temperature])
        valid = np.isfinite(x).all(axis=1) & np.isfinite(data.time)
        names = ["calibrated", "aleatoric_physics", "epistemic_physics", "residual_physics", "total", "lower", "upper"]
        if self.network is not None:
            names += ["aleatoric_nn", "epistemic_nn"]
        out = {k: np.full((n, 3), np.nan) for k in names}
        idx = np.flatnonzero(valid)
        base = self.predictor(method=method, n_params=n_params, n_qmc=n_qmc, seed=seed)
        # a term whose features depend on earlier rows (hysteresis) is evaluated on the whole valid series once, so
        # the chunks below continue its history instead of restarting it
        from bayesmag._src.core.physics import inputs_from_data
        from bayesmag._src.core.physics_uq import history_columns
        hist = history_columns(self.model, inputs_from_data(data.subset(idx))) if self.model.has_history else None
        # input transforms (thermal lag, timing offset) see a series: each chunk is predicted with the rows its
        # transforms remember on both sides (as they would on the whole recording), then those rows are dropped
        pad = 0
        if self.model.transforms and idx.size > chunk_size:
            from bayesmag._src.core.physics import median_step
            need = self.model.memory_rows(self.theta, median_step(np.asarray(data.time)[idx]) or 1.0)
            pad = chunk_size if need is None else min(int(need), 10 * chunk_size)
        starts = range(0, idx.size, chunk_size)
        if progress:
            from tqdm.auto import tqdm
            starts = tqdm(starts, desc="apply", unit="chunk", leave=False)
        for lo in starts:
            rows = idx[lo:lo + chunk_size]
            pr = dataclasses.replace(base, uq=dataclasses.replace(base.uq, chunk_size=min(4096, max(256, rows.size))),
                                     domain=None)
            a, b = max(0, lo - pad), min(idx.size, lo + rows.size + pad)     # the chunk with its context
            pred = pr.predict(data.subset(idx[a:b]), new_session=new_session,
                              history=None if hist is None else tuple(None if h is None else h[a:b] for h in hist))
            keep = slice(lo - a, lo - a + rows.size)
            lo_, hi_ = pred.interval(level)
            out["calibrated"][rows], out["total"][rows] = pred.mean[keep], pred.total[keep]
            out["lower"][rows], out["upper"][rows] = lo_[keep], hi_[keep]
            for k, v in pred.parts.items():
                if k == "residual_physics" and self.network is not None:
                    continue
                out.setdefault(k, np.full((n, 3), np.nan))[rows] = np.broadcast_to(v, pred.mean.shape)[keep]
        out["residual_physics"][idx] = np.broadcast_to(self.residual_sd, (idx.size, 3))
        valid = valid & np.all([np.isfinite(out[k]).all(axis=1) for k in ("calibrated", "total", "lower", "upper")],
                               axis=0)                     # a NaN output is never valid
        in_dom = np.zeros(n, dtype=bool)
        reason = np.full(n, "invalid", dtype=object)
        outside = self.domain.outside(data.subset(valid), out["calibrated"][valid])
        if not check_rates:
            outside = outside[:, :4]                    # values only: no time, no rates
        in_dom[valid] = ~outside.any(axis=1)
        reason[valid] = self.domain.reasons(outside)
        out["in_domain"] = in_dom
        out["in_domain_reason"] = reason
        out["valid"] = valid
        if warn:
            import warnings

            from bayesmag._src.core.data import CalibrationWarning, user_stacklevel
            n_out = int((~in_dom & valid).sum())
            step = self.domain.step_note(data) if check_rates and self.domain is not None else None
            for w in [*(new_session_notes(self) if new_session else []), step,
                      n_out and out_of_domain_note(n_out, n, reason[~in_dom & valid])]:
                if w:
                    warnings.warn(w[0].upper() + w[1:], CalibrationWarning, stacklevel=user_stacklevel())
        return out


def new_session_notes(cal) -> list[str]:
    """What a new recording does not get from the calibration: a between-session (transfer) term, and its terms
    bound to training runs (``run_offset``, ``run_step``: :func:`~bayesmag._src.core.physics.new_session_runs`)."""
    notes = []
    tsd = getattr(cal, "transfer_sd", None)
    if getattr(cal, "sessions", None) is None and (tsd is None or not np.any(np.asarray(tsd, float) > 0)):
        fleet = isinstance(getattr(cal, "config", None), dict) and "sensor_id" in cal.config
        why = ("a `bayesmag fleet` sensor: fleets do not estimate one" if fleet else
               "its training data held one run, or [uq] transfer = \"off\"")
        fix = ("For one, calibrate this sensor alone with `bayesmag run` on at least 3 sessions ([uq] transfer = "
               "\"loro\")." if fleet else "Calibrate on at least 3 sessions for a transfer term.")
        notes.append(f"the calibration holds no between-session (transfer) term ({why}): the intervals of this "
                     f"recording, a new session, cover only the error within a session and can be far too narrow. "
                     + fix)
    bound = [t.name for t in cal.model.terms if t.bound_runs()]
    if not bound:
        return notes
    it = "it" if len(bound) == 1 else "them"
    return notes + [f"the calibration's {', '.join(bound)} describe{'s' if len(bound) == 1 else ''} training runs "
            f"{list(cal.model.bound_runs)} only: this recording is calibrated without {it} (as a run with no offset "
            f"of its own and no step; run ids are not matched), and the spread between runs is in the transfer part."]


#: What each reason of a vector calibration's domain check means, for :func:`out_of_domain_note`.
_REASON_TEXT = {"field_range": "a reading or the calibrated field beyond the training range",
                "temperature": "the temperature outside the training span",
                "field_rate": "the field changing faster than in training",
                "temperature_rate": "the temperature changing faster than in training"}


def out_of_domain_counts(reasons) -> dict[str, int]:
    """How many rows each reason of :data:`~bayesmag._src.core.domain.REASONS` flags, from the rows' ``;``-joined
    reason strings (a row outside for two reasons counts under both); reasons no row has are left out."""
    split = [str(r).split(";") for r in np.asarray(reasons, dtype=object).reshape(-1)]
    counts = {k: sum(k in r for r in split) for k in _REASON_TEXT}
    return {k: v for k, v in counts.items() if v}


def out_of_domain_note(n_out: int, n: int, reasons=None) -> str:
    """The rows of a prediction outside the calibration's training domain, as ``apply`` and ``predict`` say it; with
    ``reasons`` (the rows' ``in_domain_reason`` strings, or :func:`out_of_domain_counts`' dict) the count of each
    reason, with what it means, so that the user knows what to fix."""
    counts = reasons if isinstance(reasons, dict) else (None if reasons is None else out_of_domain_counts(reasons))
    why = ""
    if counts:
        why = "; " + ", ".join(f"{k} {v} ({_REASON_TEXT.get(k, k)})" for k, v in counts.items() if v)
    return (f"{n_out} of {n} rows lie outside the calibration's training domain (in_domain=false{why}): their values "
            f"are extrapolation and their intervals may be far too narrow.")


def save_calibration(path: Path, predictor, *, config: dict, level: float = 0.95) -> None:
    """Write the :class:`~bayesmag._src.core.predictor.Predictor` as ``calibration.json`` and ``calibration.npz``
    into folder ``path``."""
    from bayesmag._src.core.version import __version__
    fit = predictor.fit
    cov = np.asarray(fit.cov, np.float64)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))         # exactly symmetric: the loader checks it (issue 21 #5)
    arrays = {"theta": np.asarray(fit.theta), "cov": cov, "sigma_in": np.asarray(predictor.sigma_in),
              "residual_sd": np.asarray(predictor.residual_sd, dtype=np.float64), "s2": np.asarray(fit.s2)}
    if predictor.transfer_sd is not None:
        arrays["transfer_sd"] = np.asarray(predictor.transfer_sd, np.float64)
    if getattr(predictor, "network_transfer_sd", None) is not None:
        arrays["network_transfer_sd"] = np.asarray(predictor.network_transfer_sd, np.float64)
    if predictor.scale is not None:
        arrays["interval_scale"] = np.asarray(predictor.scale, np.float64)
    sessions_meta = None
    if getattr(predictor, "sessions", None) is not None:      # hierarchical transfer model (docs/sessions.md)
        sessions_meta = predictor.sessions.meta()
        for k, v in predictor.sessions.as_arrays().items():
            arrays[f"sessions/{k}"] = np.asarray(v, np.float64)
    meta_net, version = None, FORMAT_VERSION
    if predictor.network is not None:
        network = network_to_artifact(predictor.network, passes=predictor.passes, seed=predictor.network_seed,
                                      fusion=predictor.fusion)
        meta_net = network["meta"]
        if "members" in meta_net:
            version = ENSEMBLE_FORMAT_VERSION
        for k, v in network["arrays"].items():
            arrays[f"network/{k}"] = np.asarray(v)
    doc = {
        "format": FORMAT, "format_version": version, "package_version": __version__,
        "model": model_to_json(fit.model), "param_names": list(fit.model.param_names),
        "axes": list(AXES), "likelihood": predictor.family, "level": level,
        "domain": dataclasses.asdict(predictor.domain), "config": config, "network": meta_net,
        **({"sessions": sessions_meta} if sessions_meta is not None else {}),
        "arrays": {"file": "calibration.npz", "keys": sorted(arrays),
                   "sha256": {k: array_sha256(v) for k, v in sorted(arrays.items())}},
        "units": {"field": "uT", "temperature": "C", "time": "s"},
    }
    bad = [k for k, v in arrays.items() if np.issubdtype(np.asarray(v).dtype, np.number)
           and not np.isfinite(np.asarray(v)).all()]
    if bad:
        raise ArtifactError(f"the calibration to save holds NaN/inf in {bad[:3]}; it was not written.")
    np.savez(Path(path) / "calibration.npz", **arrays)
    write_json(Path(path) / "calibration.json", doc)


def load(path: str | Path) -> Calibration:
    """Load the calibration a ``bayesmag run`` wrote into folder ``path``.

    Every field is checked (:func:`validate_artifact`); a damaged, tampered or unfinished
    calibration raises :class:`ArtifactError` naming the file and field, never a wrong result.
    """
    path = check_run_folder(path)
    field_run_error(path, ArtifactError)
    return read_calibration(path)


def check_run_folder(path: str | Path, holds: str = "calibration.json") -> Path:
    """``path`` as a finished run folder: a folder, not a staging one, its marker (if any) complete; else
    :class:`ArtifactError` saying what to give instead."""
    from bayesmag._src.app.outdir import is_staging_name, marker_status

    path = Path(path)
    if not path.is_dir():
        old = sorted(path.parent.glob(f".{path.name}.old-*")) if not path.exists() else []
        hint = (f" An interrupted run left the earlier result in {old[0]}; the next bayesmag run into "
                f"{path.parent} restores it (or rename it yourself)." if old else "")
        raise ArtifactError(f"{path} is not a folder; give the run folder that holds {holds}.{hint}")
    if is_staging_name(path.name):
        raise ArtifactError(f"{path} is a temporary folder of an unfinished or interrupted bayesmag run, not a "
                            f"calibration; give the run folder itself (re-run `bayesmag run` if it is missing).")
    mark = marker_status(path)
    if mark is not None and not mark.get("complete"):
        raise ArtifactError(f"{path} was not finished (its .bayesmag-run marker says incomplete); re-run "
                            f"`bayesmag run` to write a full calibration.")
    from bayesmag._src.app.outdir import KIND_WORDS, folder_kind
    kind = folder_kind(mark)
    if kind not in (None, "run", "calibrator"):
        where = " (one of its sensors/<id> folders is)" if kind == "fleet" else ""
        raise ArtifactError(f"{path} holds {KIND_WORDS.get(kind, kind)}, not a calibration{where}; give a run "
                            f"folder that `bayesmag run` wrote (it holds {holds}).")
    return path


def is_field_run(path) -> bool:
    """True for a field-calibration run folder: ``field_params.json`` (or its marker lists one), no vector
    ``calibration.json``."""
    from bayesmag._src.app.outdir import marker_status
    path = Path(path)
    if (path / "calibration.json").exists():
        return False
    listed = (marker_status(path) or {}).get("files") if path.is_dir() else None
    return (path / "field_params.json").exists() or (isinstance(listed, list) and "field_params.json" in listed)


def load_field(path: str | Path):
    """The :class:`~bayesmag._src.core.field_calibration.FieldCalibration` a field-calibration run wrote into
    folder ``path`` (``field_params.json``); :class:`ArtifactError` naming the file and what is wrong."""
    from bayesmag._src.core.field_calibration import FieldCalibration

    path = check_run_folder(path, "field_params.json")
    j = path / "field_params.json"
    if not j.exists() and is_field_run(path):
        raise ArtifactError(f"{j} is missing from this field-calibration run (its .bayesmag-run marker lists it): the "
                            f"folder was changed after the run. Re-run `bayesmag run` on the field config.")
    if not j.exists():
        raise ArtifactError(f"{path} holds no field_params.json: it is not a field-calibration run"
                            + (" (it holds calibration.json: load it with bayesmag.load)."
                               if (path / "calibration.json").exists() else "."))
    try:
        doc = json.loads(j.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ArtifactError(f"{j} is not valid JSON ({e}); the file is damaged.") from None
    try:
        return FieldCalibration.from_json(doc)
    except ValueError as e:
        raise ArtifactError(f"{j}: {str(e).removeprefix('field_params.json: ')}") from None


def field_run_error(path, error) -> None:
    """Raise ``error`` for a field-calibration run folder (``field_params.json``, no vector calibration): re-running
    does not give it a ``calibration.json`` (the message said so), so say what it is and what to use instead."""
    if is_field_run(path):
        from bayesmag._src.app.formats import FORMATS
        held = [f"calibration{ext}" for ext in FORMATS.values() if (Path(path) / f"calibration{ext}").is_file()]
        has_report = (Path(path) / "report.md").is_file()
        what = ((f"its exports ({', '.join(held)}" + (", the first with the full model" if
                                                     "calibration.export.json" in held else "") + ")")
                if held else "no exports ([measurement] exports was empty; re-run with the formats wanted)")
        what += " and its report.md" if has_report else ""
        raise error(f"{path} is a field-calibration run (calibration against |B| or a scalar reference, "
                    f"field_params.json): `bayesmag export`, `bayesmag report` and bayesmag.load take a calibration against a vector "
                    f"reference. The run folder already holds {what}; `bayesmag apply` "
                    f"calibrates a new recording with it, and from Python bayesmag.load_field(run).predict(b, t) "
                    f"(bayesmag.load reads a vector calibration); docs/field.md.")


def _check_version(v, j: Path, writer) -> None:
    """``format_version`` must be an integer this code reads; a newer one says to upgrade."""
    if isinstance(v, bool) or not isinstance(v, int):
        raise ArtifactError(f"{j}: field 'format_version' = {v!r} must be an integer (one of "
                            f"{list(READABLE_VERSIONS)}), not {type(v).__name__}; the file was edited or is damaged.")
    if v > max(READABLE_VERSIONS):
        from bayesmag._src.core.version import __version__
        raise ArtifactError(f"{j} has calibration format version {v}; this bayesmag reads versions "
                            f"{list(READABLE_VERSIONS)} (it is version {__version__}). The file was written by a "
                            f"newer bayesmag ({writer}): upgrade bayesmag (pip install -U bayesmag) to apply it.")
    if v not in READABLE_VERSIONS:
        raise ArtifactError(f"{j} has calibration format version {v}, which no bayesmag reads (this one reads "
                            f"{list(READABLE_VERSIONS)}); the file is damaged. Re-run `bayesmag run`.")


def read_calibration(path: str | Path) -> Calibration:
    """The :class:`Calibration` in ``path``'s ``calibration.json`` and ``.npz``, every field checked; the marker
    and folder name are not looked at (:func:`load` does, for users; ``run`` reads its staging folder back)."""
    path = Path(path)
    j, z = path / "calibration.json", path / "calibration.npz"
    missing = [p.name for p in (j, z) if not p.exists()]
    if len(missing) == 2:
        raise ArtifactError(f"{path} holds no bayesmag calibration (no calibration.json, no calibration.npz): give the "
                            f"folder a `bayesmag run` (or `Calibrator.save`, or a fleet's sensors/<id>) wrote.")
    if missing:
        raise ArtifactError(f"{path} is incomplete: {missing} missing. Re-run `bayesmag run` to write a full calibration.")
    try:
        doc = json.loads(j.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ArtifactError(f"{j} is not valid JSON ({e}); the file is damaged.") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ArtifactError(f"{j} is not a bayesmag calibration "
                            f"(format {doc.get('format') if isinstance(doc, dict) else type(doc).__name__!r}).")
    _check_version(doc.get("format_version"), j, f"bayesmag {doc.get('package_version', '?')}")
    try:
        with np.load(z, allow_pickle=False) as f:
            arrays = {k: np.asarray(f[k]) for k in f.files}
    except Exception as e:          # BadZipFile, pickled data, truncated members, zlib errors ...
        raise ArtifactError(f"{z} cannot be read as a numpy .npz archive ({type(e).__name__}: {e}); "
                            f"the file is damaged.") from None
    try:
        cal = validate_artifact(doc, arrays, where=str(path))
    except ArtifactError:
        raise
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:
        raise ArtifactError(f"{j}: the calibration description is damaged ({type(e).__name__}: {e}).") from None
    _check_sums(doc, arrays, z)         # after the field checks: they name what is implausible, this what changed
    return cal


def array_sha256(a) -> str:
    """sha256 of an array's dtype, shape and bytes (C order): what ``calibration.json`` records per array."""
    import hashlib
    a = np.ascontiguousarray(np.asarray(a))
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return h.hexdigest()


def _check_sums(doc: dict, arrays: dict, z: Path) -> None:
    """Every array of ``calibration.npz`` as ``calibration.json`` recorded it (its sha256); files written before
    the sums were recorded have none to check."""
    sums = (doc.get("arrays") or {}).get("sha256") if isinstance(doc.get("arrays"), dict) else None
    if sums is None:
        return
    if not isinstance(sums, dict):
        raise ArtifactError(f"{z.parent / 'calibration.json'}: field 'arrays.sha256' must map array names to "
                            f"checksums; the file is damaged.")
    changed = sorted(k for k in set(sums) | set(arrays) if k not in arrays or sums.get(k) != array_sha256(arrays[k]))
    if changed:
        raise ArtifactError(f"{z}: array(s) {changed[:5]} differ from the checksums calibration.json recorded when the "
                            f"run wrote them: the file was edited or damaged after the run, so the calibration is "
                            f"not applied. Re-run `bayesmag run` (or restore the run folder).")


def _field(name: str, value, where: str, *, shape=None, finite=True, kind: str = "value") -> np.ndarray:
    arr = np.asarray(value)
    if not (np.issubdtype(arr.dtype, np.number) and not np.issubdtype(arr.dtype, np.complexfloating)):
        raise ArtifactError(f"{where}: field '{name}' holds {arr.dtype} values, not real numbers; the file is damaged.")
    arr = arr.astype(np.float64)
    if shape is not None and arr.shape != shape:
        raise ArtifactError(f"{where}: field '{name}' has shape {arr.shape}; expected {shape}. The file is damaged.")
    if finite and not np.isfinite(arr).all():
        raise ArtifactError(f"{where}: field '{name}' holds {int((~np.isfinite(arr)).sum())} NaN/inf value(s); "
                            f"the calibration is damaged and would give NaN results.")
    limit = _MAX_ABS[kind]
    if arr.size and np.nanmax(np.abs(np.where(np.isfinite(arr), arr, 0.0))) > limit:
        raise ArtifactError(f"{where}: field '{name}' holds {float(arr.flat[np.argmax(np.abs(np.nan_to_num(arr)))]):.3g}, "
                            f"beyond any plausible value (|x| <= {limit:g}); the calibration is damaged.")
    return arr


def validate_artifact(doc: dict, arrays: dict, *, where: str = "calibration") -> Calibration:
    """A :class:`Calibration` from the parsed ``calibration.json`` and ``.npz`` arrays, every field checked.

    Refused with :class:`ArtifactError` naming the field: missing keys, wrong shapes or
    types, NaN/inf anywhere (parameters, covariance, noise model, domain, network weights), a
    covariance that is not symmetric positive definite, an input-noise covariance that is not
    positive semi-definite, a negative residual sd, an unknown likelihood or fusion, ``level``
    outside (0, 1), and network weights without a network description (or the reverse).
    """
    from bayesmag._src.core.likelihoods import LIKELIHOODS

    for key in ("model", "param_names", "domain"):
        if key not in doc:
            raise ArtifactError(f"{where}: calibration.json lacks field '{key}'; the file is damaged.")
    need = {"theta", "cov", "sigma_in", "residual_sd"}
    if not need <= set(arrays):
        raise ArtifactError(f"{where}: calibration.npz lacks arrays {sorted(need - set(arrays))}; the file is "
                            f"damaged or incomplete.")
    model = model_from_json(doc["model"])
    p = model.n_params
    if tuple(doc["param_names"]) != model.param_names:
        raise ArtifactError(f"{where}: field 'param_names' {doc['param_names']} does not match the model "
                            f"{list(model.param_names)}; the files are inconsistent.")
    theta = _field("theta", arrays["theta"], where, shape=(3, p))
    cov = _field("cov", arrays["cov"], where, shape=(3, p, p), kind="variance")
    sigma_in = _field("sigma_in", arrays["sigma_in"], where, shape=(4, 4), kind="variance")
    residual_sd = _field("residual_sd", arrays["residual_sd"], where, shape=(3,))
    s2 = _field("s2", arrays["s2"], where, shape=(3,), kind="variance") if "s2" in arrays else None
    for a, ax in enumerate(AXES):
        c = cov[a]
        d = np.sqrt(np.abs(np.diag(c)))
        if not (np.diag(c) > 0).all() or not np.allclose(c, c.T, rtol=1e-8, atol=0):
            raise ArtifactError(f"{where}: field 'cov' (axis {ax}) is not a symmetric matrix with a positive "
                                f"diagonal; the calibration is damaged.")
        try:
            np.linalg.cholesky(c / np.outer(d, d))
        except np.linalg.LinAlgError:
            raise ArtifactError(f"{where}: field 'cov' (axis {ax}) is not positive definite; the calibration "
                                f"is damaged.") from None
    if not np.allclose(sigma_in, sigma_in.T) or np.linalg.eigvalsh(sigma_in).min() < -1e-12 * max(
            1.0, np.abs(sigma_in).max()):
        raise ArtifactError(f"{where}: field 'sigma_in' is not a symmetric positive semi-definite 4x4 matrix.")
    if (residual_sd < 0).any() or (s2 is not None and (s2 < 0).any()):
        raise ArtifactError(f"{where}: field 'residual_sd' or 's2' is negative; the calibration is damaged.")
    likelihood = doc.get("likelihood", "gaussian")
    if likelihood not in LIKELIHOODS:
        raise ArtifactError(f"{where}: field 'likelihood' = {likelihood!r} is not known; it must be one of "
                            f"{sorted(LIKELIHOODS)}.")
    level = doc.get("level", 0.95)
    if isinstance(level, bool) or not isinstance(level, (int, float)) or not 0 < level < 1:
        raise ArtifactError(f"{where}: field 'level' = {level!r} must be a number in (0, 1).")
    dom = doc["domain"]
    if not isinstance(dom, dict):
        raise ArtifactError(f"{where}: field 'domain' must be a table; got {dom!r}.")
    low = _field("domain.low", dom.get("low"), where, shape=(4,), kind="domain")
    high = _field("domain.high", dom.get("high"), where, shape=(4,), kind="domain")
    out_lo = None if dom.get("out_low") is None else _field("domain.out_low", dom["out_low"], where, shape=(3,))
    out_hi = None if dom.get("out_high") is None else _field("domain.out_high", dom["out_high"], where, shape=(3,))
    margin = float(_field("domain.margin", dom.get("margin", 0.05), where, shape=()))
    rate_hi = None if dom.get("rate_high") is None else _field("domain.rate_high", dom["rate_high"], where, shape=(4,), kind="domain")
    step = None if dom.get("step") is None else float(_field("domain.step", dom["step"], where, shape=(), kind="domain"))
    extra = {k: _field(k, arrays[k], where, shape=(3,)) for k in ("transfer_sd", "interval_scale", "network_transfer_sd")
             if k in arrays}
    if any((v < 0).any() for v in extra.values()):
        raise ArtifactError(f"{where}: field 'transfer_sd', 'interval_scale' or 'network_transfer_sd' is negative; the "
                            f"calibration is damaged.")
    if (low > high).any():
        raise ArtifactError(f"{where}: field 'domain' has low > high; the calibration is damaged.")
    net_arrays = {k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith("network/")}
    meta = doc.get("network")
    network = None
    if meta is None and net_arrays:
        raise ArtifactError(f"{where}: field 'network' is null but calibration.npz holds network weights "
                            f"{sorted(net_arrays)[:3]}...; the files are inconsistent.")
    if meta is not None:
        network = _check_network(meta, net_arrays, where)
    ses_arrays = {k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith("sessions/")}
    sessions = None
    if doc.get("sessions") is not None or ses_arrays:
        from bayesmag._src.pipeline.sessions.hierarchical import posterior_from_artifact
        try:
            sessions = posterior_from_artifact(doc.get("sessions"), ses_arrays, model.param_names)
        except ValueError as e:
            raise ArtifactError(f"{where}: {e} The calibration is damaged.") from None
    return Calibration(model=model, theta=theta, cov=cov, sigma_in=sigma_in, residual_sd=residual_sd,
                       domain=Domain(tuple(low.tolist()), tuple(high.tolist()), margin,
                                     None if out_lo is None else tuple(out_lo.tolist()),
                                     None if out_hi is None else tuple(out_hi.tolist()),
                                     None if rate_hi is None else tuple(rate_hi.tolist()), step),
                       likelihood=likelihood, level=float(level), config=doc.get("config", {}), network=network,
                       package_version=doc.get("package_version", ""), s2=s2, sessions=sessions, **extra)


def _check_network(meta, arrays: dict, where: str) -> dict:
    """The saved network's description and weights: known fusion, complete finite weights, matching shapes."""
    from bayesmag._src.pipeline.hybrid import FUSIONS

    if not isinstance(meta, dict) or not isinstance(meta.get("spec"), dict):
        raise ArtifactError(f"{where}: field 'network' must be a table with 'spec'; the file is damaged.")
    fusion = meta.get("fusion", "moment_match")
    if fusion not in FUSIONS:
        raise ArtifactError(f"{where}: field 'network.fusion' = {fusion!r} is not known; it must be one of "
                            f"{list(FUSIONS)}.")
    n_layers, passes = meta.get("n_layers"), meta.get("passes")
    for name, v in (("network.n_layers", n_layers), ("network.passes", passes)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ArtifactError(f"{where}: field '{name}' = {v!r} must be a positive integer.")
    if not arrays:
        raise ArtifactError(f"{where}: field 'network' describes a network but calibration.npz holds no network "
                            f"weights; the files are inconsistent.")
    for k, v in arrays.items():
        _field(f"network/{k}", v, where, kind="domain")
    members = meta.get("members")
    prefixes = [""]
    if members is not None:
        if isinstance(members, bool) or not isinstance(members, int) or members < 2:
            raise ArtifactError(f"{where}: field 'network.members' = {members!r} must be an integer of at least 2 "
                                f"(the networks of a deep ensemble).")
        prefixes = [f"member{k}/" for k in range(members)]
        stray = sorted(k for k in arrays if not k.startswith(tuple(prefixes)))
        if stray:
            raise ArtifactError(f"{where}: calibration.npz holds network arrays {['network/' + k for k in stray][:3]} "
                                f"outside the {members} ensemble members 'network/member0..{members - 1}/'; the files "
                                f"are inconsistent.")
    shapes = None
    for pre in prefixes:
        width = None
        for i in range(n_layers):
            w, b = arrays.get(f"{pre}layer{i}/w"), arrays.get(f"{pre}layer{i}/b")
            if w is None or b is None:
                raise ArtifactError(f"{where}: calibration.npz lacks network/{pre}layer{i}/w or /b; the file is "
                                    f"damaged.")
            if w.ndim < 2 or b.shape != w.shape[:-2] + w.shape[-1:] or (width is not None and w.shape[-2] != width):
                raise ArtifactError(f"{where}: network {pre}layer {i} has shapes w {w.shape}, b {b.shape} that do not "
                                    f"chain; the file is damaged.")
            width = w.shape[-1]
        mine = {k[len(pre):]: v.shape for k, v in arrays.items() if k.startswith(pre)}
        if shapes is not None and mine != shapes:
            diff = sorted(k for k in set(mine) | set(shapes) if mine.get(k) != shapes.get(k))
            raise ArtifactError(f"{where}: ensemble member network/{pre} differs from member 0 in arrays {diff[:3]} "
                                f"(shapes {[mine.get(k) for k in diff[:3]]} against {[shapes.get(k) for k in diff[:3]]}); "
                                f"every member has the same network. The file is damaged.")
        shapes = mine
    network = {"meta": meta, "arrays": arrays}
    network_from_artifact(network)          # every remaining key and setting present and known
    return network


# --------------------------------------------------------------------------- network weights


def network_to_artifact(net, *, passes: int, seed: int, fusion: str) -> dict:
    """A trained :class:`~bayesmag._src.core.network.ResidualNetwork` as JSON metadata + named arrays; a
    :class:`~bayesmag._src.core.network.NetworkEnsemble` as every member's arrays under ``member<k>/`` and
    ``meta["members"] = K`` (the rest of ``meta``, ``n_fit`` / ``n_val`` included, from member 0)."""
    from bayesmag._src.core.network import NetworkEnsemble

    if isinstance(net, NetworkEnsemble):
        parts = [network_to_artifact(m, passes=passes, seed=seed, fusion=fusion) for m in net.members]
        arrays = {f"member{k}/{name}": v for k, p in enumerate(parts) for name, v in p["arrays"].items()}
        return {"meta": {**parts[0]["meta"], "members": len(parts)}, "arrays": arrays}
    spec = net.spec.to_dict()
    arrays = {f"standardizer/{k}": np.asarray(v) for k, v in net.standardizer._asdict().items()}
    for i, layer in enumerate(net.params):
        arrays[f"layer{i}/w"] = np.asarray(layer.w)
        arrays[f"layer{i}/b"] = np.asarray(layer.b)
    if net.frequencies is not None:
        arrays["fourier/frequencies"] = np.asarray(net.frequencies)
    if net.variance_scale is not None:
        arrays["recalibration/variance_scale"] = np.asarray(net.variance_scale, np.float64)
    meta = {"spec": spec, "n_layers": len(net.params), "passes": int(passes), "seed": int(seed), "fusion": fusion,
            "n_fit": int(net.n_fit), "n_val": int(net.n_val), "inputs": ["bx_meas", "by_meas", "bz_meas", "temperature"]}
    return {"meta": meta, "arrays": arrays}


def network_from_artifact(network: dict):
    """Rebuild the :class:`~bayesmag._src.core.network.ResidualNetwork` (or, with ``meta["members"]``, the
    :class:`~bayesmag._src.core.network.NetworkEnsemble`) saved by :func:`network_to_artifact`."""
    import jax.numpy as jnp

    from bayesmag._src.core.network import Dense, NetworkEnsemble, NetworkSpec, ResidualNetwork, Standardizer

    meta, arr = network["meta"], network["arrays"]
    if meta.get("members") is not None:
        single = {k: v for k, v in meta.items() if k != "members"}
        return NetworkEnsemble(tuple(
            network_from_artifact({"meta": single, "arrays": {n[len(f"member{k}/"):]: v for n, v in arr.items()
                                                              if n.startswith(f"member{k}/")}})
            for k in range(meta["members"])))
    try:
        spec = NetworkSpec.from_dict(meta["spec"])
    except KeyError as e:
        raise ArtifactError(f"the saved network has {e.args[0]} this bayesmag does not know; "
                            f"install the version that wrote it.") from None
    try:
        params = tuple(Dense(jnp.asarray(arr[f"layer{i}/w"]), jnp.asarray(arr[f"layer{i}/b"]))
                       for i in range(meta["n_layers"]))
        st = Standardizer(*(arr[f"standardizer/{k}"] for k in Standardizer._fields))
        freqs = np.asarray(arr["fourier/frequencies"], np.float64) if spec.fourier_features else None
        vscale = arr.get("recalibration/variance_scale")
    except KeyError as e:
        raise ArtifactError(f"the saved network lacks array {e}; calibration.npz is damaged.") from None
    return ResidualNetwork(spec, params, st, None, meta.get("n_fit", 0), meta.get("n_val", 0), freqs,
                           None if vscale is None else np.asarray(vscale, np.float64))


def apply_network(network: dict, data: CalibrationData):
    """MC-DropConnect residual mean, aleatoric and epistemic variances (n, 3) of a saved network."""
    from bayesmag._src.core.network import mc_predict
    from bayesmag._src.core.predictor import network_inputs

    net = network_from_artifact(network)
    p = mc_predict(net, network_inputs(data), passes=network["meta"]["passes"], seed=network["meta"]["seed"])
    return p.mean, p.aleatoric**2, p.epistemic**2, p.shape
