r"""The sensor-frame joint model: catalogue terms as distortions of the sensor's own reading.

.. math::  B_\mathrm{ref} = (S + K_s T_c)\,(u - d(\theta; x)) + O + K_o T_c \;[+\, g(\theta; x) e_a]

``u`` is the measured reading (3 channels), ``d`` a distortion acting on one channel ``c``
(``d_c = F(x) \theta``, the catalogue term's features), fitted jointly over the three
outputs (24 + k parameters). A distortion of one channel reaches every calibrated output
through the calibration matrix; fitting it per output axis would report one effect three
times. Output-frame terms (``g`` on output ``a`` alone) and whole-sensor transforms (thermal
lag, timing offset) are the other two kinds of :class:`Extension`.

Two evaluations of the same model: :class:`Designs` builds the *linearised* stacked design
(the gain matrix ``S + Ks Tc`` held at the current fit; exact for output-frame terms) for the
fast cross-validated search, and :func:`refit` solves the exact bilinear model by one
Levenberg-Marquardt in JAX with Newey-West standard errors.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from bayesmag._src.core.catalogue import Setting
from bayesmag._src.core.fit import covariance, levenberg_marquardt
from bayesmag._src.core.physics import Inputs, ThermoAffine

__all__ = ["Extension", "JointModel", "Designs", "refit", "gain_matrix", "solve_sym", "lstsq"]

FRAMES = ("sensor", "output", "whole")


@dataclasses.dataclass(frozen=True)
class Extension:
    """A catalogue setting placed in the model: ``frame`` "sensor" (distorts channel ``slot``),
    "output" (adds to calibrated output ``slot``) or "whole" (transforms all inputs)."""

    setting: Setting
    frame: str
    slot: int | None = None

    @property
    def name(self) -> str:
        return self.setting.component.name

    @property
    def component(self):
        return self.setting.component

    @property
    def param_names(self) -> tuple:
        names = self.component.param_names()
        if self.frame == "whole":
            return names
        return tuple(names[i] for i in self.setting.cols) if self.setting.cols is not None else names

    @property
    def n_linear(self) -> int:
        return 0 if self.frame == "whole" else len(self.param_names)

    def features(self, inputs: Inputs):
        F = self.component.features(inputs)
        return F if self.setting.cols is None else F[:, list(self.setting.cols)]

    def with_cols(self, cols: tuple) -> "Extension":
        return dataclasses.replace(self, setting=dataclasses.replace(self.setting, cols=tuple(cols)))


@dataclasses.dataclass(frozen=True)
class JointModel:
    """Base thermo-affine model of the three outputs plus extensions; parameters flat:
    base (3 x k0, row-major), linear extension parameters in order, transform values in order."""

    base: ThermoAffine
    extensions: tuple = ()

    @property
    def k0(self) -> int:
        return len(self.base.param_names())

    @property
    def linear(self) -> tuple:
        return tuple(e for e in self.extensions if e.frame != "whole")

    @property
    def transforms(self) -> tuple:
        return tuple(e for e in self.extensions if e.frame == "whole")

    def slices(self) -> dict:
        """Extension -> indices of its parameters in the flat vector."""
        out, i = {}, 3 * self.k0
        for e in self.linear:
            out[e] = list(range(i, i + e.n_linear))
            i += e.n_linear
        for e in self.transforms:
            out[e] = [i]
            i += 1
        return out

    @property
    def n_params(self) -> int:
        return 3 * self.k0 + sum(e.n_linear for e in self.linear) + len(self.transforms)

    def transform(self, theta, inputs: Inputs) -> Inputs:
        sl = self.slices()
        for e in self.transforms:
            inputs = e.component(theta[jnp.array(sl[e])], inputs)
        return inputs

    def predict(self, theta, inputs: Inputs, drop: Extension | None = None):
        """(n, 3) calibrated field; ``drop``: evaluate without that linear extension's contribution."""
        sl = self.slices()
        inp = self.transform(theta, inputs)
        d = jnp.zeros_like(inp.b)
        add = jnp.zeros_like(inp.b)
        for e in self.linear:
            if e is drop:
                continue
            contrib = e.features(inp) @ theta[jnp.array(sl[e])]
            if e.frame == "sensor":
                d = d.at[:, e.slot].add(contrib)
            else:
                add = add.at[:, e.slot].add(contrib)
        X0 = self.base.features(inp._replace(b=inp.b - d))
        W = theta[: 3 * self.k0].reshape(3, self.k0)
        return X0 @ W.T + add


