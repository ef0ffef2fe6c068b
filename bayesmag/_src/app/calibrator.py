"""A scikit-learn estimator for notebooks and pipelines: ``bayesmag.Calibrator(config).fit(X, y).predict(X)``.

``fit`` converts the config to library settings and calls :func:`~bayesmag.calibrate` directly
(no job, no files, no process spawned); the fitted calibration is the saved
:class:`~bayesmag.Calibration` (:meth:`Calibrator.save` writes the folder ``bayesmag apply`` reads).
It follows scikit-learn's estimator contract without importing scikit-learn (an optional extra,
``pip install bayesmag[sklearn]``): the constructor only stores its parameters, ``get_params`` /
``set_params`` / :func:`sklearn.base.clone` / ``Pipeline`` work, ``fit`` returns ``self``, fitted
attributes end in ``_``.
"""

from __future__ import annotations

import inspect
import tempfile
from pathlib import Path

import numpy as np

from bayesmag._src.app.config import Config, ConfigError, config_from_dict, read_config_dict
from bayesmag._src.core.data import AXES, CalibrationData, DataError

__all__ = ["Calibrator", "DEFAULT_CONFIG", "PARAM_UNITS"]

#: The config of ``Calibrator()``: the default settings (physics stage, ``"auto"`` uncertainty), no figures.
DEFAULT_CONFIG = {"name": "calibrator", "split": {"kind": "none"}, "output": {"figures": False, "progress": False}}

#: Units of the paper model's parameters (``params_``); other terms' parameters say ``""`` unless the
#: term names them with a ``param_units()`` method.
PARAM_UNITS = {"S": "1", "Ks": "1/C", "O": "uT", "Ko": "uT/C"}

#: Column order of a NumPy ``X``: the measured field (uT) and the temperature (C), then optionally time (s)
#: and run; a NumPy ``y`` is the reference field ``(n, 3)`` in uT.
ARRAY_COLUMNS = ("bx_meas", "by_meas", "bz_meas", "temperature", "time", "run")


#: What :meth:`Calibrator.predict` returns (the ``output`` parameter).
OUTPUTS = ("full", "field")


class NotFittedError(RuntimeError, ValueError, AttributeError):
    """A :class:`Calibrator` used before :meth:`~Calibrator.fit` (scikit-learn's ``NotFittedError`` contract: a
    ``ValueError`` and an ``AttributeError``; a ``RuntimeError`` as before)."""


#: The reference columns ``y`` may name (a DataFrame ``y`` is read by these names, in this order).
_REF_COLUMNS = ("bx_ref", "by_ref", "bz_ref")


def _drop_none(d):
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    return d


