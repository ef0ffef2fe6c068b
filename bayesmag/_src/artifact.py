"""Calibrations users keep: a versioned, self-contained, non-pickle artifact; load it and apply it.

A run folder holds the calibration as two files:

* ``calibration.json`` -- format name and version, package version, the physics model
  (terms and transforms with their settings), parameter names, the input-noise covariance,
  residual standard deviations, the training domain, the likelihood family, the resolved
  config, and the names of the arrays below;
* ``calibration.npz`` -- numeric arrays (``theta`` (3, p), ``cov`` (3, p, p), and, when the
  hybrid stage ran, the network weights and standardisation under ``network/...`` keys),
  written with ``numpy.savez`` (loaded with ``allow_pickle=False``).

:func:`load` returns a :class:`Calibration` whose :meth:`~Calibration.predict` is sklearn-like:
it takes a recording (no reference needed) and returns calibrated values with their
uncertainty parts, a central interval and an ``in_domain`` flag per row.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from .data import AXES, CalibrationData
from .domain import Domain
from .physics import PhysicsModel, ThermoAffine

__all__ = ["Calibration", "save_calibration", "load", "ArtifactError", "FORMAT", "FORMAT_VERSION"]

FORMAT = "bayesmag.calibration"
FORMAT_VERSION = 1
#: Versions this code reads (older ones listed here once a converter exists).
READABLE_VERSIONS = (1,)


class ArtifactError(ValueError):
    """A calibration folder that cannot be loaded; the message says exactly why."""


def _component_registry() -> dict[str, type]:
    from . import catalogue  # noqa: F401  (registers catalogue terms)
    from .physics import EXTRA_TERMS
    return {"thermo_affine": ThermoAffine, **EXTRA_TERMS}


def model_to_json(model: PhysicsModel) -> dict:
    def one(c):
        return {"name": c.name, "settings": {f.name: getattr(c, f.name) for f in dataclasses.fields(c)}}
    return {"terms": [one(t) for t in model.terms], "transforms": [one(t) for t in model.transforms]}


def model_from_json(d: dict) -> PhysicsModel:
    reg = _component_registry()

    def build(item):
        name = item["name"]
        if name not in reg:
            raise ArtifactError(f"the calibration uses physics component {name!r}, which this bayesmag does not "
                                f"know (known: {sorted(reg)}); install the version that wrote it.")
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

    @property
    def param_names(self):
        return self.model.param_names

    def physics_fit(self):
        """A :class:`~bayesmag.PhysicsFit`-like view for :func:`~bayesmag.physics_uncertainty`."""
        from .fit import PhysicsFit
        s2 = self.s2 if self.s2 is not None else self.residual_sd**2
        empty = ({}, {}, {})
        return PhysicsFit(model=self.model, theta=self.theta, cov=self.cov, s2=s2, n=0,
                          rmse_in_sample=np.full(3, np.nan), result=("converged",) * 3, n_steps=np.zeros(3),
                          covariance_method="", cov_info=empty, diagnostics=empty)

    def _family_dist(self, mean, var, shape):
        from .likelihoods import moment_match
        spec = self.network["meta"]["spec"]
        if self.likelihood == "student_t":
            df = shape.get("df") if spec.get("df") is None else spec["df"]
            return moment_match("student_t", mean, var, df=df)
        return moment_match(self.likelihood, mean, var)

    def predict(self, data: CalibrationData, *, level: float | None = None, method: str = "analytic",
                n_params: int = 100, n_qmc: int = 256, seed: int = 0, chunk_size: int = 100_000,
                progress: bool = False) -> dict[str, np.ndarray]:
        """Calibrated field and uncertainty for every row of ``data`` (reference columns not needed).

        Rows with non-finite inputs are not dropped: their outputs are NaN and ``valid`` is False.
        Returns a dict of (n, 3) arrays: ``calibrated, aleatoric_physics, epistemic_physics,
        residual_physics, total, lower, upper`` (plus ``aleatoric_nn, epistemic_nn`` with a network),
        and (n,) arrays ``in_domain`` and ``valid``.
        """
        from .likelihoods import Gaussian
        from .physics import Inputs
        from .physics_uq import physics_uncertainty

        level = self.level if level is None else level
        n = data.n
        x = np.column_stack([data.b_meas, data.temperature])
        valid = np.isfinite(x).all(axis=1) & np.isfinite(data.time)
        out = {k: np.full((n, 3), np.nan) for k in ("calibrated", "aleatoric_physics", "epistemic_physics",
                                                    "residual_physics", "total", "lower", "upper")}
        idx = np.flatnonzero(valid)
        fit = self.physics_fit()
        starts = range(0, idx.size, chunk_size)
        if progress:
            from tqdm.auto import tqdm
            starts = tqdm(starts, desc="apply", unit="chunk", leave=False)
        for lo in starts:
            rows = idx[lo:lo + chunk_size]
            inp = Inputs(data.b_meas[rows], data.temperature[rows], data.time[rows], data.run[rows])
            uq = physics_uncertainty(fit, inp, sigma_in=self.sigma_in, method=method, n_params=n_params,
                                     n_qmc=n_qmc, seed=seed, chunk_size=min(4096, max(256, rows.size)))
            resid = np.broadcast_to(self.residual_sd, uq.mean.shape)
            mean, var = uq.mean, uq.aleatoric**2 + resid**2 + uq.epistemic**2
            out["aleatoric_physics"][rows] = uq.aleatoric
            out["epistemic_physics"][rows] = uq.epistemic
            out["residual_physics"][rows] = resid
            dist = None
            if self.network is not None:
                nn_mean, nn_alea, nn_epi, shape = apply_network(self.network, data.subset(rows))
                out.setdefault("aleatoric_nn", np.full((n, 3), np.nan))[rows] = np.sqrt(nn_alea)
                out.setdefault("epistemic_nn", np.full((n, 3), np.nan))[rows] = np.sqrt(nn_epi)
                mean = mean + nn_mean
                if self.network["meta"].get("fusion", "moment_match") == "paper":
                    var = uq.aleatoric**2 + nn_alea + nn_epi + uq.epistemic**2
                else:   # the network's aleatoric part already holds the propagated input noise
                    var = nn_alea + nn_epi + uq.epistemic**2
                    dist = self._family_dist(mean, var, shape)
            sd = np.sqrt(var)
            dist = Gaussian(mean, sd) if dist is None else dist
            lo_, hi_ = (np.asarray(a) for a in dist.interval(level))
            out["calibrated"][rows], out["total"][rows] = mean, sd
            out["lower"][rows], out["upper"][rows] = lo_, hi_
        in_dom = np.zeros(n, dtype=bool)
        in_dom[valid] = ~self.domain.outside(data.subset(valid), out["calibrated"][valid]).any(axis=1)
        out["in_domain"] = in_dom
        out["valid"] = valid
        return out


def save_calibration(path: Path, *, fit, sigma_in: np.ndarray, residual_sd: np.ndarray, domain: Domain,
                     config: dict, likelihood: str = "gaussian", level: float = 0.95,
                     network: dict | None = None) -> None:
    """Write ``calibration.json`` and ``calibration.npz`` into folder ``path``."""
    from .. import __version__
    arrays = {"theta": np.asarray(fit.theta), "cov": np.asarray(fit.cov), "sigma_in": np.asarray(sigma_in),
              "residual_sd": np.asarray(residual_sd, dtype=np.float64), "s2": np.asarray(fit.s2)}
    meta_net = None
    if network is not None:
        meta_net = network["meta"]
        for k, v in network["arrays"].items():
            arrays[f"network/{k}"] = np.asarray(v)
    doc = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "package_version": __version__,
        "model": model_to_json(fit.model), "param_names": list(fit.model.param_names),
        "axes": list(AXES), "likelihood": likelihood, "level": level,
        "domain": dataclasses.asdict(domain), "config": config, "network": meta_net,
        "arrays": {"file": "calibration.npz", "keys": sorted(arrays)},
        "units": {"field": "uT", "temperature": "C", "time": "s"},
    }
    np.savez(Path(path) / "calibration.npz", **arrays)
    (Path(path) / "calibration.json").write_text(json.dumps(doc, indent=2, default=_json_default))


def _json_default(o: Any):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def load(path: str | Path) -> Calibration:
    """Load the calibration a ``bayesmag run`` wrote into folder ``path``."""
    path = Path(path)
    j, z = path / "calibration.json", path / "calibration.npz"
    if not path.is_dir():
        raise ArtifactError(f"{path} is not a folder; give the run folder that holds calibration.json.")
    missing = [p.name for p in (j, z) if not p.exists()]
    if missing:
        raise ArtifactError(f"{path} is incomplete: {missing} missing. Re-run `bayesmag run` to write a full calibration.")
    try:
        doc = json.loads(j.read_text())
    except json.JSONDecodeError as e:
        raise ArtifactError(f"{j} is not valid JSON ({e}); the file is damaged.") from None
    if doc.get("format") != FORMAT:
        raise ArtifactError(f"{j} is not a bayesmag calibration (format {doc.get('format')!r}).")
    v = doc.get("format_version")
    if v not in READABLE_VERSIONS:
        raise ArtifactError(f"{j} has calibration format version {v}; this bayesmag reads versions "
                            f"{list(READABLE_VERSIONS)}. It was written by bayesmag {doc.get('package_version')}: "
                            f"install that version (or newer) to apply it.")
    with np.load(z, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    need = {"theta", "cov", "sigma_in", "residual_sd"}
    if not need <= set(arrays):
        raise ArtifactError(f"{z} lacks arrays {sorted(need - set(arrays))}; the file is damaged or incomplete.")
    model = model_from_json(doc["model"])
    if tuple(doc["param_names"]) != model.param_names or arrays["theta"].shape != (3, model.n_params):
        raise ArtifactError(f"{path}: parameters do not match the model description; the files are inconsistent.")
    network = None
    if doc.get("network") is not None:
        network = {"meta": doc["network"],
                   "arrays": {k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith("network/")}}
    dom = doc["domain"]
    return Calibration(model=model, theta=arrays["theta"], cov=arrays["cov"], sigma_in=arrays["sigma_in"],
                       residual_sd=arrays["residual_sd"],
                       domain=Domain(tuple(dom["low"]), tuple(dom["high"]), dom.get("margin", 0.05),
                                     dom.get("out_low") and tuple(dom["out_low"]),
                                     dom.get("out_high") and tuple(dom["out_high"])),
                       likelihood=doc.get("likelihood", "gaussian"), level=doc.get("level", 0.95),
                       config=doc.get("config", {}), network=network, package_version=doc.get("package_version", ""),
                       s2=arrays.get("s2"))


# --------------------------------------------------------------------------- network weights


def network_to_artifact(net, *, passes: int, seed: int, fusion: str) -> dict:
    """A trained :class:`~bayesmag._src.network.ResidualNetwork` as JSON metadata + named arrays."""
    spec = {f.name: getattr(net.spec, f.name) for f in dataclasses.fields(net.spec)}
    spec["log_scale_clip"] = list(spec["log_scale_clip"])
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
    """Rebuild the :class:`~bayesmag._src.network.ResidualNetwork` saved by :func:`network_to_artifact`."""
    import jax.numpy as jnp

    from .network import Dense, NetworkSpec, ResidualNetwork, Standardizer

    meta, arr = network["meta"], network["arrays"]
    spec_d = dict(meta["spec"])
    spec_d["log_scale_clip"] = tuple(spec_d["log_scale_clip"])
    known = {f.name for f in dataclasses.fields(NetworkSpec)}
    unknown = set(spec_d) - known
    if unknown:
        raise ArtifactError(f"the saved network has settings {sorted(unknown)} this bayesmag does not know; "
                            f"install the version that wrote it ({known=}).")
    spec = NetworkSpec(**spec_d)
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
    from .network import mc_predict

    net = network_from_artifact(network)
    x = np.column_stack([data.b_meas, data.temperature])
    p = mc_predict(net, x, passes=network["meta"]["passes"], seed=network["meta"]["seed"])
    return p.mean, p.aleatoric**2, p.epistemic**2, p.shape
