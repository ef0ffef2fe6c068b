"""Float64 for the physics fit: the warning raised when an entry point that needs it runs with JAX in float32."""

from __future__ import annotations

import warnings

import jax

__all__ = ["Float64Warning", "warn_if_float32"]


class Float64Warning(UserWarning):
    """A bayesmag computation that needs float64 ran with JAX in float32."""


def warn_if_float32(name: str) -> None:
    """Warn (:class:`Float64Warning`, at the user's line) when JAX computes in float32 now: ``name`` ran there.

    Example:
      >>> warn_if_float32("fit_physics")   # silent under float64 (``import bayesmag``'s default)
    """
    if not jax.config.jax_enable_x64:
        from bayesmag._src.core.data import user_stacklevel
        warnings.warn(f"bayesmag.{name} runs with JAX in float32 (BAYESMAG_ENABLE_X64=0 and no "
                      f"`with bayesmag.enable_x64():`); its results are float32 approximations.",
                      Float64Warning, stacklevel=user_stacklevel())
