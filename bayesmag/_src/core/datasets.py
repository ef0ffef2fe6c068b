"""Named datasets: where to find them, how to fetch and verify them.

A dataset named ``NAME`` is looked up, in order, in ``$BAYESMAG_DATA_DIR/NAME/``,
then in the user cache ``$XDG_CACHE_HOME/bayesmag/NAME/`` (``~/.cache/bayesmag``).
``bayesmag data fetch NAME`` downloads it from its pinned URL into the cache and
checks its sha256.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import http.client
import os
import urllib.error
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
    """Download dataset ``name`` from its pinned URL into the cache and verify its sha256.

    The file is written to a hidden sibling (``.NAME.partial-PID``) and renamed into place only when it is complete
    and its sha256 is right, so a failed or interrupted download never leaves a file under the dataset's name (nor
    the sibling, nor a folder it created). A download that fails (no network, HTTP error, timeout, connection
    dropped) is a :class:`DataError` naming the URL, the path it would write and the two fixes.
    """
    ds = _check_name(name)
    target = (dest or cache_dir()) / ds.name / ds.filename
    if target.exists() and not force:
        if sha256_of(target) == ds.sha256:
            return target
    made = [q for q in (target.parent, *target.parent.parents) if not q.exists()]
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.partial-{os.getpid()}")
    done = False
    try:
        with open(tmp, "wb") as f:                  # a write error (read-only cache, full disk) names the file
            _download(ds, target, f)
        got = sha256_of(tmp)
        if got != ds.sha256:
            raise DataError(f"Downloaded {ds.url} has sha256 {got}, expected {ds.sha256}; the file was discarded "
                            f"and nothing was written. {_fetch_fix(ds, target)}")
        tmp.replace(target)
        done = True
    finally:
        if not done:
            tmp.unlink(missing_ok=True)
            for q in made:                          # innermost first: only the folders this call created, if empty
                with contextlib.suppress(OSError):
                    q.rmdir()
    return target


def _fetch_fix(ds: Dataset, target: Path) -> str:
    return (f"Download {ds.url} by hand to {target} (sha256 {ds.sha256}), or set BAYESMAG_DATA_DIR to a folder "
            f"holding {ds.name}/{ds.filename}.")


def _download(ds: Dataset, target: Path, f) -> None:
    """Copy ``ds.url`` into the open file ``f``; a failure to read it is a :class:`DataError` with the fixes."""
    try:
        r = urllib.request.urlopen(ds.url, timeout=60)
    except (OSError, ValueError) as e:             # URLError, HTTPError, timeouts are OSErrors
        raise DataError(_fetch_failed(ds, target, e)) from None
    with r:
        while True:
            try:
                chunk = r.read(1 << 20)
            except (OSError, ValueError, http.client.HTTPException) as e:    # the connection dropped midway
                raise DataError(_fetch_failed(ds, target, e)) from None
            if not chunk:
                return
            f.write(chunk)


def _fetch_failed(ds: Dataset, target: Path, e: BaseException) -> str:
    if isinstance(e, urllib.error.HTTPError):
        why = f"HTTP {e.code} {e.reason}"
    else:
        reason = getattr(e, "reason", None) or e
        why = " ".join(str(reason).split()) or type(reason).__name__
    return (f"Could not download dataset {ds.name!r} from {ds.url} ({why}; no network?); nothing was written to "
            f"{target}. {_fetch_fix(ds, target)}")


def load_dataset(name: str) -> CalibrationData:
    """Find and load dataset ``name`` (verifying its sha256)."""
    ds = _check_name(name)
    path = find_dataset(name)
    got = sha256_of(path)
    if got != ds.sha256:
        raise DataError(f"{path} has sha256 {got}, but {name} should have {ds.sha256}: the file is modified or "
                        f"truncated. Re-fetch it with `bayesmag data fetch {name} --force`.")
    return ds.loader(path)
