"""Monte Carlo check of a thermal lag's se from the temperature log's noise (``frame.log_noise_se``).

    python benchmarks/mc_lag_log_noise.py [--seed 18] [--draws 20]

Independent thermal_lag campaign ``seed`` with a noiseless log (``log_noise=0``); each draw adds
fresh white noise of 0.02 C to the log (everything else fixed), fits the thermo-affine model with
a first-order lag by the joint Levenberg-Marquardt refit, and records log tau. Prints the sd of
log tau over the draws (the log noise's true share), the mean propagated se
(``log_noise_se`` with the log's sd read off its second differences), the mean Newey-West se
of the residuals, and the mean bias in log tau.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import math
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--seed", type=int, default=18)
    p.add_argument("--draws", type=int, default=20)
    a = p.parse_args(argv)
    import bayesmag
    import independent_campaigns as IC
    from bayesmag._src.core import catalogue as C
    from bayesmag._src.core.physics import ThermoAffine, inputs_from_data, resolve_t0
    from bayesmag._src.pipeline.discover.frame import Extension, JointModel, log_noise_se, lstsq, refit, \
        temperature_log_sd

    d0, planted = IC.campaign("thermal_lag", a.seed, n=5000, log_noise=0.0)
    log_tau = math.log(planted.params["tau"])
    rng = np.random.default_rng(1)
    est, se_res, se_log = [], [], []
    for _ in range(a.draws):
        T = np.asarray(d0.temperature) + 0.02 * rng.standard_normal(d0.n)
        d = bayesmag.CalibrationData(d0.b_meas, T, d0.b_ref, d0.time, d0.run, "mc")
        base = ThermoAffine(t0=resolve_t0("mean", T), temperature=True)
        inputs, y, run = inputs_from_data(d), np.asarray(d.b_ref), np.asarray(d.run)
        X0 = np.asarray(base.features(inputs))
        W0 = np.stack([lstsq(X0, y[:, k]) for k in range(3)])
        w = 1.0 / np.std(y - X0 @ W0.T, axis=0)
        lag = Extension(C.Setting(C.ThermalLag(tau0=math.exp(log_tau)), nl=log_tau), "whole")
        model = JointModel(base, (lag,))
        k0 = X0.shape[1]
        Xl = np.asarray(base.features(model.transform(jnp.concatenate([jnp.zeros(3 * k0), jnp.array([log_tau])]),
                                                      inputs)))
        th0 = np.concatenate([np.stack([lstsq(Xl, y[:, k]) for k in range(3)]).reshape(-1), [log_tau]])
        theta, cov, _, _ = refit(model, th0, inputs, y, w, run)
        i = model.slices()[lag][0]
        est.append(theta[i])
        se_res.append(math.sqrt(cov[i, i]))
        se_log.append(log_noise_se(model, theta, inputs, w, i, temperature_log_sd(T, run)))
    est = np.array(est)
    print(json.dumps({"seed": a.seed, "draws": a.draws, "sd_log_tau_over_draws": float(est.std(ddof=1)),
                      "mean_log_noise_se": float(np.mean(se_log)), "mean_newey_west_se": float(np.mean(se_res)),
                      "mean_bias_log_tau": float(est.mean() - log_tau)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
