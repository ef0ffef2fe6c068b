"""bayesmag: calibrate 3-axis magnetometers with trustworthy uncertainty."""

import jax as _jax

# The physics fit and its uncertainty need float64; the residual network casts to float32 itself.
_jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"
