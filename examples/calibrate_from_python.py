"""Calibrate a simulated sensor from Python: fit, inspect the parameters, propagate uncertainty.

Run: python examples/calibrate_from_python.py
"""

import numpy as np

import bayesmag as bm

# A simulated Helmholtz-coil campaign of the paper's sensor (Table 2 parameters), 0.05 uT noise.
data = bm.simulate.simulate(4800, design="campaign", seed=0, noise_sd=0.05)
split = bm.make_split(data, kind="time_blocks", test_fraction=0.2, seed=0)
train, test = data.subset(split.train), data.subset(split.test)

t0 = float(train.temperature.mean())                    # reference temperature T0 (C): the training mean
model = bm.PhysicsModel.paper(t0=t0)
fit = bm.fit_physics(train, model, covariance_method="newey_west")
# The truth is written in T (T0 = 0), the fit in T - T0: S + Ks T = (S + Ks T0) + Ks (T - T0), likewise O.
truth = bm.simulate.TrueParams.paper()
truth_at_t0 = np.concatenate([truth.S + truth.Ks * t0, truth.Ks, (truth.O + truth.Ko * t0)[:, None],
                              truth.Ko[:, None]], axis=1)
print(f"axis y, T0 = {t0:.2f} C: parameter, fitted value +- u (2 significant figures), truth, (fit - truth) / u")
for name, v, s, true in zip(fit.param_names, fit.theta[1], fit.std[1], truth_at_t0[1]):
    print(f"  y.{name:5s} {v:+.6f} +- {s:.2g}   truth {true:+.6f}   {(v - true) / s:+.1f}")
print("condition number (y):", f"{fit.diagnostics[1]['condition_number']:.3g}")

uq = bm.physics_uncertainty(fit, bm.inputs_from_data(test), sigma_in=bm.estimate_input_noise(train),
                            n_params=500, n_qmc=1000, seed=0)
err = test.b_ref - uq.mean
print("test RMSE (uT):", np.sqrt((err**2).mean(0)).round(4))
print("mean aleatoric / epistemic sd (uT):", uq.aleatoric.mean(0).round(4), uq.epistemic.mean(0).round(5))
