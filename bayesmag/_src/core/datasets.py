"""Named datasets: where to find them, how to fetch and verify them.

A dataset named ``NAME`` is looked up, in order, in ``$BAYESMAG_DATA_DIR/NAME/``,
then in the user cache ``$XDG_CACHE_HOME/bayesmag/NAME/`` (``~/.cache/bayesmag``).
``bayesmag data fetch NAME`` downloads it from its pinned URL into the cache and
checks its sha256.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import urllib.request
from pathlib import Path
from typing import Callable

from bayesmag._src.core.data import CalibrationData, DataError, load_belsten

__all__ = ["Dataset", "DATASETS", "find_dataset", "fetch_dataset", "load_dataset", "cache_dir"]


@dataclasses.dataclass(frozen=True)
class Dataset:
    name: str
    filename: str
    url: str
    sha256: str
    loader: Callable[[Path], CalibrationData]
    description: str


DATASETS: dict[str, Dataset] = {
    "belsten2023": Dataset(
        name="belsten2023",
        filename="full_data.csv",
        url=(
            "https://raw.githubusercontent.com/MIT-STARLab/AV-MagEval-Data/"
            "c1e62a166f5e10752d0d6975e705226548f17495/automated_calibration/full_data.csv"
        ),
        sha256="8fe453c880fa8c2f1e69a5e732ec3833c91f0dec0bfc75be0099381ed08c511a",
        loader=load_belsten,
        description="HMC1053 AMR vs MEDA FVM400 reference, 6 Helmholtz-coil campaigns, 3378 rows (Belsten et al. 2023)",
    ),
}


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "bayesmag"


def _check_name(name: str) -> Dataset:
    if name not in DATASETS:
        raise DataError(f"Dataset {name!r} is not known; known datasets: {sorted(DATASETS)}. "
                        f"For your own recording use [data] path = \"file.csv\".")
    return DATASETS[name]


def _candidates(ds: Dataset) -> list[Path]:
    out = []
    env = os.environ.get("BAYESMAG_DATA_DIR")
    if env:
        out.append(Path(env) / ds.name / ds.filename)
    out.append(cache_dir() / ds.name / ds.filename)
    return out


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def find_dataset(name: str) -> Path:
    """Path of dataset ``name``'s file; :class:`DataError` saying where it looked and how to fetch it."""
    ds = _check_name(name)
    cands = _candidates(ds)
    for p in cands:
        if p.exists():
            return p
    looked = ", ".join(str(p) for p in cands)
    raise DataError(
        f"Dataset {name!r} was not found (looked in: {looked}). Run `bayesmag data fetch {name}` to download it, "
        f"or set BAYESMAG_DATA_DIR to a folder containing {name}/{ds.filename}."
    )


def fetch_dataset(name: str, *, dest: Path | None = None, force: bool = False) -> Path:
    """Download dataset ``name`` from its pinned URL into the cache and verify its sha256."""
    ds = _check_name(name)
    target = (dest or cache_dir()) / ds.name / ds.filename
    if target.exists() and not force:
        if sha256_of(target) == ds.sha256:
            return target
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_suffix(target.suffix + ".part")
    with urllib.request.urlopen(ds.url, timeout=60) as r, open(tmp, "wb") as f:
        f.write(r.read())
    got = sha256_of(tmp)
    if got != ds.sha256:
        tmp.unlink(missing_ok=True)
        raise DataError(f"Downloaded {ds.url} has sha256 {got}, expected {ds.sha256}; the file was discarded.")
    tmp.replace(target)
    return target


def load_dataset(name: str) -> CalibrationData:
    """Find and load dataset ``name`` (verifying its sha256)."""
    ds = _check_name(name)
    path = find_dataset(name)
    got = sha256_of(path)
    if got != ds.sha256:
        raise DataError(f"{path} has sha256 {got}, but {name} should have {ds.sha256}: the file is modified or "
                        f"truncated. Re-fetch it with `bayesmag data fetch {name} --force`.")
    return ds.loader(path)
