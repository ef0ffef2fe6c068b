"""Shared test data: a thermo-affine sensor with known parameters (close to the paper's Table 2)."""

import numpy as np

from bayesmag import CalibrationData, PhysicsModel, PhysicsUQ, inputs_from_data
from bayesmag._src.network import MCPrediction

TRUE_THETA = np.array([[1.02, -0.16, -0.21, 0.003, 0.004, 0.008, -1.2, 0.036],
                       [-0.16, 2.37, 0.04, 0.0027, -0.05, -0.0028, -0.07, -0.0009],
                       [-0.086, 0.096, 1.21, 0.0046, -0.0011, -0.004, 4.32, -0.16]])


def affine_data(n: int, seed: int, noise: float):
    """(data, design matrix): fields uniform +-50 uT, T uniform 0-40 C, reference = model + Gaussian noise."""
    r = np.random.default_rng(seed)
    b = r.uniform(-50, 50, (n, 3))
    t = r.uniform(0, 40, n)
    X = np.asarray(PhysicsModel.paper().features(inputs_from_data(CalibrationData(b, t, None))))
    y = X @ TRUE_THETA.T + noise * r.standard_normal((n, 3))
    return CalibrationData(b, t, y, time=np.arange(n) * 0.25), X


def uq_parts(seed=0, n=50):
    """Random physics UQ and MC-network outputs for ``n`` rows (fusion and predictor tests)."""
    rng = np.random.default_rng(seed)
    phys = PhysicsUQ(mean=rng.normal(size=(n, 3)), aleatoric=rng.uniform(0.01, 0.02, (n, 3)),
                     epistemic=rng.uniform(0.001, 0.003, (n, 3)), epistemic_mc=np.zeros((n, 3)),
                     epistemic_jac=np.zeros((n, 3)))
    nn = MCPrediction(mean=rng.normal(0, 0.02, (n, 3)), aleatoric=rng.uniform(0.01, 0.03, (n, 3)),
                      epistemic=rng.uniform(0.001, 0.005, (n, 3)), shape={"df": rng.uniform(3, 9, (n, 3))})
    return phys, nn