def gain_matrix(base: ThermoAffine, W: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(n, 3, 3) reading-to-output gain S + Ks Tc of base coefficients ``W`` (3, k0)."""
    S = W[:, 0:3]
    if not base.temperature:
        return np.broadcast_to(S, (t.size, 3, 3))
    return S[None] + W[None, :, 3:6] * (t - base.t0)[:, None, None]


def solve_sym(G: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Solution of G b = c for a symmetric PSD, column-scaled G, with a ridge of 1e-10 of its mean
    eigenvalue: for c in the range of G (c = X'y) the null directions stay ~0 (near minimum norm).
    An LU solve, not an eigendecomposition: ~100x faster on these small systems."""
    lam = 1e-10 * max(float(np.trace(G)) / max(G.shape[0], 1), 1e-300)
    return np.linalg.solve(G + lam * np.eye(G.shape[0]), c)


def lstsq(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares by normal equations on column-scaled X (rank-deficiency safe)."""
    s = np.sqrt((X * X).sum(0))
    s = np.where(s > 0, s, 1.0)
    Xs = X / s
    return solve_sym(Xs.T @ Xs, Xs.T @ y) / s


_transform_jit = jax.jit(lambda comp, p, inp: comp(p, inp), static_argnums=0)


class Designs:
    """Stacked, weighted, linearised designs (3n rows, output-major) with caches.

    ``w`` (3,) weights each output by 1 / its noise floor; ``gain`` (n, 3, 3) is ``S + Ks Tc``
    at the current fit, so a sensor-frame column for channel c is ``-gain[:, a, c] F`` on output a."""

    def __init__(self, base: ThermoAffine, inputs: Inputs, y: np.ndarray, w: np.ndarray, gain: np.ndarray):
        self.base, self.inputs, self.w, self.gain = base, inputs, np.asarray(w), gain
        self.n = y.shape[0]
        self.y = (np.asarray(y) * self.w).T.reshape(-1)
        self._inp: dict = {}
        self._feat: dict = {}

    def transformed(self, transforms: tuple) -> Inputs:
        key = tuple(e.setting for e in transforms)
        if key not in self._inp:
            inp = self.inputs
            for e in transforms:
                canon = e.component.canonical() if hasattr(e.component, "canonical") else type(e.component)()
                inp = _transform_jit(canon, jnp.array([e.setting.nl]), inp)
            self._inp[key] = inp
        return self._inp[key]

    def _features(self, comp, transforms) -> np.ndarray:
        key = (comp, tuple(e.setting for e in transforms))
        if key not in self._feat:
            inp = self.transformed(transforms)
            # eager: features are a few elementwise ops, and a jit keyed on the component would
            # compile anew for every grid point and every recording (t0, thresholds, time_ref)
            f = comp.features(inp)
            self._feat[key] = np.asarray(f)
        return self._feat[key]

    def columns(self, e: Extension, transforms: tuple) -> np.ndarray:
        """(3n, k) stacked weighted columns of a linear extension."""
        F = self._features(e.component, transforms)
        if e.setting.cols is not None:
            F = F[:, list(e.setting.cols)]
        out = np.zeros((3, self.n, F.shape[1]))
        if e.frame == "sensor":
            for a in range(3):
                out[a] = -self.gain[:, a, e.slot][:, None] * F * self.w[a]
        else:
            out[e.slot] = F * self.w[e.slot]
        return out.reshape(3 * self.n, -1)

    def matrix(self, exts: tuple) -> np.ndarray:
        transforms = tuple(e for e in exts if e.frame == "whole")
        X0 = self._features(self.base, transforms)
        k0 = X0.shape[1]
        B = np.zeros((3, self.n, 3 * k0))
        for a in range(3):
            B[a, :, a * k0:(a + 1) * k0] = X0 * self.w[a]
        cols = [B.reshape(3 * self.n, -1)] + [self.columns(e, transforms) for e in exts if e.frame != "whole"]
        return np.concatenate(cols, axis=1)


_lm_jit = jax.jit(lambda model, th0, inputs, y, w: levenberg_marquardt(
    lambda th: ((y - model.predict(th, inputs)) * w).T.reshape(-1), th0), static_argnums=0)
_jac_jit = jax.jit(lambda model, th, inputs, w: jax.jacfwd(
    lambda t: (model.predict(t, inputs) * w).T.reshape(-1))(th), static_argnums=0)


_tvjp_jit = jax.jit(lambda model, th, inputs, w, v: jax.vjp(
    lambda T: (model.predict(th, inputs._replace(t=T)) * w).T.reshape(-1), inputs.t)[1](v)[0], static_argnums=0)


def temperature_log_sd(t: np.ndarray, run: np.ndarray) -> float:
    r"""Sd of white noise in a temperature log from its second differences within runs,
    :math:`1.4826\,\mathrm{MAD}(\Delta^2 T) / \sqrt 6` (ramps and holds cancel; 0 for a noiseless log)."""
    t, run = np.asarray(t, dtype=float), np.asarray(run)
    d2 = t[2:] - 2 * t[1:-1] + t[:-2]
    ok = (run[2:] == run[1:-1]) & (run[1:-1] == run[:-2])
    return float(1.4826 * np.median(np.abs(d2[ok])) / np.sqrt(6)) if ok.any() else 0.0


def log_noise_se(model: JointModel, theta: np.ndarray, inputs: Inputs, w: np.ndarray, index: int,
                 sd_t: float) -> float:
    r"""Standard error that white noise of sd ``sd_t`` in the logged temperature adds to
    parameter ``index`` of the weighted least-squares fit (errors in the variable that the
    model's transforms act on, e.g. a thermal lag's input and each run's starting state).

    Linearised: :math:`\partial\hat\theta/\partial T = -(J^\top J)^{-1} J^\top \partial r/\partial T`,
    so :math:`\mathrm{se} = \mathrm{sd}_T\,\lVert D^\top J (J^\top J)^{-1} e_i \rVert` with
    :math:`D = \partial (w\,\hat y)/\partial T` applied by one vector-Jacobian product."""
    if sd_t <= 0:
        return 0.0
    th, wj = jnp.asarray(theta), jnp.asarray(w)
    J = np.asarray(_jac_jit(model, th, inputs, wj))
    e = np.zeros(J.shape[1])
    e[index] = 1.0
    v = J @ np.linalg.lstsq(J.T @ J, e, rcond=None)[0]
    a = np.asarray(_tvjp_jit(model, th, inputs, wj, jnp.asarray(v)))
    return float(sd_t * np.linalg.norm(a))


def refit(model: JointModel, theta0: np.ndarray, inputs: Inputs, y: np.ndarray, w: np.ndarray,
          run: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """(theta, cov, resid (n, 3), converged) of the exact joint model by one LM over all
    parameters (weighted by ``w``), Newey-West covariance (lags within each run and output)."""
    yj, wj = jnp.asarray(y), jnp.asarray(w)
    sol = _lm_jit(model, jnp.asarray(theta0), inputs, yj, wj)
    theta = np.asarray(sol.theta)
    ok = bool(np.all(np.isfinite(theta))) and int(sol.result) != 2
    if not ok:
        theta = np.asarray(theta0)
    J = np.asarray(_jac_jit(model, jnp.asarray(theta), inputs, wj))
    resid = np.asarray(y) - np.asarray(model.predict(jnp.asarray(theta), inputs))
    r = (resid * np.asarray(w)).T.reshape(-1)
    run3 = np.concatenate([np.asarray(run) + a * (int(np.max(run)) + 1) for a in range(3)])
    cov, _ = covariance(J, r, method="newey_west", run=run3)
    return theta, cov, resid, ok and int(sol.result) == 0
