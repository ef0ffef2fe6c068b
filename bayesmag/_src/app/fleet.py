"""``bayesmag fleet CONFIG``: calibrate many sensors in one compiled batch, judge each against limits and the fleet.

A fleet config (``[fleet]`` table; see ``configs/fleet_simulated.toml`` and ``docs/fleet.md``) names
the recordings -- a folder of CSV/Parquet files, a glob, a manifest CSV (``id,path``), or the
simulated population of :func:`~bayesmag._src.core.simulate_fleet.simulate_fleet` -- one per sensor.
Each recording is split (contiguous time blocks held out per run), the physics model is fitted to
every sensor at once (:func:`~bayesmag._src.core.fleet_fit.fit_fleet`), the exact physics uncertainty
is propagated (:func:`~bayesmag._src.core.fleet_fit.fleet_uncertainty`), and every sensor gets:

* a verdict against ``[fleet.limits]`` (|offset|, gain error, cross-axis, offset tempco, test RMSE,
  test coverage, converged, identifiable, and ``run``'s design and input-noise warnings: ``design``,
  ``input_noise``);
* robust z-scores of each parameter and of log test RMSE against the fleet (outlier when
  ``max |z| > outlier_z``; computed only with at least :data:`MIN_SENSORS_OUTLIERS` sensors);
* its own folder ``sensors/<id>/`` with the files of a single ``bayesmag run`` folder: ``calibration.json``/``.npz``
  (``bayesmag apply --model`` and ``bayesmag export`` take it), ``params.json``, ``predictions.csv``,
  ``metrics.json``, ``config.resolved.toml``, ``report.md``/``report.html`` and, with ``[output] figures = true``,
  the single run's figures (:mod:`~bayesmag._src.app.fleet_sensors`).

With ``[network] enabled = true`` every sensor's residual network is trained in one compiled batch
(:func:`~bayesmag._src.core.network_batch.fit_residual_networks`: each equals the single-sensor training with the
same seed up to float32 rounding) and fused with its physics prediction as a single run fuses it; the verdict's
test RMSE and coverage are then the hybrid prediction's.

The fleet gets ``fleet.json``, ``fleet_table.csv``, ``fleet_report.md`` and figures. The output folder is
staged and swapped in whole (``outdir``), so a failed fleet leaves nothing half-written.
"""

from __future__ import annotations

import dataclasses
import glob as globlib
import re
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

from bayesmag._src.app.config import ConfigError, NetworkConfig, apply_overrides
from bayesmag._src.core.data import AXES, CalibrationData, DataError, make_split, validate
from bayesmag._src.core.fleet_fit import FleetData, fit_fleet, fleet_input_noise, fleet_uncertainty, robust_z
from bayesmag._src.core.physics import PhysicsModel

__all__ = ["FleetConfig", "load_fleet_config", "fleet_config_from_dict", "run_fleet", "is_fleet_config",
           "MIN_SENSORS_OUTLIERS"]

#: Fewest sensors for the robust outlier test: below ~40 the fleet median and MAD are themselves too
#: uncertain (the MAD's relative sd is ~1.17/sqrt(N), 18 % at N = 40) for a fixed |z| threshold.
MIN_SENSORS_OUTLIERS = 40
_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,99}$")


@dataclasses.dataclass(frozen=True)
class Limits:
    """``[fleet.limits]``: a sensor passes when every quantity is inside its limit (at the fleet's ``t0``)."""

    max_offset_ut: float = 10.0          # max_j |O_j|
    max_gain_error: float = 0.05         # max_j |S_jj - 1|
    max_cross_axis: float = 0.03         # max_{j != k} |S_jk|
    max_offset_tempco: float = 0.1       # max_j |Ko_j|, uT/C (temperature terms only)
    max_rmse_ut: float = 0.2             # max_j test RMSE
    min_coverage: float = 0.90           # min_j test coverage of the `level` intervals


@dataclasses.dataclass(frozen=True)
class SimulateFleet:
    n_sensors: int = 100
    n_rows: int = 5000
    seed: int = 0
    n_defective: int = 5
    noise_sd: float = 0.05
    rows_spread: float = 0.0


@dataclasses.dataclass(frozen=True)
class FleetConfig:
    """A validated fleet config (see the module docstring)."""

    name: str = "fleet"
    source: str | None = None            # "simulated"
    recordings: str | None = None        # folder or glob of CSV/Parquet files (id = file stem)
    manifest: str | None = None          # CSV with columns id,path
    batch_size: int = 64
    outlier_z: float = 7.0
    sensor_folders: bool = True
    figures: bool = True
    simulate: SimulateFleet = SimulateFleet()
    limits: Limits = Limits()
    test_fraction: float = 0.2
    split_seed: int = 0
    n_blocks: int = 1
    t0: float = 25.0
    temperature_terms: bool = True
    covariance: str = "white"
    level: float = 0.95
    sigma_in: str | list = "auto"
    temperature_unit: str = "C"          # [data]: how every recording is read (as a run's [data] keys)
    field_unit: str | None = None
    time_unit: str = "s"
    columns: dict = dataclasses.field(default_factory=dict)
    network: NetworkConfig = dataclasses.field(default_factory=lambda: NetworkConfig(interval_calibration="none"))
    sensor_figures: bool = False         # [output] figures: each sensor folder gets the single run's figures
    base: Path = Path(".")               # folder of the config file (relative paths)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("base")
        return d