class Calibrator:
    """Fit a calibration on a DataFrame, a :class:`~bayesmag.CalibrationData` or NumPy arrays, then predict.

    Args:
      config: None (the physics stage with the default settings, :data:`DEFAULT_CONFIG`), a TOML
        path or packaged config name (``"paper_physics"``), a :class:`~bayesmag.Config`, or a plain dict
        as parsed from TOML. Its ``[data]`` table and ``[split]`` are not used: the rows given to
        :meth:`fit` are the data, and ``holdout`` says which of them are held out.
      overrides: ``--set``-style ``key=value`` strings applied to the config.
      out: a folder: after :meth:`fit` the calibration is saved in ``out/run`` (:meth:`save`).
      columns, temperature_unit, field_unit: how the data are read (a DataFrame's column names; the
        declared units, converted to uT and C). Undeclared, the field is checked to be in uT and the
        temperature in C (nT, mT, gauss and kelvin refused), as on the command line.
      duplicate_times: ``"ignore"`` (default: a physics fit does not use time), ``"refuse"`` (rows of a
        run that share a timestamp are named) or ``"spread"`` (spread evenly up to the next stamp, as
        for the whole-second Belsten stamps at 4 Hz).
      holdout: None (default: every row fits, no metrics), a fraction in (0, 1) (that share of the rows,
        chosen as the config's ``[split]`` kind chooses them, is held out and scored into ``metrics_``),
        or ``"config"`` (the config's own ``[split]``). Nothing is ever held out silently.
      output: what :meth:`predict` returns: ``"full"`` (default: a DataFrame of the calibrated field, its
        uncertainty parts, interval and domain flags for a DataFrame, the dict of arrays otherwise) or
        ``"field"`` (the calibrated field alone, an ``(n, 3)`` array: what scikit-learn's metrics, scorers and
        ``cross_val_predict`` expect).

    NumPy input: ``X`` ``(n, 4)`` columns :data:`ARRAY_COLUMNS` (``bx, by, bz`` in uT, temperature in C;
    optional 5th time in s and 6th run), ``y`` ``(n, 3)`` the reference field in uT.

    Attributes after :meth:`fit`: ``run_`` (the :class:`~bayesmag.CalibrationRun`), ``calibration_``
    (the :class:`~bayesmag.Calibration` :meth:`predict` applies), ``physics_fit_``, ``params_`` (a
    labelled DataFrame), ``metrics_`` (scores of the held-out rows, or None), ``run_dir_`` (with ``out``).

    Example:
      >>> import bayesmag
      >>> d = bayesmag.simulate.simulate(400, design="campaign", seed=0)
      >>> cal = bayesmag.Calibrator().fit(d)
      >>> cal.predict(d)["calibrated"].shape
      (400, 3)
      >>> list(cal.params_.columns)
      ['axis', 'parameter', 'value', 'sd', 'unit']
    """

    def __init__(self, config=None, overrides=(), *, out: str | Path | None = None, columns: dict | None = None,
                 temperature_unit: str = "C", field_unit: str | None = None, holdout: float | str | None = None,
                 duplicate_times: str = "ignore", output: str = "full"):
        self.config = config
        self.overrides = overrides
        self.out = out
        self.columns = columns
        self.temperature_unit = temperature_unit
        self.field_unit = field_unit
        self.holdout = holdout
        self.duplicate_times = duplicate_times
        self.output = output

    # ------------------------------------------------------------------ scikit-learn's parameter protocol
    @classmethod
    def _get_param_names(cls) -> list[str]:
        return [p for p in inspect.signature(cls.__init__).parameters if p != "self"]

    def get_params(self, deep: bool = True) -> dict:
        """The constructor parameters (scikit-learn's ``get_params``; ``deep`` has nothing to recurse into)."""
        return {name: getattr(self, name) for name in self._get_param_names()}

    def set_params(self, **params) -> "Calibrator":
        """Set constructor parameters by name; returns ``self``.

        Raises:
            ValueError: a name that is not a parameter (the message lists them).
        """
        valid = self._get_param_names()
        for k, v in params.items():
            if k not in valid:
                raise ValueError(f"Calibrator has no parameter {k!r}; its parameters are {valid}.")
            setattr(self, k, v)
        return self

    def __sklearn_tags__(self):
        from sklearn.utils import Tags, TargetTags  # only called by scikit-learn itself
        from sklearn.utils import RegressorTags
        tags = Tags(estimator_type="regressor", target_tags=TargetTags(required=False, multi_output=True,
                                                                      single_output=False),
                    regressor_tags=RegressorTags())
        tags.input_tags.two_d_array = True
        tags.input_tags.allow_nan = False
        return tags

    # ------------------------------------------------------------------ config and data
    def _config(self) -> Config:
        c = self.config
        if c is None:
            raw = {k: dict(v) if isinstance(v, dict) else v for k, v in DEFAULT_CONFIG.items()}
        elif isinstance(c, Config):
            raw = _drop_none(c.to_dict())
        elif isinstance(c, dict):
            raw = _drop_none(dict(c))
        elif isinstance(c, (str, Path)):
            from bayesmag._src.app.config import resolve_config_path
            raw = read_config_dict(resolve_config_path(str(c)))
        else:
            raise ConfigError(f"config must be None, a path, a Config or a dict; got {type(c).__name__}.")
        if self.overrides:
            from bayesmag._src.app.config import apply_overrides
            ov = [self.overrides] if isinstance(self.overrides, str) else list(self.overrides)   # one key=value
            raw = apply_overrides(raw, ov)
        raw["data"] = {"source": "simulated"}        # a placeholder: the rows come from fit()
        return config_from_dict(raw)

    def _rows(self, X, y=None, *, need_reference: bool = False, field_unit=None, temperature_unit=None,
              columns=None, train_max_ut: float | None = None,
              train_noise_ut: float | None = None) -> tuple[CalibrationData, object]:
        """``X`` (and ``y``) as checked CalibrationData in uT and C (the command line's unit checks,
        :func:`~bayesmag._src.core.frames.as_calibration_data`), and the DataFrame index (or None).
        ``field_unit``, ``temperature_unit``, ``columns``: the caller's (``predict``'s), else the constructor's."""
        from bayesmag._src.core.frames import as_calibration_data, is_frame

        field_unit = self.field_unit if field_unit is None else field_unit
        temperature_unit = self.temperature_unit if temperature_unit is None else temperature_unit
        columns = self.columns if columns is None else columns

        index = X.index if is_frame(X) else None
        if not isinstance(X, CalibrationData) and not is_frame(X):
            a = np.asarray(X, dtype=np.float64)
            if a.ndim != 2 or a.shape[1] not in (4, 5, 6):
                raise DataError(f"X as an array must be (n, 4) [bx, by, bz, temperature] (optionally time, run); "
                                f"got shape {a.shape}.")
            X = CalibrationData(a[:, :3], a[:, 3], None, a[:, 4] if a.shape[1] > 4 else None,
                                a[:, 5].astype(int) if a.shape[1] > 5 else None, source="array X")
        if y is not None:
            if index is not None and hasattr(y, "index") and not index.equals(y.index):
                raise DataError("X and y are pandas objects with different indexes; y is used by position (as in "
                                "scikit-learn), so its rows would be paired with other rows of X. Align them first: "
                                "y.loc[X.index] (or y.to_numpy() if the row order is already right).")
            ref = np.asarray(_reference_by_name(y, columns).to_numpy() if hasattr(y, "to_numpy") else y,
                             dtype=np.float64)
            n = len(X) if is_frame(X) else X.n
            if ref.shape != (n, 3):
                raise DataError(f"y must be the reference field (n, 3) = ({n}, 3); got shape {ref.shape}.")
            bad = ~np.isfinite(ref)
            if bad.any():
                from bayesmag._src.core.data import _bad_rows
                col = ("bx_ref", "by_ref", "bz_ref")[int(np.flatnonzero(bad.any(axis=0))[0])]
                raise DataError(f"y (the reference field) has {int(bad.sum())} non-finite value(s) (NaN or inf), "
                                f"first in column {col}, at {_bad_rows(bad.any(axis=1))}. Remove or repair those "
                                f"rows (of X and y alike) before calibrating.")
            _note_second_reference(X, ref, columns)
            if is_frame(X):
                X = X.assign(**{f"{a}_ref": ref[:, i] for i, a in enumerate(("bx", "by", "bz"))})
            else:
                X = CalibrationData(X.b_meas, X.temperature, ref, X.time, X.run, source=X.source,
                                    field_unit=X.field_unit, time_given=X.time_given)
        columns = columns if is_frame(X) else None
        if columns and y is not None:       # y is the reference: a mapping of reference columns must not replace it
            columns = {k: v for k, v in dict(columns).items() if k not in ("bx_ref", "by_ref", "bz_ref")}
        rows = as_calibration_data(X, columns=columns, field_unit=field_unit,
                                   temperature_unit=temperature_unit, require_reference=need_reference,
                                   duplicate_times=self.duplicate_times, what="the data given to Calibrator",
                                   train_max_ut=train_max_ut, train_noise_ut=train_noise_ut)
        return rows, index

    def _split(self, cfg: Config, rows: CalibrationData):
        from bayesmag._src.core.data import make_split

        h = self.holdout
        if h is None:
            return None
        sp = cfg.split
        if isinstance(h, str):
            if h != "config":
                raise ValueError(f"holdout = {h!r} must be None, a fraction in (0, 1) or \"config\".")
            kind, fraction = sp.kind, sp.test_fraction
        else:
            if not 0 < float(h) < 1:
                raise ValueError(f"holdout = {h!r} must be None, a fraction in (0, 1) or \"config\".")
            kind = sp.kind if sp.kind != "none" else "random"
            fraction = float(h)
        if kind == "none":
            return None
        return make_split(rows, kind=kind, test_fraction=fraction, seed=sp.seed, test_runs=sp.test_runs,
                          n_blocks=sp.n_blocks)

    # ------------------------------------------------------------------ estimator
    def fit(self, X, y=None) -> "Calibrator":
        """Calibrate on ``X`` (with the reference columns, or the reference as ``y``); returns ``self``.

        Runs :func:`~bayesmag.calibrate` with the config's stages (physics; network and NUTS when the
        config enables them) on the rows (minus the ``holdout`` rows, which are scored into ``metrics_``).
        """
        from bayesmag._src.core.data import validate
        from bayesmag._src.core.precision import warn_if_float32
        from bayesmag._src.pipeline.calibrate import calibrate

        warn_if_float32("Calibrator.fit")
        for attr in ("run_", "physics_fit_", "metrics_", "calibration_", "params_", "run_dir_", "_cfg"):
            self.__dict__.pop(attr, None)          # a refit (or a failed one) keeps nothing of the last fit
        cfg = self._config()
        rows, _ = self._rows(X, y, need_reference=True)
        split = self._split(cfg, rows)
        train, test = (rows, None) if split is None else (rows.subset(split.train), rows.subset(split.test))
        settings = cfg.settings()
        try:
            model = settings.physics.model(train)
        except (ValueError, TypeError) as e:
            raise ConfigError(f"[physics] extra_terms: {e}") from None
        validate(rows, n_params=model.n_params, origin=rows.source or "the rows given to Calibrator.fit",
                 need_temperature_variation=cfg.physics.temperature_terms, allow_duplicate_times=True)
        from bayesmag._src.app.job import time_order_reasons
        from bayesmag._src.core.data import check_time_order
        reasons = time_order_reasons(cfg, model)
        if split is None:                   # no holdout: no split takes the rows in time order
            reasons = [r for r in reasons if r and "split" not in r]
        check_time_order(rows, reasons, origin=rows.source or "the rows given to Calibrator.fit")
        if cfg.nuts.enabled:
            from bayesmag._src.app.nuts_stage import check_nuts_config
            settings = cfg.settings(nuts_priors=check_nuts_config(cfg, model.param_names))
        self.run_ = calibrate(train, settings, test=test,
                              series=None if split is None else (rows, split.train, split.test))
        self.physics_fit_ = self.run_.fit
        self.metrics_ = None
        if split is not None:
            from bayesmag._src.app.job import job_metrics
            self.metrics_, _ = job_metrics(cfg, self.run_, rows, split, test)
        self._cfg = cfg
        self.calibration_ = self._calibration()
        self.params_ = self._params_frame()
        if self.out is not None:
            self.run_dir_ = self._save(Path(self.out) / "run", replaces="same")
        return self

    def _calibration(self):
        """The fitted calibration exactly as saved and loaded (a round trip through a temporary folder)."""
        from bayesmag._src.app.artifact import load
        with tempfile.TemporaryDirectory(prefix="bayesmag-calibrator-") as tmp:
            return load(self._save(Path(tmp) / "run", replaces="none"))

    def _params_frame(self):
        import pandas as pd

        fit = self.physics_fit_
        sd = np.sqrt(np.stack([np.diag(np.asarray(c)) for c in fit.cov]))
        units = []
        for comp in fit.model.components:
            own = getattr(comp, "param_units", None)
            if callable(own):
                units += list(own())
            elif comp.name == "thermo_affine":
                units += [PARAM_UNITS[n.split("_")[0]] for n in comp.param_names()]
            else:
                units += [""] * len(comp.param_names())
        recs = [{"axis": ax, "parameter": name, "value": float(fit.theta[a][j]), "sd": float(sd[a][j]),
                 "unit": units[j]} for a, ax in enumerate(AXES) for j, name in enumerate(fit.model.param_names)]
        return pd.DataFrame.from_records(recs, columns=["axis", "parameter", "value", "sd", "unit"])

    def save(self, path: str | Path, *, overwrite: bool = False) -> Path:
        """Write the fitted calibration into folder ``path`` (atomically): ``calibration.json``/``.npz``
        (``bayesmag apply --model PATH`` and :func:`bayesmag.load` read them), ``params.json``,
        ``config.resolved.toml`` and, with a holdout, ``metrics.json``. Returns ``path``.

        ``path`` may be new or an empty folder. A folder holding a complete bayesmag result (a ``bayesmag run``, an
        earlier save, a fleet, ...) is replaced only with ``overwrite=True`` (only the files bayesmag listed in it
        go); a folder with files bayesmag did not write is never replaced (:mod:`~bayesmag._src.app.outdir`).
        """
        self._check_fitted("run_")
        return self._save(Path(path), replaces="any" if overwrite else "none")

    def _save(self, path: Path, *, replaces: str) -> Path:
        """:meth:`save` with :func:`~bayesmag._src.app.outdir.check_out`'s ``replaces``: ``"same"`` for ``fit``'s
        ``out`` (a refit replaces its own earlier save, never a ``bayesmag run``)."""
        from bayesmag._src.app.outdir import KIND_WORDS, OccupiedError, OutputError, _suggest, staging_dir

        config = self._cfg.to_dict()
        # the rows came from fit(), not from a file: no [data] source (the placeholder "simulated" would make
        # `bayesmag run` of this config, and `export`'s refit of a least-squares format, use simulated rows)
        config["data"] = {k: v for k, v in config["data"].items() if k not in ("source", "path", "simulate")}
        try:
            with staging_dir(path, kind="calibrator", replaces=replaces) as tmp:
                self._write(tmp, config)
        except OccupiedError as e:
            held = KIND_WORDS.get(e.kind, "a complete bayesmag result")
            fix = ("Pass overwrite=True to replace it" if replaces == "none" else
                   "Give the Calibrator another out= folder, or call save(path, overwrite=True) to replace it")
            raise OccupiedError(f"{path} holds {held}; saving here would replace it with this Calibrator's "
                                f"calibration (and remove every file bayesmag listed there). {fix}, or save into a "
                                f"new folder, e.g. {_suggest(path)}.", e.folder, e.kind) from None
        except OutputError as e:                # the command line's words without its option: save(path) has none
            raise OutputError(str(e).replace("--out ", "")) from None
        return path

    def _write(self, tmp: Path, config: dict) -> None:
        """The files of :meth:`save` into the staging folder ``tmp``."""
        import json

        from bayesmag._src.app.artifact import save_calibration
        from bayesmag._src.app.config import to_toml
        (tmp / "params.json").write_text(json.dumps(self.physics_fit_.to_json(), indent=2))
        (tmp / "config.resolved.toml").write_text(
            "# Fitted by bayesmag.Calibrator on rows given in Python (no [data] source): to rerun it with\n"
            "# `bayesmag run`, set [data] path to the recording.\n" + to_toml(config))
        save_calibration(tmp, self.run_.predictor, config=config, level=self._cfg.uq.level)
        if self.metrics_ is not None:
            (tmp / "metrics.json").write_text(json.dumps(self.metrics_, indent=2))

    def _check_fitted(self, attr: str = "calibration_"):
        if not hasattr(self, attr):
            raise NotFittedError("this Calibrator is not fitted yet: call fit(data) first.")

    def predict(self, X, **kwargs):
        """Calibrated field and uncertainty (:meth:`bayesmag.Calibration.predict`'s keywords): with ``output =
        "full"`` a DataFrame for a DataFrame (its index kept), the dict of ``(n, 3)`` arrays for a CalibrationData
        or an array; with ``"field"`` the ``(n, 3)`` calibrated field. ``columns``, ``field_unit`` and
        ``temperature_unit`` given here replace the constructor's for these rows. The rates are checked only for
        rows with times (a ``time`` column, a 5th array column, or a CalibrationData made with times)."""
        self._check_fitted()
        if self.output not in OUTPUTS:
            raise ValueError(f"output = {self.output!r} must be one of {list(OUTPUTS)}.")
        from bayesmag._src.core.frames import is_frame, prediction_frame
        units = {k: kwargs.pop(k) for k in ("columns", "field_unit", "temperature_unit") if k in kwargs}
        if isinstance(X, CalibrationData) and not units:
            out = self.calibration_.predict(X, **kwargs)
        else:
            rows, index = self._rows(X, train_max_ut=self.calibration_._train_max(),
                                     train_noise_ut=self.calibration_._train_noise(), **units)
            kwargs.setdefault("check_rates", rows.time_given)
            out = self.calibration_.predict(rows, check_units=False, **kwargs)   # checked by _rows
            if is_frame(X) and self.output == "full":
                return prediction_frame(out, index)
        return out if self.output == "full" else out["calibrated"]

    def score(self, X, y=None) -> float:
        r"""Minus the mean CRPS (uT) of the predictive distribution at the reference, over rows and axes:
        :math:`-\frac{1}{3n}\sum_{i,a} \mathrm{CRPS}(F_{ia}, y_{ia})` (higher is better, 0 is perfect;
        scikit-learn's convention). ``y``: the reference, unless ``X`` holds it. The rows are scored as a *new
        session* (the transfer part included, as :meth:`predict` and ``bayesmag apply`` treat them): rows of a
        training session (a random split) score a little worse than ``metrics_``, which scores same-session
        intervals."""
        from bayesmag._src.core import metrics as M

        self._check_fitted()
        rows, _ = self._rows(X, y, need_reference=True)
        pred = self.calibration_.predictor().predict(rows)
        return -float(np.mean(M.crps(pred.dist, rows.b_ref)))

    def __repr__(self) -> str:
        params = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items()
                           if v != inspect.signature(type(self).__init__).parameters[k].default)
        return f"Calibrator({params})"


