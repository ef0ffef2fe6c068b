"""All-or-nothing output folders: write into a temporary sibling, rename into place on success."""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path

__all__ = ["staging_dir"]


@contextlib.contextmanager
def staging_dir(out: str | Path):
    """Yield a temporary folder; on success it replaces ``out`` atomically, on failure it is removed.

    A failed run never leaves a half-written folder that looks complete, and an existing
    complete ``out`` survives a failed re-run untouched.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if out.exists():
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        out.rename(old)
    tmp.rename(out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
