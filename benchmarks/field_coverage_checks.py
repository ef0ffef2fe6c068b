"""Is the Laplace posterior of a field fit as wide as the estimator's spread? (docs/field.md, Peers: the checks
behind the invariant-coverage discussion.)

Keeps one campaign's attitudes, temperatures and truth (``bench_field.run_one``'s split: 4 held-out blocks of 5 %)
and refits the constant 50 uT model to ``--draws`` fresh draws of the reading noise; prints per identified
invariant the spread / mean Laplace sd and the mean z, the coverage of the 95 % intervals and the mean chi^2 of the
identified invariants (expected: their number). ``--gauge`` replaces the truth's thermal matrix by its
gauge-representable part, R0 triu(R0^T Ks) (M(T) = R0 U(T): no temperature-dependent rotation), with the same noise
draws. ``--hessian`` also compares the full Hessian's sds with the Gauss-Newton ones on the campaign's own draw.

Examples (the docs' numbers)::

  python benchmarks/field_coverage_checks.py few_orientations 51 20 20 --draws 150
  python benchmarks/field_coverage_checks.py few_orientations 17 15 40 --draws 100 --noise 0.005
  python benchmarks/field_coverage_checks.py dance 7 15 40 --draws 60 --rng-offset 2000 [--gauge]
"""

from __future__ import annotations

import argparse

import numpy as np

from bayesmag._src.core.field import (Constant, _invariants_jac, _static, field_target, fit_field, gauge_form,
                                      invariants)
from bayesmag.simulate import simulate_field


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("kind")
    ap.add_argument("seed", type=int)
    ap.add_argument("t_start", type=float)
    ap.add_argument("t_end", type=float)
    ap.add_argument("--draws", type=int, default=100)
    ap.add_argument("--noise", type=float, default=0.05, help="reading noise sd of the refits, uT")
    ap.add_argument("--rng-offset", type=int, default=1000, help="noise draws from default_rng(offset + seed)")
    ap.add_argument("--gauge", action="store_true")
    ap.add_argument("--hessian", action="store_true")
    a = ap.parse_args()
    kw = {} if a.kind == "two_temperature" else {"temperature": (a.t_start, a.t_end)}
    c = simulate_field(a.kind, n=2000, seed=a.seed, n_orient=12, **kw)
    d, tr = c.data, c.truth
    test = np.zeros(d.n, bool)
    for b in range(4):
        s = int((0.1 + 0.22 * b) * d.n)
        test[s:s + d.n // 20] = True
    train = ~test
    t, B = d.temperature[train], tr.b_body[train]
    S, Ks, O, Ko, t0 = tr.S, tr.Ks, tr.O, tr.Ko, tr.t0
    if a.gauge:
        R0, U0 = gauge_form(S)
        S, Ks = R0 @ U0, R0 @ np.triu(R0.T @ Ks)
    M, o = S + Ks * (t - t0)[:, None, None], O + Ko * (t - t0)[:, None]
    clean = np.linalg.solve(M, (B - o)[..., None])[..., 0]
    y = field_target(Constant(50.0), n=int(train.sum()))
    if a.hessian:
        import jax
        import jax.numpy as jnp
        f = fit_field(d.b_meas[train], t, y, Constant(50.0))
        u, tt, yy = jnp.asarray(d.b_meas[train]), jnp.asarray(t), jnp.asarray(y)

        def nlp(th):
            r = f.model.residual(th, u, tt, yy)
            return 0.5 * jnp.sum(r * r) / (f.s2 * f.inflation) + 0.5 * jnp.sum(((th - f.prior_mean) / f.prior_sd) ** 2)
        th = jnp.asarray(f.theta)
        g, H = np.asarray(jax.grad(nlp)(th)), np.asarray(jax.hessian(nlp)(th))
        cH = np.linalg.inv(H)
        _, G = (np.asarray(x) for x in _invariants_jac(_static(f.model), th))
        ok = f.invariants()["identified"]
        print("Newton step at the estimate, max over parameters (posterior sd):", float(np.max(np.abs(f.cov @ g) / f.std)))
        print("invariant sd, full Hessian / Gauss-Newton:",
              (np.sqrt(np.diag(G @ cH @ G.T)) / np.sqrt(np.diag(G @ f.cov @ G.T)))[ok].round(3))
        print("parameter posterior sd / prior sd:", (f.std / f.prior_sd).round(3))
    rng = np.random.default_rng(a.rng_offset + a.seed)
    V, SD, Z, chi2, ok0 = [], [], [], [], None
    for _ in range(a.draws):
        f = fit_field(clean + rng.normal(0, a.noise, clean.shape), t, y, Constant(50.0))
        inv = f.invariants()
        ok = inv["identified"]
        ok0 = ok if ok0 is None else ok0
        if not np.array_equal(ok, ok0) or not f.converged:
            print("skipped a draw: identified set or convergence differs")
            continue
        dt = f.model.t0 - t0
        dv = (inv["value"] - np.asarray(invariants(S + Ks * dt, Ks, O + Ko * dt, Ko)))[ok]
        V.append(inv["value"][ok]); SD.append(inv["sd"][ok]); Z.append(dv / inv["sd"][ok])
        chi2.append(float(dv @ np.linalg.solve(inv["cov"][np.ix_(ok, ok)], dv)))
    V, SD, Z = np.array(V), np.array(SD), np.array(Z)
    print(f"{a.kind} seed {a.seed} {'gauge-representable truth' if a.gauge else 'truth as simulated'}: "
          f"{len(V)} draws, {int(ok0.sum())} identified invariants")
    print("spread / mean Laplace sd:", (V.std(0) / SD.mean(0)).round(3))
    print("mean z:", Z.mean(0).round(2))
    print(f"coverage {np.mean(np.abs(Z) <= 1.96):.3f}, mean chi^2 {np.mean(chi2):.2f} (dof {int(ok0.sum())})")


if __name__ == "__main__":
    main()