_TABLES = {
    "": {"name", "fleet", "data", "split", "physics", "uq", "network", "output"},
    "data": {"temperature_unit", "field_unit", "time_unit", "columns"},
    "fleet": {"source", "recordings", "manifest", "batch_size", "outlier_z", "sensor_folders", "figures", "simulate",
              "limits"},
    "fleet.simulate": {f.name for f in dataclasses.fields(SimulateFleet)},
    "fleet.limits": {f.name for f in dataclasses.fields(Limits)},
    "split": {"test_fraction", "seed", "n_blocks", "kind"},
    "physics": {"t0", "temperature_terms", "covariance"},
    "uq": {"level", "sigma_in", "method"},
    "output": {"figures"},
}


def is_fleet_config(raw: dict) -> bool:
    """True for a parsed TOML config that describes a fleet (has a ``[fleet]`` table)."""
    return isinstance(raw, dict) and isinstance(raw.get("fleet"), dict)


def _check_keys(raw: dict, where: str) -> None:
    for k, v in raw.items():
        path = f"{where}.{k}" if where else k
        if k not in _TABLES[where]:
            raise ConfigError(f"Fleet config key {path!r} is not known; valid keys in "
                              f"{'[' + where + ']' if where else 'the top level'}: {sorted(_TABLES[where])}.")
        if path in _TABLES and path:
            if not isinstance(v, dict):
                raise ConfigError(f"Fleet config key {path!r} must be a table; got {v!r}.")
            _check_keys(v, path)


def _typed(value, tp, key):
    ok = {int: lambda v: isinstance(v, int) and not isinstance(v, bool),
          float: lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v),
          bool: lambda v: isinstance(v, bool), str: lambda v: isinstance(v, str)}[tp](value)
    if not ok:
        raise ConfigError(f"Fleet config key {key!r} must be a {tp.__name__}; got {value!r}.")
    return tp(value)


def _build(cls, raw: dict, prefix: str):
    kw = {}
    for f in dataclasses.fields(cls):
        if f.name in raw:
            tp = type(f.default)
            kw[f.name] = _typed(raw[f.name], tp, f"{prefix}.{f.name}")
    return cls(**kw)