def _reference_by_name(y, columns):
    """A DataFrame ``y`` in the reference order ``bx_ref, by_ref, bz_ref`` when it names them (or the names
    ``columns`` maps them to), in any order; otherwise as given (scikit-learn reads ``y`` by position). A ``y`` that
    names some reference or other canonical columns but not all three is refused (it would be read by position)."""
    if not hasattr(y, "columns"):
        return y
    from bayesmag._src.core.data import CANONICAL_COLUMNS
    names = [dict(columns or {}).get(c, c) for c in _REF_COLUMNS]
    have = [str(c) for c in y.columns]
    for cand in (names, list(_REF_COLUMNS)):            # the mapped names, or the canonical ones
        if set(cand) <= set(have):
            return y[cand]
    known = set(names) | set(CANONICAL_COLUMNS)
    if any(c in known for c in have):
        raise DataError(f"y has columns {have}: it names canonical column(s) but not all of the reference columns "
                        f"{names}, so its columns cannot be matched to x, y and z. Give y the columns {names} (any "
                        f"order), or pass y.to_numpy() in the order x, y, z.")
    return y


def _note_second_reference(X, ref, columns) -> None:
    """``fit(X, y)`` where ``X`` holds the reference columns too and they differ from ``y``: ``y`` is the reference
    (scikit-learn's target), said with a :class:`~bayesmag.DataNote` naming the rows (it was silent before)."""
    from bayesmag._src.core.frames import is_frame
    if is_frame(X):
        names = [dict(columns or {}).get(c, c) for c in _REF_COLUMNS]
        if not set(names) <= set(map(str, X.columns)):
            return
        own = np.asarray(X[names].to_numpy(), dtype=np.float64)
    elif isinstance(X, CalibrationData) and X.b_ref is not None:
        own = np.asarray(X.b_ref, dtype=np.float64)
    else:
        return
    diff = ~np.isclose(own, ref, rtol=1e-9, atol=1e-9) & np.isfinite(own)
    if diff.any():
        import warnings

        from bayesmag._src.core.data import DataNote, _bad_rows, user_stacklevel
        warnings.warn(DataNote(f"X holds reference columns and y differs from them at {_bad_rows(diff.any(axis=1))}: "
                               f"y is the reference used (X's reference columns are ignored). Drop them from X, or "
                               f"leave y out, to silence this."), stacklevel=user_stacklevel())
