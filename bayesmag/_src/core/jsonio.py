"""Strict JSON for every file bayesmag writes: NaN and inf become ``null``, never the non-standard tokens.

``json.dumps`` writes ``NaN``/``Infinity`` by default, which strict parsers (browsers, ``jq``, Go,
Rust's serde) refuse. :func:`dumps` replaces every non-finite float by ``None`` first and then
serialises with ``allow_nan=False``; NumPy scalars and arrays become plain numbers and lists.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["dumps", "write_json", "strict"]


def strict(obj: Any) -> Any:
    """``obj`` with NumPy values as Python ones and every non-finite float as ``None`` (recursively)."""
    if isinstance(obj, dict):
        return {k: strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return strict(obj.tolist())
    if isinstance(obj, np.generic):
        return strict(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps(obj: Any, *, indent: int | None = 2, **kwargs) -> str:
    """Strict JSON text of ``obj`` (non-finite numbers as ``null``).

    Example:
      >>> dumps({"a": float("nan"), "b": [1.0, float("inf")]}, indent=None)
      '{"a": null, "b": [1.0, null]}'
    """
    return json.dumps(strict(obj), indent=indent, allow_nan=False, **kwargs)


def write_json(path: str | Path, obj: Any, *, indent: int | None = 2) -> None:
    """Write ``obj`` to ``path`` as strict JSON (:func:`dumps`)."""
    Path(path).write_text(dumps(obj, indent=indent))