def fleet_config_from_dict(raw: dict, *, base: Path = Path(".")) -> FleetConfig:
    """Validate a parsed fleet TOML into a :class:`FleetConfig` (unknown keys and bad values: :class:`ConfigError`)."""
    if not is_fleet_config(raw):
        raise ConfigError("This is not a fleet config: it has no [fleet] table (see configs/fleet_simulated.toml).")
    _check_keys(raw, "")
    fl, sp, ph, uq, da = (raw.get(k, {}) for k in ("fleet", "split", "physics", "uq", "data"))
    network = _network_config(raw.get("network", {}))
    chosen = [k for k in ("source", "recordings", "manifest") if fl.get(k) not in (None, "")]
    if len(chosen) != 1:
        raise ConfigError(f"[fleet] needs exactly one of source = \"simulated\", recordings = \"FOLDER or GLOB\" or "
                          f"manifest = \"FILE.csv\"; got {chosen or 'none'}.")
    if fl.get("source") not in (None, "simulated"):
        raise ConfigError(f"[fleet] source = {fl['source']!r} is not known; the only named source is \"simulated\" "
                          f"(give recordings = \"FOLDER or GLOB\" or manifest = \"FILE.csv\" for your files).")
    if fl.get("source") == "simulated" and da:
        raise ConfigError(f"[data] {sorted(da)}: a simulated fleet has no files to read; remove the [data] table "
                          f"(it applies to recordings = \"FOLDER or GLOB\" or manifest = \"FILE.csv\").")
    if sp.get("kind", "time_blocks") != "time_blocks":
        raise ConfigError(f"[split] kind = {sp['kind']!r}: a fleet holds out contiguous time blocks in every run "
                          f"(kind = \"time_blocks\"), so test rows are never neighbours of training rows.")
    if uq.get("method", "analytic") != "analytic":
        raise ConfigError(f"[uq] method = {uq['method']!r}: the fleet's physics uncertainty is the exact \"analytic\" "
                          f"method (one compiled batch); remove the key or set it to \"analytic\".")
    if ph.get("covariance", "white") not in ("white", "ar1"):
        raise ConfigError(f"[physics] covariance = {ph['covariance']!r} is not available for a fleet; use \"white\" "
                          f"or \"ar1\" (Newey-West: calibrate that sensor alone with bayesmag run).")
    t0 = ph.get("t0", 25.0)
    if isinstance(t0, str) or isinstance(t0, bool) or not isinstance(t0, (int, float)):
        raise ConfigError(f"[physics] t0 = {t0!r} must be a number (C): one reference temperature for the whole "
                          f"fleet keeps the sensors' offsets and gains comparable.")
    sig = uq.get("sigma_in", "auto")
    if sig != "auto" and not (isinstance(sig, list) and len(sig) == 4 and
                              all(isinstance(x, (int, float)) and not isinstance(x, bool) and x >= 0 for x in sig)):
        raise ConfigError(f"[uq] sigma_in = {sig!r} must be \"auto\" or four standard deviations "
                          f"[bx, by, bz, T] (uT, uT, uT, C), all >= 0.")
    cfg = FleetConfig(
        name=_typed(raw.get("name", "fleet"), str, "name"), source=fl.get("source"),
        recordings=fl.get("recordings") and _typed(fl["recordings"], str, "fleet.recordings"),
        manifest=fl.get("manifest") and _typed(fl["manifest"], str, "fleet.manifest"),
        batch_size=_typed(fl.get("batch_size", 64), int, "fleet.batch_size"),
        outlier_z=_typed(fl.get("outlier_z", 7.0), float, "fleet.outlier_z"),
        sensor_folders=_typed(fl.get("sensor_folders", True), bool, "fleet.sensor_folders"),
        figures=_typed(fl.get("figures", True), bool, "fleet.figures"),
        simulate=_build(SimulateFleet, fl.get("simulate", {}), "fleet.simulate"),
        limits=_build(Limits, fl.get("limits", {}), "fleet.limits"),
        test_fraction=_typed(sp.get("test_fraction", 0.2), float, "split.test_fraction"),
        split_seed=_typed(sp.get("seed", 0), int, "split.seed"), n_blocks=_typed(sp.get("n_blocks", 1), int, "split.n_blocks"),
        t0=float(t0), temperature_terms=_typed(ph.get("temperature_terms", True), bool, "physics.temperature_terms"),
        covariance=ph.get("covariance", "white"), level=_typed(uq.get("level", 0.95), float, "uq.level"),
        sigma_in=sig, network=network, **_data_keys(da),
        sensor_figures=_typed(raw.get("output", {}).get("figures", False), bool, "output.figures"), base=Path(base))
    s, lim = cfg.simulate, cfg.limits
    checks = [("fleet.batch_size", cfg.batch_size, cfg.batch_size >= 1, ">= 1"),
              ("fleet.outlier_z", cfg.outlier_z, cfg.outlier_z > 0, "> 0"),
              ("split.test_fraction", cfg.test_fraction, 0 < cfg.test_fraction < 1, "in (0, 1)"),
              ("split.n_blocks", cfg.n_blocks, cfg.n_blocks >= 1, ">= 1"),
              ("uq.level", cfg.level, 0 < cfg.level < 1, "in (0, 1)"),
              ("fleet.simulate.n_sensors", s.n_sensors, s.n_sensors >= 1, ">= 1"),
              ("fleet.simulate.n_rows", s.n_rows, s.n_rows >= 20, ">= 20"),
              ("fleet.simulate.n_defective", s.n_defective, 0 <= s.n_defective <= s.n_sensors, "in [0, n_sensors]"),
              ("fleet.simulate.noise_sd", s.noise_sd, s.noise_sd >= 0, ">= 0"),
              ("fleet.simulate.rows_spread", s.rows_spread, 0 <= s.rows_spread < 1, "in [0, 1)")]
    checks += [(f"fleet.limits.{f.name}", getattr(lim, f.name), getattr(lim, f.name) > 0, "> 0")
               for f in dataclasses.fields(Limits)]
    checks.append(("fleet.limits.min_coverage", lim.min_coverage, lim.min_coverage <= 1,
                   "a fraction in (0, 1], e.g. 0.95 for 95 %"))
    for key, value, ok, what in checks:
        if not ok:
            raise ConfigError(f"Fleet config key {key!r} is {value!r}; it must be {what}.")
    return cfg


