"""Issue 24: is the second posterior mode of simulated draw 3 (z axis) a property of the shifts or of the noise?

Run:  python benchmarks/scan_modes_noise_check.py

Draw 3's training campaign (the benchmark's seeds) without any session shift (noise sd 0.02, the default), and
with the `gauss` shifts at a tenth of the noise (0.002): the modes BFGS finds from the two starts of
``_modes`` on the z axis (between-session sds in uT at an RMS input, noise sd, AR(1) rho, log posterior).
"""
import sys, numpy as np, jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_transfer import _session, _shifted_params
import bayesmag
from bayesmag._src.pipeline.sessions import hierarchical as H
from bayesmag._src.core.simulate import TrueParams
for label, gen, noise in (("no shift", lambda g: TrueParams.paper(), 0.02), ("gauss, noise 0.002", _shifted_params, 0.002)):
    train = _session(3, 30, rows=100, session_params=gen, noise_sd=noise)
    fit = bayesmag.fit_physics(train, bayesmag.PhysicsModel.paper(t0=float(np.mean(train.temperature))))
    st = H.run_stats(train, fit, H.DEFAULT_EFFECTS)
    a = 2
    args = (jnp.asarray(st.m0[a]), jnp.asarray(st.m1[a]), jnp.asarray(st.m2[a]), jnp.asarray(st.first[a]), jnp.asarray(st.n), jnp.asarray(st.effects), H.TAU_PRIOR_SCALE, H.SIGMA_PRIOR_SCALE, H.REML)
    def fg(h):
        v, g = H._neg_lp_and_grad(jnp.asarray(h), *args); v = float(v)
        return (v, np.asarray(g)) if np.isfinite(v) else (1e300, np.zeros(len(h)))
    for h, _ in H._modes(fg, H._init_h(st, a, 0.5), 5, 0.5, search=True):
        print(label, "tau", np.exp(h[:5]).round(3), "sigma", np.exp(h[5]).round(4), "rho", np.tanh(h[6]).round(2), "lp", round(-fg(h)[0], 1))