def _data_keys(raw: dict) -> dict:
    """``[data]`` of a fleet: ``temperature_unit``, ``field_unit``, ``time_unit`` and ``columns`` of a run's
    ``[data]``, applied to every recording."""
    from bayesmag._src.core.data import TIME_UNITS
    choices = {"temperature_unit": ("C", "K"), "field_unit": ("uT", "nT", "mT", "G"), "time_unit": tuple(TIME_UNITS)}
    for k, ok in choices.items():
        if k in raw and raw[k] not in ok:
            raise ConfigError(f"Fleet config key 'data.{k}' is {raw[k]!r}; it must be one of {list(ok)}.")
    cols = raw.get("columns", {})
    if not isinstance(cols, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in cols.items()):
        raise ConfigError(f"Fleet config key 'data.columns' must be a table of canonical name = \"file column\" "
                          f"(e.g. bx_meas = \"Bx\"); got {cols!r}.")
    return {"temperature_unit": raw.get("temperature_unit", "C"), "field_unit": raw.get("field_unit"),
            "time_unit": raw.get("time_unit", "s"), "columns": dict(cols)}


def _read(cfg: FleetConfig, path) -> CalibrationData:
    """One recording, read with the fleet's ``[data]`` units and column mapping."""
    from bayesmag._src.core.frames import load_table
    return load_table(path, columns=cfg.columns or None, temperature_unit=cfg.temperature_unit,
                      field_unit=cfg.field_unit, time_unit=cfg.time_unit, require_reference=True)


def _network_config(raw) -> NetworkConfig:
    """``[network]`` of a fleet: the single run's table (same keys, defaults and checks), one likelihood, no
    conformal folds (``interval_calibration = "none"``, the fleet's default)."""
    from bayesmag._src.app.config import _build
    if not isinstance(raw, dict):
        raise ConfigError(f"Fleet config key 'network' must be a table; got {raw!r}.")
    raw = {"interval_calibration": "none", **raw}
    if raw["interval_calibration"] != "none":
        raise ConfigError(f"[network] interval_calibration = {raw['interval_calibration']!r}: a fleet trains one "
                          f"network per sensor (no cross-conformal fold networks); set it to \"none\" or calibrate "
                          f"that sensor alone with bayesmag run.")
    net = _build(NetworkConfig, raw, "network")
    if len(net.likelihoods) != 1:
        raise ConfigError(f"[network] likelihoods = {list(net.likelihoods)}: a fleet trains one likelihood per sensor; "
                          f"name one (compare likelihoods on one sensor with bayesmag run).")
    return net


def load_fleet_config(path, overrides=()) -> FleetConfig:
    """Read a fleet TOML file, apply ``--set key=value`` overrides, validate."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"Fleet config {path} does not exist or is not a file.")
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise ConfigError(f"{path} is not a valid TOML file: {e}") from None
    return fleet_config_from_dict(apply_overrides(raw, list(overrides)), base=path.parent)


# --------------------------------------------------------------------------- recordings


def _resolve(cfg: FleetConfig, p: str) -> Path:
    q = Path(p).expanduser()
    return q if q.is_absolute() or q.exists() else cfg.base / q


def _recording_paths(cfg: FleetConfig) -> list[tuple[str, Path]]:
    """(id, path) of every recording the config names; ids checked (file-name safe, unique)."""
    if cfg.manifest is not None:
        man = _resolve(cfg, cfg.manifest)
        if not man.is_file():
            raise DataError(f"[fleet] manifest {man} does not exist.")
        lines = [ln.strip() for ln in man.read_text(encoding="utf-8-sig").splitlines() if ln.strip()]
        if not lines or [c.strip() for c in lines[0].split(",")] != ["id", "path"]:
            raise DataError(f"manifest {man}: the first line must be the header 'id,path'; got {lines[:1]}.")
        items = []
        for k, ln in enumerate(lines[1:], start=2):
            parts = [c.strip() for c in ln.split(",")]
            if len(parts) != 2 or not all(parts):
                raise DataError(f"manifest {man}, line {k}: expected 'id,path'; got {ln!r}.")
            p = Path(parts[1]).expanduser()
            items.append((parts[0], p if p.is_absolute() else man.parent / p))
    else:
        spec = cfg.recordings
        folder = _resolve(cfg, spec)
        if folder.is_dir():
            files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".csv", ".parquet", ".pq"))
        else:
            pattern = spec if Path(spec).is_absolute() or globlib.glob(spec) else str(cfg.base / spec)
            files = sorted(Path(p) for p in globlib.glob(pattern))
        if not files:
            raise DataError(f"[fleet] recordings = {spec!r} matches no CSV or Parquet file.")
        items = [(p.stem, p) for p in files]
    seen = {}
    for sid, p in items:
        if not _ID.match(sid):
            raise DataError(f"sensor id {sid!r} ({p}) is not usable as a folder name: use letters, digits, '_', '-', '.'.")
        if sid in seen:
            raise DataError(f"sensor id {sid!r} appears twice ({seen[sid]} and {p}); ids must be unique.")
        seen[sid] = p
        if not p.is_file():
            raise DataError(f"sensor {sid}: recording {p} does not exist.")
    return items


def load_recordings(cfg: FleetConfig, errors: list | None = None
                    ) -> tuple[list[CalibrationData], tuple[str, ...], object]:
    """The fleet's recordings, ids and (simulated fleets) the ground truth. ``errors``: a list to collect the
    sensors whose file cannot be read into (they are left out); None: the first raises."""
    if cfg.source == "simulated":
        from bayesmag._src.core.simulate_fleet import simulate_fleet
        s = cfg.simulate
        recs, truth = simulate_fleet(s.n_sensors, s.n_rows, seed=s.seed, n_defective=s.n_defective,
                                     noise_sd=s.noise_sd, rows_spread=s.rows_spread)
        return recs, truth.ids, truth
    recs, ids = [], []
    for sid, p in _recording_paths(cfg):
        try:
            recs.append(_read(cfg, p))
        except DataError as e:
            if errors is None:
                raise DataError(f"sensor {sid}: {e}") from None
            errors.append(f"sensor {sid}: {' '.join(str(e).split())}")
            continue
        ids.append(sid)
    return recs, tuple(ids), None


def _raise_sensor_errors(errors: list, n: int) -> None:
    """One :class:`DataError` naming every sensor whose recording cannot be calibrated (the fleet stopped at the
    first, so a fleet with three bad files took three reruns: sixth outside pass)."""
    if len(errors) == 1:
        raise DataError(errors[0])
    if errors:
        raise DataError(f"{len(errors)} of {n} sensors cannot be calibrated (nothing was written; fix each, or "
                        f"leave its recording out, and rerun): " + " | ".join(errors))


def sensor_split_rows(saved: dict) -> tuple[CalibrationData, CalibrationData]:
    """A fleet sensor's training and test rows, reloaded through the fleet config saved with its calibration
    (``calibration.json``'s ``config``: :meth:`FleetConfig.to_dict` plus ``sensor_id`` and ``fleet_base``);
    ``bayesmag export`` measures the accuracy an export loses on them."""
    d = dict(saved)
    sid, base = d.pop("sensor_id"), Path(d.pop("fleet_base", "."))
    names = {f.name for f in dataclasses.fields(FleetConfig)} - {"simulate", "limits", "network", "base"}
    cfg = FleetConfig(**{k: v for k, v in d.items() if k in names}, simulate=SimulateFleet(**d["simulate"]),
                      limits=Limits(**d["limits"]), base=base)
    if cfg.source == "simulated":
        recs, ids, _ = load_recordings(cfg)
        rec = recs[ids.index(sid)]
    else:
        rec = _read(cfg, dict(_recording_paths(cfg))[sid])
    sp = make_split(rec, kind="time_blocks", test_fraction=cfg.test_fraction, seed=cfg.split_seed,
                    n_blocks=cfg.n_blocks)
    return rec.subset(sp.train), rec.subset(sp.test)


# --------------------------------------------------------------------------- job


def _sigma_in(cfg: FleetConfig, train: FleetData) -> np.ndarray:
    if cfg.sigma_in == "auto":
        return fleet_input_noise(train)
    return np.broadcast_to(np.diag(np.asarray(cfg.sigma_in, np.float64) ** 2), (train.n_sensors, 4, 4)).copy()


def _limits_quantities(theta: np.ndarray, names: tuple[str, ...], rmse: np.ndarray, cover: np.ndarray) -> dict:
    """(N,) per-sensor quantities compared with [fleet.limits]."""
    ix = {n: i for i, n in enumerate(names)}
    S = theta[:, :, [ix["S_x"], ix["S_y"], ix["S_z"]]]                       # (N, 3, 3)
    off = ~np.eye(3, dtype=bool)
    q = {"max_offset_ut": np.abs(theta[:, :, ix["O"]]).max(axis=1),
         "max_gain_error": np.abs(np.diagonal(S, axis1=1, axis2=2) - 1).max(axis=1),
         "max_cross_axis": np.abs(S[:, off]).max(axis=1),
         "max_rmse_ut": rmse.max(axis=1), "min_coverage": cover.min(axis=1)}
    if "Ko" in ix:
        q["max_offset_tempco"] = np.abs(theta[:, :, ix["Ko"]]).max(axis=1)
    return q


#: The start of :func:`~bayesmag._src.core.fit._design_warnings`' temperature-span warning (its own fail reason here).
_SPAN_WARNING = "The training temperature spans only"


def _sensor_warnings(cfg: FleetConfig, model, fit, trains, train_pred, uq, n_test) -> tuple[list, list]:
    """Each sensor's design warnings (those of :func:`~bayesmag.fit_physics`: too few rows per parameter, a narrow
    temperature span, gross outliers) and its input-noise warning or None (``bayesmag run``'s, on its test rows)."""
    import types

    from bayesmag._src.pipeline.settings import input_noise_warning
    from bayesmag._src.core.fit import _design_warnings
    source = "auto" if cfg.sigma_in == "auto" else "config"
    design, noise = [], []
    for i, d in enumerate(trains):
        design.append(list(_design_warnings(d, model, fit.cov[i], d.b_ref - train_pred[i, :d.n])))
        noise.append(input_noise_warning(source, uq.aleatoric[i, :int(n_test[i])],
                                         types.SimpleNamespace(s2=fit.s2[i])))
    return design, noise


def _refuse_shared_recordings(ids, files) -> None:
    """:class:`DataError` when two sensors' recordings are the same bytes (one file named twice, or a copy): each
    would get a certificate and firmware parameters fitted on the other unit's data (sixth outside pass: both
    passed sign-off)."""
    by_hash: dict = {}
    for sid, f in zip(ids, files):
        if f is not None:
            by_hash.setdefault(f[1], []).append((sid, f[0]))
    same = [v for v in by_hash.values() if len(v) > 1]
    if same:
        groups = "; ".join(" and ".join(f"sensor {sid} ({p})" for sid, p in g) for g in same[:3])
        raise DataError(f"{groups}: the recordings are identical (same sha256), so one unit would be certified on "
                        f"another's data. Give each sensor its own recording (check the manifest or the copied "
                        f"files).")


def run_fleet(cfg: FleetConfig, out, *, progress: bool = True) -> dict:
    """Run the fleet job described by ``cfg`` and write its outputs into ``out`` (staged, swapped in whole)."""
    from bayesmag._src.app.outdir import reserve, staging_dir

    out = Path(out)
    paths = [] if cfg.source == "simulated" else _recording_paths(cfg)
    inputs = [p for _, p in paths]
    if cfg.manifest is not None:
        inputs.append(_resolve(cfg, cfg.manifest))
    with reserve(out, inputs=inputs, kind="fleet"):       # an --out holding a recording is refused before any work
        timings = {}
        t_all = t = time.perf_counter()
        errors: list[str] = []
        recs, ids, truth = load_recordings(cfg, errors)
        model = PhysicsModel.paper(t0=cfg.t0, temperature=cfg.temperature_terms)
        trains, tests, test_rows, splits = [], [], [], []
        for sid, d in zip(ids, recs):
            try:
                validate(d, n_params=model.n_params, origin=f"sensor {sid}",
                         need_temperature_variation=cfg.temperature_terms)
                sp = make_split(d, kind="time_blocks", test_fraction=cfg.test_fraction, seed=cfg.split_seed,
                                n_blocks=cfg.n_blocks)
            except ValueError as e:         # DataError is a ValueError
                errors.append(f"sensor {sid}: {' '.join(str(e).split())}")
                continue
            trains.append(d.subset(sp.train))
            tests.append(d.subset(sp.test))
            test_rows.append(sp.test)
            splits.append(sp.as_dict())
        _raise_sensor_errors(errors, len(paths) or len(ids))
        from bayesmag._src.core.datasets import sha256_of     # each sensor's file, as a run records its recording
        files = [(p.resolve(), sha256_of(p)) for _, p in paths] or [None] * len(ids)
        _refuse_shared_recordings(ids, files)
        train = FleetData.from_recordings(trains, ids)
        test = FleetData.from_recordings(tests, ids)
        timings["load"] = time.perf_counter() - t
        say = (lambda m: print(f"  fleet: {m}", file=sys.stderr, flush=True)) if progress else (lambda m: None)
        say(f"{len(ids)} recordings loaded ({timings['load']:.1f} s); fitting in batches of {cfg.batch_size}")

        t = time.perf_counter()
        fit = fit_fleet(train, model, covariance_method=cfg.covariance, batch_size=cfg.batch_size)
        timings["physics_fit"] = time.perf_counter() - t
        say(f"physics fit {timings['physics_fit']:.1f} s; propagating the uncertainty")
        t = time.perf_counter()
        sigma_in = _sigma_in(cfg, train)
        uq_batch = max(1, min(cfg.batch_size, 16))
        uq_train = fleet_uncertainty(fit, train, sigma_in, batch_size=uq_batch)
        m = train.mask[..., None]
        mean_alea2 = (np.where(m, uq_train.aleatoric**2, 0).sum(axis=1) / train.n_rows[:, None])
        residual_sd = np.sqrt(np.maximum(fit.s2 - mean_alea2, 0.0))
        del uq_train
        uq = fleet_uncertainty(fit, test, sigma_in, batch_size=uq_batch)
        timings["physics_uq"] = time.perf_counter() - t

        from scipy.stats import norm
        zq = norm.ppf(0.5 + cfg.level / 2)
        mt = test.mask[..., None]
        total = np.sqrt(uq.aleatoric**2 + uq.epistemic**2 + residual_sd[:, None, :] ** 2)
        err = test.b_ref - uq.mean
        nt = test.n_rows[:, None]
        rmse = np.sqrt(np.where(mt, err**2, 0).sum(axis=1) / nt)
        cover = np.where(mt, np.abs(err) <= zq * total, False).sum(axis=1) / nt
        raw_rmse = np.sqrt(np.where(mt, (test.b_ref - test.b_meas) ** 2, 0).sum(axis=1) / nt)
        from bayesmag._src.core.fleet_fit import fleet_predict
        train_pred = fleet_predict(fit, train, batch_size=cfg.batch_size)
        design, noise = _sensor_warnings(cfg, model, fit, trains, train_pred, uq, test.n_rows)

        stages = None
        if cfg.sensor_folders or cfg.network.enabled:
            from bayesmag._src.app.fleet_sensors import fleet_networks, sensor_stages
            t = time.perf_counter()
            stages = sensor_stages(ids, trains, tests, test_rows, splits, fit, uq, sigma_in, residual_sd,
                                   train_pred, design, level=cfg.level)
            timings["sensor_predictions"] = time.perf_counter() - t
        physics_rmse, physics_cover = rmse, cover
        if cfg.network.enabled:
            say(f"training {len(ids)} residual networks in batches of {cfg.batch_size}")
            t = time.perf_counter()
            stages, timings["network_train"] = fleet_networks(stages, cfg.network, level=cfg.level,
                                                              batch_size=cfg.batch_size, progress=progress)
            timings["hybrid"] = time.perf_counter() - t - timings["network_train"]
            name = cfg.network.likelihoods[0]
            hyb = [st.hybrid.predictions[name] for st in stages]
            rmse = np.array([np.sqrt(np.mean((st.test.b_ref - h.mean) ** 2, axis=0)) for st, h in zip(stages, hyb)])
            from bayesmag._src.app.fleet_sensors import interval
            cover = np.array([np.mean((st.test.b_ref >= lo) & (st.test.b_ref <= hi), axis=0)
                              for st, h in zip(stages, hyb) for lo, hi in [interval(h, cfg.level)]])

        names = model.param_names
        q = _limits_quantities(fit.theta, names, rmse, cover)
        # a sensor whose training temperature barely varies has no measured thermal terms (the fit's Ks and Ko are
        # extrapolations, core.fit.MIN_TEMPERATURE_SPAN_C): it cannot be signed off, and its tempco is not scored
        from bayesmag._src.core.fit import MIN_TEMPERATURE_SPAN_C
        thermal = "Ko" in names
        span = np.array([float(np.ptp(train.temperature[i][train.mask[i]])) for i in range(len(ids))])
        fails, identifiable = [], fit.identifiable       # (N,), computed once
        for i in range(len(ids)):
            narrow = thermal and span[i] < MIN_TEMPERATURE_SPAN_C
            f = [k for k, v in q.items() if not (narrow and k == "max_offset_tempco")
                 and (v[i] < getattr(cfg.limits, k) if k.startswith("min") else v[i] > getattr(cfg.limits, k))]
            if narrow:
                f.append("temperature_span")
            if not fit.converged[i]:
                f.append("not_converged")
            if not identifiable[i]:
                f.append("unidentifiable")
            if [w for w in design[i] if not (narrow and w.startswith(_SPAN_WARNING))]:
                f.append("design")          # too few rows, gross outliers (the span has its own reason)
            if noise[i]:
                f.append("input_noise")     # the intervals (and so the coverage verdict) are too wide
            fails.append(f)
        N = len(ids)
        feat_names = [f"{n}[{ax}]" for ax in AXES for n in names] + [f"log_rmse[{ax}]" for ax in AXES]
        feats = np.concatenate([fit.theta.reshape(N, -1), np.log(np.maximum(rmse, 1e-300))], axis=1)
        outliers_computed = N >= MIN_SENSORS_OUTLIERS
        z = robust_z(feats, axis=0) if outliers_computed else np.full_like(feats, np.nan)
        zmax = np.abs(z).max(axis=1) if outliers_computed else np.full(N, np.nan)
        outlier = zmax > cfg.outlier_z if outliers_computed else np.zeros(N, bool)
        flagged = np.array([bool(fails[i]) or bool(outlier[i]) for i in range(N)])

        notes = [[n for n, on in (
            (f"the training temperature spans only {span[i]:.3g} C (< {MIN_TEMPERATURE_SPAN_C:g} C): the thermal "
             f"terms are not measured, so the tempco is not scored and the sensor cannot be signed off (fails "
             f"'temperature_span'); record it over a wider range", thermal and span[i] < MIN_TEMPERATURE_SPAN_C),
            (f"the data cannot inform every parameter (smallest relative singular value "
             f"{float(fit.sv_ratio[i].min()):.2g}, or a covariance that is not positive definite): its parameters and "
             f"their uncertainties are meaningless, so the calibration must not be used (fails 'unidentifiable'); "
             f"record more rows with every field axis and the temperature varied", not identifiable[i])) if on]
            for i in range(len(ids))]
        sensors = []
        for i, sid in enumerate(ids):
            top = [] if not outliers_computed else [
                {"quantity": feat_names[j], "z": float(z[i, j])}
                for j in np.argsort(-np.abs(z[i]))[:3] if abs(z[i, j]) > cfg.outlier_z]
            sensors.append({
                "id": sid, "n_train": int(train.n_rows[i]), "n_test": int(test.n_rows[i]),
                "verdict": "fail" if flagged[i] else "pass", "fails_limits": fails[i],
                "outlier": bool(outlier[i]), "max_abs_robust_z": None if not outliers_computed else float(zmax[i]),
                "outlying_quantities": top,
                "limits_quantities": {k: float(v[i]) for k, v in q.items()},
                "training_temperature_span_c": float(span[i]),
                **({"notes": notes[i]} if notes[i] else {}),
                "warnings": [*design[i], *([noise[i]] if noise[i] else [])],
                "test_rmse": dict(zip(AXES, map(float, rmse[i]))), "raw_rmse": dict(zip(AXES, map(float, raw_rmse[i]))),
                "test_coverage": dict(zip(AXES, map(float, cover[i]))),
                "prediction": f"hybrid ({cfg.network.likelihoods[0]})" if cfg.network.enabled else "physics",
                **({"physics_test_rmse": dict(zip(AXES, map(float, physics_rmse[i]))),
                    "physics_test_coverage": dict(zip(AXES, map(float, physics_cover[i])))}
                   if cfg.network.enabled else {}),
                "residual_sd": dict(zip(AXES, map(float, residual_sd[i]))),
                "sigma_in_sd": dict(zip(["bx", "by", "bz", "T"], map(float, np.sqrt(np.diagonal(sigma_in[i]))))),
                "solver": {"result": [int(r) for r in fit.result[i]], "steps": [int(s) for s in fit.n_steps[i]]},
            })
        pct = lambda a: {"median": float(np.median(a)), "p05": float(np.percentile(a, 5)),  # noqa: E731
                         "p95": float(np.percentile(a, 95)), "min": float(np.min(a)), "max": float(np.max(a)),
                         "robust_sd": float(1.4826 * np.median(np.abs(a - np.median(a))))}
        distribution = {feat_names[j]: pct(feats[:, j]) for j in range(feats.shape[1])}
        distribution.update({f"limit:{k}": pct(v) for k, v in q.items()})
        summary = {
            "name": cfg.name, "n_sensors": N, "n_pass": int((~flagged).sum()), "n_fail": int(flagged.sum()),
            "flagged": [ids[i] for i in np.flatnonzero(flagged)],
            "failed_limits": {ids[i]: fails[i] for i in range(N) if fails[i]},
            "outliers": [ids[i] for i in np.flatnonzero(outlier)],
            "warnings": {sid: x["warnings"] for sid, x in zip(ids, sensors) if x["warnings"]},
            "outlier_test": ({"computed": True, "threshold_abs_z": cfg.outlier_z, "quantities": feat_names}
                             if outliers_computed else
                             {"computed": False, "reason": f"{N} sensors < {MIN_SENSORS_OUTLIERS}: the fleet median "
                                                           f"and MAD are too uncertain for robust z-scores"}),
            "limits": dataclasses.asdict(cfg.limits), "level": cfg.level, "t0": cfg.t0,
            "network": ({**cfg.network.table(), "verdicts_use": "the hybrid prediction's test RMSE and coverage"}
                        if cfg.network.enabled else {"enabled": False}),
            "param_names": list(names), "distribution": distribution, "sensors": sensors,
        }
        if truth is not None:
            planted = set(truth.defects)
            got = set(summary["flagged"])
            summary["ground_truth"] = {**truth.to_json(), "planted_flagged": sorted(planted & got),
                                       "planted_missed": sorted(planted - got), "false_flags": sorted(got - planted),
                                       "exact": planted == got}
        t = time.perf_counter()
        say(f"uncertainty {timings['physics_uq']:.1f} s; writing {out}")
        with staging_dir(out, kind="fleet") as tmp:
            from bayesmag._src.app.fleet_report import write_fleet_outputs
            sources = ([f"simulated fleet sensor {sid}" for sid in ids] if cfg.source == "simulated" else
                       [str(p) for _, p in _recording_paths(cfg)])
            write_fleet_outputs(tmp, cfg, summary, stages=stages, sigma_in=sigma_in, ids=ids, feats=feats,
                                feat_names=feat_names, z=z, flagged=flagged, timings=timings, sources=sources,
                                files=files)
            timings["write"] = time.perf_counter() - t
            timings["total"] = time.perf_counter() - t_all
            summary["timings"] = {k: round(v, 3) for k, v in timings.items()}
            from bayesmag._src.core.jsonio import write_json
            write_json(tmp / "fleet.json", summary)
            from bayesmag._src.app.fleet_report import write_fleet_report
            write_fleet_report(tmp, summary)
    return summary
