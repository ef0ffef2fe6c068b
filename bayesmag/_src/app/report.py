r"""A calibration certificate a metrologist can read: ``report.md`` (and ``report.html``) from a run folder.

Besides accuracy and coverage it holds, in the manner of the GUM (JCGM 100:2008): the
identity of the calibration (ID, date, bayesmag version, data file sha256, device under test
and reference instrument from ``[certificate]``); the model equation with its reference
temperature :math:`T_0` and S, Ks, O, Ko as matrices/vectors with standard uncertainties;
units on every parameter; every uncertainty rounded to two significant figures with its value
rounded to match (:func:`gum_round`); fit statistics (n, p, chi-square, AIC/BIC, solver
iterations); and an uncertainty budget with Type A / Type B labels, degrees of freedom per
component, the effective degrees of freedom (Welch-Satterthwaite, GUM G.4.1), the coverage
factor :math:`k = t_{(1+p)/2}(\nu_{\mathrm{eff}})` and the expanded uncertainty :math:`U = k\,u_c`
per axis, for the same session and for a new session (with the between-session transfer term).

The certificate is a sequence of sections (:data:`SECTIONS`): each a function of a
:class:`ReportContext` returning Markdown lines; a new section is one more function in the
tuple (``render_report(..., sections=SECTIONS + (my_section,))``).
"""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import html
import json
import math
import re
from pathlib import Path

import numpy as np

__all__ = ["write_report", "render_report", "render_html", "welch_satterthwaite", "coverage_factor",
           "parameter_unit", "uncertainty_budget", "fit_statistics", "gum_round", "gum_format",
           "expanded_uncertainties", "hybrid_new_session", "transfer_missing", "condition_uncertainties", "certificate_record", "ReportContext", "SECTIONS"]

AXES = ("x", "y", "z")

_UNITS = {"S": "1", "Ks": "1/C", "O": "uT", "Ko": "uT/C", "Ko2": "uT/C^2", "Ko3": "uT/C^3", "Ks2": "1/C^2",
          "q": "1/uT", "c": "1/uT^2", "h": "uT", "drift_rate": "uT/s", "run_step": "uT", "log_tau": "ln(s)",
          "delta": "s"}


def parameter_unit(name: str) -> str:
    """Unit of a physics parameter from its name (``S_x`` -> 1, ``Ks_y`` -> 1/C, ``q_xx_T`` -> 1/(uT C), ...)."""
    thermal = name.endswith("_T")
    base = name[:-2] if thermal else name
    unit = _UNITS.get(base, _UNITS.get(base.split("_")[0], "?"))
    if thermal:
        unit = f"({unit})/C" if unit != "1" else "1/C"
    return unit


def welch_satterthwaite(u, nu) -> float:
    """Effective degrees of freedom of ``u_c = sqrt(sum u_i^2)`` (GUM eq. G.2b); ``inf`` terms add nothing."""
    u = np.asarray(u, dtype=np.float64)
    nu = np.asarray(nu, dtype=np.float64)
    uc4 = float(np.sum(u**2)) ** 2
    finite = np.isfinite(nu) & (u > 0)
    den = float(np.sum(u[finite] ** 4 / nu[finite]))
    return math.inf if den == 0 else uc4 / den


def coverage_factor(nu_eff: float, level: float) -> float:
    """``k`` such that ``u_c k`` covers ``level`` (Student t with ``nu_eff`` degrees of freedom; normal if infinite)."""
    from scipy import stats
    q = 0.5 * (1.0 + level)
    return float(stats.norm.ppf(q) if not math.isfinite(nu_eff) else stats.t.ppf(q, nu_eff))


def _digits(x: float, d: int, fixed: bool) -> str:
    """``x`` written with its last digit at the decimal place ``10**d`` (fixed, or scientific)."""
    if fixed:
        return f"{x:.{max(0, -d)}f}"
    e = int(math.floor(math.log10(abs(x)))) if x != 0 else d
    return f"{x:.{max(0, e - d)}e}"


def gum_round(value: float, u: float, sig: int = 2) -> tuple[str, str]:
    """``(value, u)`` as strings: ``u`` to ``sig`` significant figures, ``value`` rounded to the same
    decimal place (GUM 7.2.6). Non-finite or zero ``u``: value to 6 significant figures.

    Example:
        >>> gum_round(1.00213456, 4.90148e-05)
        ('1.002135', '0.000049')
        >>> gum_round(-3.2e-05, 4.87e-07)
        ('-3.200e-05', '4.9e-07')
    """
    value, u = float(value), abs(float(u))
    if not math.isfinite(value):
        return str(value), str(u)
    if not math.isfinite(u) or u == 0:
        return f"{value:.6g}", ("0" if u == 0 else str(u))
    d = int(math.floor(math.log10(u))) - (sig - 1)
    ur = round(u, -d)
    if ur >= 10 ** (d + sig):                   # 9.96e-05 -> 1.0e-04: one place to the left
        d += 1
        ur = round(u, -d)
    vr = round(value, -d)
    if vr == 0:
        vr = 0.0                                 # no "-0.000"
    fixed = -7 <= d and max(abs(vr), ur) < 1e6      # one notation for the pair (fixed down to 1e-7: a table of
                                                    # thermal gains reads 0.0032475 beside 0.007999, not 3.2475e-03)
    return _digits(vr, d, fixed), _digits(ur, d, fixed)


def gum_format(value: float, u: float, unit: str = "") -> str:
    """``value ± u`` rounded by :func:`gum_round`, e.g. ``1.002135 ± 0.000049``; a unit is appended."""
    v, e = gum_round(value, u)
    return f"{v} ± {e}" + (f" {unit}" if unit and unit != "1" else "")


def _u2(x: float) -> str:
    """A standard or expanded uncertainty to two significant figures."""
    return gum_round(x, x)[1] if x and math.isfinite(x) else ("0" if x == 0 else str(x))


def _param_table(ax: str, p: dict, corr_threshold: float) -> list[str]:
    vals, sds, names = p["values"], p["std"], list(p["values"])
    lines = [f"### Axis {ax}", "", "| parameter | value | std. uncertainty u | unit | relative u |",
             "|---|---|---|---|---|"]
    for n in names:
        v, s = vals[n], sds[n]
        rel = f"{abs(s / v) * 100:.2g}%" if v != 0 else "-"
        vs, us = gum_round(v, s)
        lines.append(f"| {n} | {vs} | {us} | {parameter_unit(n)} | {rel} |")
    corr = np.asarray(p["correlation"])
    pairs = [(names[i], names[j], corr[i, j]) for i in range(len(names)) for j in range(i + 1, len(names))
             if abs(corr[i, j]) > corr_threshold]
    lines.append("")
    if pairs:
        lines.append(f"Correlations with |rho| > {corr_threshold}: " +
                     ", ".join(f"{a}-{b} {c:+.3f}" for a, b, c in sorted(pairs, key=lambda t: -abs(t[2]))))
    cond = p["condition_number"]
    advice = ("well conditioned" if cond < 1e3 else
              "moderately ill-conditioned: some parameters trade off against each other" if cond < 1e6 else
              "ill-conditioned: individual parameters are poorly determined even though the predictions are fine; "
              f"{T0_ADVICE}")
    lines += ["", f"Condition number (correlation-scaled): {cond:.3g} - {advice}.",
              f"Residual sd {p['residual_std']:.4g} uT; residual lag-1 autocorrelation "
              f"{p['lag1_autocorrelation']:.2f}" + (" (the white covariance understates the standard errors; use "
                                                    "[physics] covariance = \"newey_west\")"
                                                    if p["lag1_autocorrelation"] > 0.3 and
                                                    p["covariance_info"].get("method") == "white" else "") + ".", ""]
    return lines


def white_covariance_note(params: dict) -> str | None:
    """The certificate's statement when the parameter uncertainties come from the white covariance while the
    residuals are autocorrelated: the range of Newey-West (autocorrelation-consistent) over white standard
    uncertainties per axis (``covariance_info.newey_west_sd_ratio``, computed with every white fit); None when the
    covariance is not white, the ratios are not recorded (older runs) or all are below 1.5."""
    axes = params.get("axes") or {}
    ratios = {a: (axes[a].get("covariance_info") or {}).get("newey_west_sd_ratio") for a in AXES if a in axes}
    if params.get("covariance_method") != "white" or not all(ratios.values()) or max(r[1] for r in ratios.values()) < 1.5:
        return None
    rho = " / ".join(f"{axes[a]['lag1_autocorrelation']:.2f}" for a in AXES)
    return ("The parameters' standard uncertainties u below come from the white covariance, which takes the residuals "
            f"as independent; their lag-1 autocorrelation is {rho} (x / y / z), and the autocorrelation-consistent "
            "(Newey-West) covariance of the same fit gives u " + "; ".join(
                f"{r[0]:.1f}-{r[1]:.1f}x as large on {a}" for a, r in ratios.items())
            + ". Quote those (`[physics] covariance = \"newey_west\"` puts them in this certificate and in the "
            "epistemic part of every interval).")


#: The one reference-temperature recommendation (also in the fit's design note, core/fit.py).
T0_ADVICE = 'set [physics] t0 = "mean" (the training mean temperature), which removes the S-Ks and O-Ko correlations'


def _per_axis_sd(reference_sd) -> dict:
    r = reference_sd if isinstance(reference_sd, (list, tuple)) else [reference_sd] * 3
    return {a: float(v) for a, v in zip(AXES, r)}


#: Efficiency of the MAD as an estimate of a normal sd (Rousseeuw and Croux 1993, JASA 88, 1273: 37 %).
MAD_EFFICIENCY = 0.37
#: Second differences of white noise overlap (lag-1 correlation -2/3, lag-2 1/6), so a variance from m of them
#: counts as m / (1 + 2 (4/9 + 1/36)) = 0.514 m independent values.
SECOND_DIFFERENCE_EFFICIENCY = 1.0 / (1.0 + 2.0 * (4.0 / 9.0 + 1.0 / 36.0))


def effective_dof(params: dict, n: int, p: int) -> dict:
    """Per axis, the degrees of freedom of the residual variance and the parameter covariance: the training rows'
    effective number under AR(1) residuals, ``n (1 - rho1) / (1 + rho1)`` (rho1 the residual lag-1
    autocorrelation in params.json, >= 0), less the ``p`` parameters (at least 1). Independent residuals give
    ``n - p``; Belsten's (rho1 0.76-0.87) about 200-400, not 3032."""
    out = {}
    for a in AXES:
        rho = float((params.get("axes") or {}).get(a, {}).get("lag1_autocorrelation") or 0.0)
        rho = min(max(rho, 0.0), 0.99)
        out[a] = max(n * (1.0 - rho) / (1.0 + rho) - p, 1.0)
    return out


def _components(m: dict, params: dict, reference_sd) -> list[tuple]:
    """(label, per-axis u, type, per-axis dof, evaluation) of the within-session budget. The parts are root mean
    squares over the budget's rows (``rms_*``; runs before that key: the means), so ``u_c^2`` is the rows' mean
    variance; dof: :func:`effective_dof` for the residual and the parameters, and for the noise sd estimated from
    the rows' second differences by a MAD about ``0.37 x 0.514 x (n - 2 R)`` (R the training runs)."""
    u = m["uq"]
    n = int(params.get("n_rows") or m["split"]["n_train"])
    p = len(params["model"]["param_names"])
    auto = str(u.get("sigma_in_source", "")).startswith("auto")
    ref = _per_axis_sd(reference_sd)
    d = m.get("data") or {}
    n_runs = max(len(d.get("train_runs") or d.get("runs") or [0]), 1)
    nu_res = effective_dof(params, n, p)
    nu_noise = max(MAD_EFFICIENCY * SECOND_DIFFERENCE_EFFICIENCY * (n - 2 * n_runs), 1.0) if auto else math.inf
    return [
        ("aleatoric (input noise through the model)", u.get("rms_aleatoric", u["mean_aleatoric"]), "A" if auto else "B",
         {a: nu_noise for a in AXES}, "noise sd estimated from the training rows (MAD of second differences)" if auto
         else "noise sd from the config"),
        ("residual (scatter the model does not explain)", u.get("residual_term", {a: 0.0 for a in AXES}), "A", nu_res,
         "residual variance of the fit (dof: the autocorrelated rows' effective number)"),
        ("epistemic (parameter uncertainty)", u.get("rms_epistemic", u["mean_epistemic"]), "A", nu_res,
         "parameter covariance of the fit"),
        ("reference magnetometer (`[uq] reference_sd`)", ref, "B", {a: math.inf for a in AXES},
         "stated by the user (certificate of the reference)" if any(ref.values()) else "not given (0)"),
    ]


def _transfer_sd(m: dict) -> dict:
    tr = m.get("transfer") or {}
    sd = tr.get("sd") if tr.get("method") not in (None, "off") else None
    return {a: float(sd[a]) if sd else 0.0 for a in AXES}


def transfer_missing(m: dict) -> str | None:
    """Why a run has no between-session (transfer) sd, so no U for a new session can be stated; None when it has
    one. ``[uq] transfer = "off"``, or one training run (the fallback's run-to-run change is then zero)."""
    tr = m.get("transfer") or {}
    method = tr.get("method")
    if method in (None, "off"):
        return '`[uq] transfer = "off"`' if method == "off" else "the run holds no transfer estimate"
    if method == "largest_offset_change" and not any(float(v) > 0 for v in (tr.get("sd") or {}).values()):
        return "one training run: no change between sessions can be seen"
    return None


def _checked_note(tr: dict) -> str:
    """The sentence naming the axes where the hierarchical model failed its check against leave-one-run-out and
    its sd was replaced by loro's (``[uq] transfer_check = "loro"``); "" where none."""
    chk = ((tr.get("per_run") or {}).get("model") or {}).get("check") or {}
    failed = chk.get("failed_axes") or []
    if not failed or chk.get("action") != "loro":
        return ""
    return (f"; on {', '.join(failed)} the model's spread was more than twice leave-one-run-out's (its check against "
            f"the held-out runs failed) and leave-one-run-out's constant sd is used instead (`[uq] transfer_check`)")


def hybrid_new_session(m: dict) -> dict | None:
    """The hybrid predictor's budget: its within-session parts over the test rows, interval scale and the transfer
    sd it adds to a new session (``metrics["network"]["training"][primary]["budget"]``; runs before that key have it
    only with ``[uq] transfer_networks``, under ``transfer_network.new_session``), or None (no network)."""
    net = m.get("network") or {}
    training = net.get("training") or {}
    tr = training.get(net.get("primary")) or next(iter(training.values()), None)
    if not isinstance(tr, dict):
        return None
    nt = tr.get("transfer_network")
    block = tr.get("budget") or (nt.get("new_session") if isinstance(nt, dict) else None)
    return block if isinstance(block, dict) and block.get("parts") else None


def _hybrid_components(m: dict, params: dict, reference_sd, block: dict) -> list[tuple]:
    """(label, per-axis u, dof) of the hybrid's within-session parts for a new session: every part of its
    variance times the conformal interval scale ``c`` (network parts: infinite dof, learned from the residuals
    of all training rows and recalibrated; physics epistemic: ``n - p``), and the reference (Type B)."""
    n = int(params.get("n_rows") or m["split"]["n_train"])
    p = len(params["model"]["param_names"])
    c = block.get("interval_scale") or {a: 1.0 for a in AXES}
    nu_res = effective_dof(params, n, p)
    inf = {a: math.inf for a in AXES}
    noise = next(c_[3] for c_ in _components(m, params, reference_sd) if c_[0].startswith("aleatoric"))
    labels = {"aleatoric_nn": ("hybrid: network aleatoric x c", inf),
              "epistemic_nn": ("hybrid: network epistemic x c", inf),
              "epistemic_physics": ("hybrid: physics epistemic x c", nu_res),
              "aleatoric_physics": ("hybrid: physics aleatoric x c (fusion paper)", noise)}
    out = [(labels[k][0], {a: float(c[a]) * float(v[a]) for a in AXES}, labels[k][1])
           for k, v in block["parts"].items() if k in labels]
    return out + [("reference magnetometer", _per_axis_sd(reference_sd), inf)]


def expanded_uncertainties(m: dict, params: dict, reference_sd=0.0, *, stage: str = "calibration") -> dict:
    """Combined ``u_c``, ``nu_eff``, ``k`` and ``U = k u_c`` per axis for a same-session and a new-session
    recording (the latter with the between-session transfer sd in quadrature, counted with infinite dof:
    it is already an upper confidence bound over the training runs, ``core/predictor.estimate_transfer``).

    ``stage``: ``"calibration"`` (default), the predictor the run saved, which ``bayesmag apply`` and
    :func:`bayesmag.load` use; or ``"physics"``, the physics model alone (what the firmware exports hold).
    Where the run saved a hybrid predictor (:func:`hybrid_new_session`), the calibration's U is the *hybrid's*:
    its within-session parts (:func:`_hybrid_components`) and, for a new session, the transfer sd it adds (the
    network's own new-session part included with ``[uq] transfer_networks``); ``source`` is then ``"hybrid"`` and
    ``physics`` holds the physics model's own result (same keys). Else ``source`` is ``"physics"``.

    Returns ``{"level", "same_session": {axis: {u_c, nu_eff, k, U}}, "new_session": {...}, "transfer_sd",
    "new_session_missing", "source", "new_session_source"}``; ``new_session_missing`` (:func:`transfer_missing`) is
    None, or why the transfer term was not estimated: then ``new_session`` lacks it and understates U for a new
    session.
    """
    if stage not in ("calibration", "physics"):
        raise ValueError(f"stage = {stage!r} must be 'calibration' or 'physics'.")
    level = m["uq"]["level"]
    comps = _components(m, params, reference_sd)
    tau = _transfer_sd(m)
    out = {"level": level, "transfer_sd": tau, "same_session": {}, "new_session": {},
           "new_session_missing": transfer_missing(m), "source": "physics", "new_session_source": "physics"}
    for a in AXES:
        us, nus = [c[1][a] for c in comps], [c[3][a] for c in comps]
        for key, extra_u in (("same_session", []), ("new_session", [tau[a]])):
            out[key][a] = _combine(us + extra_u, nus + [math.inf] * len(extra_u), level)
    block = hybrid_new_session(m) if stage == "calibration" else None
    if block is not None:
        out["physics"] = {k: (dict(v) if isinstance(v, dict) else v) for k, v in out.items()}
        hc = _hybrid_components(m, params, reference_sd, block)
        out["source"] = out["new_session_source"] = "hybrid"
        out["family"] = block.get("family", "gaussian")
        factor = block.get("interval_factor") or {}          # runs before it: the Gaussian's
        out["interval_factor"] = {a: factor.get(a) for a in AXES}
        if out["new_session_missing"] is None:
            out["transfer_sd"] = {a: float(block["transfer_sd"][a]) for a in AXES}
        for a in AXES:
            f = factor.get(a)
            out["same_session"][a] = _combine([c[1][a] for c in hc], [c[2][a] for c in hc], level, f)
            if out["new_session_missing"] is None:
                out["new_session"][a] = _combine([c[1][a] for c in hc] + [out["transfer_sd"][a]],
                                                 [c[2][a] for c in hc] + [math.inf], level, f)
            else:
                out["new_session"][a] = out["same_session"][a]
    return out


def _network_transfer_sd(m: dict) -> bool:
    """The hybrid's network part of the new-session error was estimated (``[uq] transfer_networks``)."""
    return any(nt.get("sd") for nt in _transfer_networks(m))


def _transfer_networks(m: dict) -> list[dict]:
    """The ``transfer_network`` blocks of the run's networks (``[uq] transfer_networks``; none without)."""
    training = (m.get("network") or {}).get("training") or {}
    return [t["transfer_network"] for t in training.values()
            if isinstance(t, dict) and isinstance(t.get("transfer_network"), dict)]


def _hybrid_applies(ex: dict, hybrid: bool) -> str:
    """The sentence saying which predictor the budget's U belong to, for a run that saved a hybrid predictor."""
    if not hybrid:
        return ""
    phys = ex["physics"]
    new = ("" if ex["new_session_missing"] else " and " + " / ".join(_u2(phys["new_session"][a]["U"]) for a in AXES)
           + " uT for a new session")
    return (" This run saved the hybrid predictor (physics model and residual network): `bayesmag apply` and "
            "`bayesmag.load(...).predict` use it, and U same session and U new session above are its (its "
            "within-session parts, rows `hybrid: ...`, and the transfer part it adds). The physics model alone -- "
            "what `bayesmag export`'s firmware formats hold -- has U " + " / ".join(
                _u2(phys["same_session"][a]["U"]) for a in AXES) + " uT for the same session" + new
            + " (rows `physics model alone`).")


def _combine(uu: list, nn: list, level: float, family_factor: float | None = None) -> dict:
    """``u_c`` (root sum of squares of ``uu``), ``nu_eff`` (Welch-Satterthwaite over dof ``nn``), ``k`` and ``U = k u_c``.

    ``family_factor``: the predictive family's central-interval half-width in sd (a Laplace's 2.12 at 95 %, a
    Student-t's, the Gaussian's 1.96): ``k`` is then that factor times the Student t(nu_eff) correction
    ``t_nu(q) / z(q)``, so ``U`` is the half-width of the interval the predictor itself gives (a Laplace hybrid's
    U was 8-11 % below its own intervals with k from the normal)."""
    from scipy import stats
    uc = math.sqrt(sum(x * x for x in uu))
    nu = welch_satterthwaite(uu, nn)
    k = coverage_factor(nu, level)
    if family_factor is not None:
        k *= float(family_factor) / float(stats.norm.ppf(0.5 + level / 2))
    return {"u_c": uc, "nu_eff": nu, "k": k, "U": k * uc}


def _dof_text(v) -> str:
    """A dof as the budget prints it: per axis (x / y / z) when they differ, ``inf``, ``> 10^4`` beyond 10 000 (the
    coverage factor is then the normal's to 4 digits; the exact value is in no file: it is the budget's arithmetic)."""
    if isinstance(v, dict):
        vals = [v[a] for a in AXES]
        texts = [_dof_text(x) for x in vals]
        return texts[0] if len(set(texts)) == 1 else " / ".join(texts)
    return "inf" if not math.isfinite(v) else "> 10^4" if v > 1e4 else f"{v:.0f}"


def _loro_evaluation(m: dict) -> str:
    """The budget's evaluation text of a leave-one-run-out transfer sd: the usable runs R, the bound, the conditions."""
    import scipy.stats

    from bayesmag._src.core.predictor import TRANSFER_CONFIDENCE
    tr = m.get("transfer") or {}
    per = tr.get("per_run") or {}
    usable = [r for r, v in per.items() if v.get("rmse")]
    r = len(usable)
    if r < 2:
        return (f"{str(tr.get('method', '')).replace('_', ' ')} over the training runs; already an upper confidence "
                "bound, so counted with infinite dof")
    inflate = (r - 1) / scipy.stats.chi2.ppf(1 - TRANSFER_CONFIDENCE, r - 1)
    temps = [per[k]["temperature"] for k in usable if per[k].get("temperature")]
    return (f"leave one run out over R = {r} usable training runs (of {len(per)}; runs {', '.join(usable)}): the "
            f"one-sided {TRANSFER_CONFIDENCE:.0%} upper confidence bound of the new-session variance (x {inflate:.2f} "
            f"on it), so counted with infinite dof (the bound carries the uncertainty of {r} runs, not also R - 1 = "
            f"{r - 1} dof)"
            + (f"; the left-out rows it was measured on span {min(t[0] for t in temps):.3g}-"
               f"{max(t[1] for t in temps):.3g} C: how sessions differ outside that is not measured" if temps else ""))


def _validated_on(m: dict) -> str:
    """Which held-out rows validate U same session, and how far that flatters."""
    sp = m.get("split") or {}
    cov = ((m.get("hybrid") and next(iter(m["hybrid"].values())).get("coverage"))
           or (m.get("physics") or {}).get("coverage"))
    text = (f"validated on this run's test rows, {sp.get('description', 'the test split')}"
            + (": coverage " + " / ".join(f"{100 * cov[a]:.1f}" for a in AXES) + " %" if cov else ""))
    if sp.get("kind") == "random":
        text += ("; a random split interleaves the test rows with training rows, which flatters: held-out time "
                 "blocks of the same session cover less (docs/physics.md, `honest_*` configs)")
    return text


def _network_combined(m: dict) -> bool:
    """The hybrid's session model was fitted on the out-of-fold hybrid residuals (``network_transfer``)."""
    return any(nt.get("combined") for nt in _transfer_networks(m))


def uncertainty_budget(m: dict, params: dict, network_parts: dict | None = None, reference_sd=0.0) -> list[str]:
    """The uncertainty-budget section: components with Type A/B and dof, u_c, nu_eff, k and U per axis,
    for the same session and for a new session (transfer term)."""
    level = m["uq"]["level"]
    comps = _components(m, params, reference_sd)
    ex = expanded_uncertainties(m, params, reference_sd)
    tr = m.get("transfer") or {}
    rows = m["uq"].get("budget_rows")
    average = "root mean square" if "rms_aleatoric" in m["uq"] else "mean"
    lines = [f"## Uncertainty budget (standard uncertainties, {average} over "
             + (f"{rows}" if rows else "test rows") + ", uT)", "",
             "| component | type | dof | x | y | z | evaluation |", "|---|---|---|---|---|---|---|"]
    dof = _dof_text
    for label, vals, typ, nu, how in comps:
        lines.append(f"| {label} | {typ} | {dof(nu)} | " + " | ".join(_u2(vals[a]) for a in AXES) + f" | {how} |")
    if m["uq"].get("budget_rows_in_domain") == 0 or "none in domain" in str(rows or ""):
        ph = m["physics"]
        lines += ["", "> **No held-out row lies inside the calibration domain.** The parts above are averaged over "
                  "rows the calibration extrapolates to, and the U below are the model's stated uncertainty there, "
                  "not an accuracy it has shown: on these rows the RMSE is " + " / ".join(
                      f"{ph['rmse'][a]:.3g}" for a in AXES) + " uT and the intervals cover " + " / ".join(
                      f"{100 * ph['coverage'][a]:.0f}" for a in AXES) + " % (x / y / z). No U is established for "
                  "rows outside the domain (section Calibration domain).", ""]

    def block(key, name):
        c = ex[key]
        return [f"| **combined u_c, {name}** | | | " + " | ".join(_u2(c[a]["u_c"]) for a in AXES)
                + " | root sum of squares |",
                f"| effective dof nu_eff, {name} | | | " + " | ".join(dof(c[a]["nu_eff"]) for a in AXES)
                + " | Welch-Satterthwaite |",
                f"| coverage factor k ({level:.0%}), {name} | | | " + " | ".join(f"{c[a]['k']:.3f}" for a in AXES)
                + (" | Student t(nu_eff)" if not ex.get("interval_factor") or ex.get("family", "gaussian") == "gaussian"
                   else f" | the {ex['family']} family's interval half-width in sd (median over the rows, "
                        + " / ".join(f"{ex['interval_factor'][a]:.3f}" for a in AXES)
                        + ") x t(nu_eff) / z: U is the half-width of the predictor's own interval") + " |",
                f"| **expanded uncertainty U = k u_c, {name}** | | | " + " | ".join(_u2(c[a]["U"]) for a in AXES)
                + " | |"]
    hybrid = ex.get("source") == "hybrid"
    if hybrid:                  # the saved predictor is the hybrid: its own within-session parts, then its U
        phys = ex["physics"]
        lines += ["| expanded uncertainty U, same session, physics model alone | | | "
                  + " | ".join(_u2(phys["same_session"][a]["U"]) for a in AXES)
                  + " | what the firmware exports hold (the parts above) |"]
        for label, vals, nu in _hybrid_components(m, params, reference_sd, hybrid_new_session(m))[:-1]:
            avg = "root mean square" if hybrid_new_session(m).get("average") == "rms" else "mean"
            lines.append(f"| {label} | A | {dof(nu)} | " + " | ".join(_u2(vals[a]) for a in AXES)
                         + f" | the hybrid predictor's within-session part ({avg} over the test rows the budget uses; "
                           "c the interval scale) |")
    lines += block("same_session", "same session")
    tau = ex["transfer_sd"]
    if tr.get("method") in (None, "off"):
        how = "off (`[uq] transfer = \"off\"`): not estimated" if tr.get("method") == "off" else "not estimated"
    elif str(tr["method"]).startswith("hierarchical"):
        how = ("hierarchical session model (docs/sessions.md): its new-session predictive sd, the uncertainty about "
               "the between-session spread included, root mean square over the training rows (each row's own in "
               "`bayesmag apply`'s `transfer` column); counted with infinite dof" + _checked_note(tr))
    elif tr["method"] == "largest_offset_change":
        how = ("largest run-to-run change of the mean residual (fewer than 3 usable runs: a rough bound, not a "
               "confidence bound); counted with infinite dof")
    else:
        how = _loro_evaluation(m)
    missing = ex["new_session_missing"]
    dom = {a: max(comps, key=lambda c: c[1][a])[0].split(" (")[0] for a in AXES}
    same, new = ex["same_session"], ex["new_session"]
    d = m.get("data") or {}
    n_runs = len(d["train_runs"] if "train_runs" in d else d.get("runs") or [])   # runs before this key: all
    same_applies = (f"Which U applies: **U same session** ({' / '.join(_u2(same[a]['U']) for a in AXES)} uT, x / y "
                    "/ z) holds for rows of the recording session this calibration was fitted on (same mounting, same "
                    "power-up, the conditions of the test rows above; " + _validated_on(m) + ")"
                    + (f"; with {n_runs} training sessions pooled in one fit it holds over their rows together, and "
                       f"the rows of one particular session can be off by part of the between-session spread, for "
                       f"which U new session is the safe statement" if n_runs > 1 else ""))
    if missing:                 # no transfer term: a "U new session" would be the same-session U, understated
        lines += ["| transfer (between sessions; new session only) | A | | not estimated | not estimated | "
                  f"not estimated | {missing} |",
                  "| **expanded uncertainty U, new session** | | | not stated | not stated | not stated | needs the "
                  "transfer term |"]
        lines += ["", same_applies + ". **No U for a new session** (any later recording, "
                  f"in the field) can be stated: the between-session (transfer) term was not estimated ({missing}), "
                  "and a new session can be off by more than U same session. "
                  + ("A `bayesmag fleet` does not estimate it: calibrate this sensor alone with `bayesmag run` on at "
                     "least 3 sessions (runs), `[uq] transfer = \"loro\"` (the default). " if m.get("fleet") else
                     "Record at least 3 sessions (runs) and set `[uq] transfer = \"loro\"` (the default). ")
                  + "Inside the calibration domain only (section Calibration domain)."]
    else:
        if hybrid:              # the new-session U is the hybrid predictor's: its within-session parts + its transfer
            nt_sd = _network_transfer_sd(m)
            how = ("the hybrid's: " + ("hierarchical session model on the out-of-fold hybrid residuals (the "
                                       "network's own new-session error inside it)" if _network_combined(m) else
                                       "physics transfer part and the network's own new-session error in quadrature"
                                       if nt_sd else "the physics transfer part (the network's own new-session error "
                                       "not estimated: `[uq] transfer_networks = true` estimates it)")
                   + "; root mean square over the training rows, counted with infinite dof")
        lines.append("| transfer (between sessions; new session only) | A | inf | "
                     + " | ".join(_u2(tau[a]) for a in AXES) + f" | {how} |")
        lines += block("new_session", "new session")
        if hybrid:
            lines.append("| expanded uncertainty U, new session, physics model alone | | | "
                         + " | ".join(_u2(ex["physics"]["new_session"][a]["U"]) for a in AXES)
                         + " | the physics parts and the physics transfer sd: what the firmware exports hold |")
        lines += ["", same_applies + "; **U new session** "
                  f"({' / '.join(_u2(new[a]['U']) for a in AXES)} uT) holds for any later recording, i.e. in the "
                  "field (`bayesmag apply` adds the transfer term to every row of a new recording; column "
                  "`transfer`). Inside the calibration domain only (section Calibration domain)."
                  + (" With the hierarchical session model the transfer sd depends on the row's field and "
                     "temperature: the U here uses its root mean square over the training rows, and the table of "
                     "U at the corners of the training domain below shows its range."
                     if str(tr.get("method", "")).startswith("hierarchical") else "")
                  + _hybrid_applies(ex, hybrid)]
    if missing and hybrid:
        lines[-1] += _hybrid_applies(ex, hybrid)
    if network_parts:
        lines += ["", "Hybrid stage (residual network), for comparison:", "",
                  "| component | type | x | y | z |", "|---|---|---|---|---|"]
        for k_, v in network_parts.items():
            lines.append(f"| {k_} | A | " + " | ".join(_u2(v[a]) for a in AXES) + " |")
        for name, tr in ((m.get("network") or {}).get("training") or {}).items():
            nt = tr.get("transfer_network") if isinstance(tr, dict) else None
            if nt and nt.get("sd"):     # [uq] transfer_networks: in the hybrid's new-session transfer part
                lines.append(f"| network's own new-session error ({name}; new session only, `transfer_networks`"
                             + ("; inside the hybrid session model, not added again" if nt.get("combined") else "")
                             + ") | A | " + " | ".join(_u2(nt["sd"][a]) for a in AXES) + " |")
        if m.get("network", {}).get("fusion", "moment_match") == "paper":
            lines += ["", "With the residual network (fusion `paper`), the hybrid's total variance is the paper's "
                      "root-sum-of-squares of physics aleatoric, physics epistemic, network aleatoric and network "
                      "epistemic parts (the input noise is counted twice: intervals tend to over-cover)."]
        else:
            lines += ["", "With the residual network (fusion `moment_match`), the hybrid's total variance is network "
                      "aleatoric + network epistemic + physics epistemic: the network learned its aleatoric part "
                      "from residuals that already contain the propagated input noise and the unexplained scatter, "
                      "so the physics aleatoric and residual parts are not added again."]
    u = m["uq"]
    lines += ["", "Type A: evaluated statistically from the calibration data; Type B: from other information "
              "(JCGM 100:2008, 4.2-4.3). Uncertainties are given to two significant figures, values rounded to "
              "match (GUM 7.2.6). The reference's uncertainty enters the budget only: the job's intervals "
              "and coverage figures do not include it.",
              "Dominant physics part per axis: " + ", ".join(f"{a}: {dom[a]}" for a in AXES) + ".",
              "Input noise sd (Bx, By, Bz in uT, T in C): "
              + ", ".join(f"{k_} {_u2(v)}" for k_, v in u["sigma_in_sd"].items()) + f" ({u['sigma_in_source']}).", ""]
    return lines


def fit_statistics(m: dict, params: dict, reference_sd=0.0) -> list[str]:
    """Fit statistics per axis: n, p, dof, RSS, chi-square against the known noise, AIC, BIC, LM iterations."""
    n = int(params.get("n_rows") or m["split"]["n_train"])
    p = len(params["model"]["param_names"])
    ref = _per_axis_sd(reference_sd)
    lines = ["## Fit statistics (training rows)", "",
             "| axis | n | p | dof | RSS (uT^2) | noise sigma (uT) | chi^2 | chi^2/dof | AIC | BIC | LM iterations | result |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for a in AXES:
        ax = params["axes"][a]
        rss = n * ax["rmse_in_sample"] ** 2
        sigma = math.sqrt(m["uq"]["mean_aleatoric"][a] ** 2 + ref[a] ** 2)
        chi2 = rss / sigma**2 if sigma > 0 else math.inf
        ll = n * math.log(rss / n) if rss > 0 else -math.inf
        aic, bic = ll + 2 * (p + 1), ll + (p + 1) * math.log(n)
        sol = ax.get("solver", {})
        lines.append(f"| {a} | {n} | {p} | {n - p} | {rss:.5g} | {sigma:.4g} | {chi2:.5g} | {chi2 / (n - p):.4g} | "
                     f"{aic:.2f} | {bic:.2f} | {sol.get('steps', '-')} | {sol.get('result', '-')} |")
    lines += ["", "chi^2 = RSS / sigma^2 with sigma^2 the propagated input-noise variance (noise sigma: not the fit's "
              "residual sd; its mean over the test rows the budget uses, "
              "where the job propagates it; it changes little from row to row) (+ reference variance): "
              "chi^2/dof near 1 means the model explains the data down to the known noise. AIC = n ln(RSS/n) + 2(p+1), "
              "BIC = n ln(RSS/n) + (p+1) ln n (Gaussian likelihood, noise variance counted as a parameter).", ""]
    return lines


def _nuts_section(m: dict, nuts_rows: list[dict] | None) -> list[str]:
    nuts = m.get("nuts")
    if not nuts:
        return []
    lines = ["## NUTS cross-check", "",
             "| axis | verdict | max R-hat | min ESS bulk | min ESS tail | divergences |", "|---|---|---|---|---|---|"]
    for ax, b in nuts.get("axes", {}).items():
        lines.append(f"| {ax} | {b.get('verdict', '-')} | {b.get('max_rhat', float('nan')):.4f} | "
                     f"{b.get('min_ess_bulk', float('nan')):.0f} | {b.get('min_ess_tail', float('nan')):.0f} | "
                     f"{b.get('divergences', '-')} |")
    if nuts_rows:
        lines += ["", "| axis | parameter | mean | sd | R-hat | ESS bulk | ESS tail |", "|---|---|---|---|---|---|---|"]
        for r in nuts_rows:
            f = lambda k, spec: format(float(r[k]), spec) if r.get(k) not in (None, "") else "-"  # noqa: E731
            has = r.get("sd") not in (None, "") and r.get("mean") not in (None, "")
            mean, sd = gum_round(float(r["mean"]), float(r["sd"])) if has else (f("mean", ".6g"), f("sd", ".2g"))
            lines.append(f"| {r.get('axis', '')} | {r.get('parameter', '')} | {mean} | {sd} | "
                         f"{f('r_hat', '.4f')} | {f('ess_bulk', '.0f')} | {f('ess_tail', '.0f')} |")
    th = nuts.get("thresholds", {})
    if th:
        lines += ["", f"Thresholds: R-hat <= {th.get('rhat_max')}, ESS >= {th.get('ess_min')}."]
    return lines + [""]


def _hybrid_section(m: dict) -> list[str]:
    tests = m.get("hybrid_vs_physics")
    train = m.get("network", {}).get("training")
    if not tests and not train:
        return []
    lines = ["## Hybrid stage: paired test and training", ""]
    if tests:
        lines += ["Paired t-test (one-sided) of the per-row squared error, physics minus hybrid, on the test rows "
                  "(positive: the hybrid is better):", "",
                  "| likelihood | axis | mean difference (uT^2) | t | p | Cohen's d |", "|---|---|---|---|---|---|"]
        for lik, axes in tests.items():
            for a in AXES:
                if a in axes:
                    t = axes[a]
                    lines.append(f"| {lik} | {a} | {t['mean_diff']:.4g} | {t['t']:.3f} | {t['p']:.3g} | "
                                 f"{t['cohens_d']:.3f} |")
        lines.append("")
    if train:
        scaled = any("interval_scale" in axes.get(a, {}) for axes in train.values() for a in AXES)
        lines += ["| likelihood | axis | epochs run | best epoch | best validation loss |"
                  + (" conformal scale c |" if scaled else ""), "|---|---|---|---|---|" + ("---|" if scaled else "")]
        for lik, axes in train.items():
            for a in AXES:
                if a in axes:
                    t = axes[a]
                    k = t.get("interval_scale")
                    lines.append(f"| {lik} | {a} | {t.get('epochs_run', '-')} | {t.get('best_epoch', '-')} | "
                                 f"{t.get('best_val_loss', float('nan')):.5g} |"
                                 + ((f" {k:.3f} |" if k is not None else " - |") if scaled else ""))
        lines.append("")
        for lik, axes in train.items():
            c = axes.get("conformal")
            if c:
                lines += [f"Conformal scale c ({lik}): cross-conformal over {c['folds']} time-block folds, each one block "
                          f"of {c.get('block_fraction', float('nan')):.3g} of every run's training rows (the network's "
                          f"validation fraction, or as long as the job's test blocks if longer), {c['rows']} rows "
                          f"scored, each by the fold network that did not see it; c multiplies the sd of the hybrid's intervals "
                          f"(floored at 1; not the coverage factor k of the budget), and the "
                          f"{c['folds']} fold networks predict together as an ensemble "
                          f"({' / '.join(map(str, c.get('ensemble_passes', [])))} MC passes).", ""]
    return lines




def _thermo(params: dict) -> dict | None:
    terms = params["model"].get("terms") or []
    return terms[0] if terms and terms[0].get("name") == "thermo_affine" else None


def certificate_record(cfg, data) -> dict:
    """The identity block of ``metrics.json``: calibration ID, UTC date, bayesmag version, data sha256,
    device under test, reference instrument and operator (``[certificate]``).

    The data hash is the file's sha256 (a CSV path or a named dataset, whose pinned hash was
    verified at load); for simulated data, the sha256 of the generated arrays. The calibration ID is
    the first 16 hex digits of sha256(resolved config TOML + data hash): the same config and data
    give the same ID.
    """
    import datetime

    from bayesmag._src.core.version import __version__
    from bayesmag._src.app.config import to_toml

    d = cfg.data
    if d.path is not None:
        from bayesmag._src.core.datasets import sha256_of
        digest, what = sha256_of(Path(d.path)), f"file {Path(d.path).name}"
    elif d.source not in (None, "simulated", "field_simulated"):
        from bayesmag._src.core.datasets import DATASETS
        ds = DATASETS[d.source]
        digest, what = ds.sha256, f"dataset {d.source} (file {ds.filename}, verified at load)"
    else:
        h = hashlib.sha256()
        for arr in (data.b_meas, data.temperature, data.b_ref, data.time, data.run):
            if arr is not None:
                h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
        digest, what = h.hexdigest(), "simulated (sha256 of the generated arrays, float64)"
    conf = to_toml(cfg.to_dict())
    cid = hashlib.sha256((conf + digest).encode()).hexdigest()[:16]
    c = cfg.certificate
    return {"calibration_id": cid, "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(
            timespec="seconds"), "bayesmag_version": __version__, "data": what, "data_sha256": digest,
            "dut": c.dut, "reference": c.reference, "operator": c.operator}


@dataclasses.dataclass(frozen=True)
class ReportContext:
    """What every section of the certificate may read."""

    metrics: dict
    params: dict
    figures: tuple = ()
    corr_threshold: float = 0.9
    network_parts: dict | None = None
    reference_sd: float | list = 0.0
    nuts_rows: list | None = None


def _identity_section(c: ReportContext) -> list[str]:
    m = c.metrics
    rec = m.get("certificate") or {}
    unset = lambda v, key: v or f"not stated (set `[certificate] {key} = \"...\"`)"  # noqa: E731
    lines = ["# Calibration report (certificate)", "",
             "| item | value |", "|---|---|",
             f"| calibration ID | {rec.get('calibration_id', 'not recorded (run written before bayesmag 0.1 certificates)')} |",
             f"| date (UTC) | {rec.get('date_utc', 'not recorded')} |",
             f"| bayesmag version | {rec.get('bayesmag_version', 'not recorded')} |",
             f"| device under test | {unset(rec.get('dut'), 'dut')} |",
             f"| reference instrument | {unset(rec.get('reference'), 'reference')} |"]
    if rec.get("operator"):
        lines.append(f"| operator | {rec['operator']} |")
    lines += [f"| data | {m['data']['source']}: {rec.get('data', '')} |",
              f"| data sha256 | `{rec.get('data_sha256', 'not recorded')}` |", "",
              f"Data: {m['data']['n_rows']} rows, runs {m['data']['runs']}. "
              f"Split: {m['split']['description']} ({m['split']['n_train']} train / {m['split']['n_test']} test rows).",
              f"Covariance: {c.params.get('covariance_method', '')}. Physics model parameters: "
              f"{', '.join(c.params['model']['param_names'])}.", ""]
    fl = m.get("fleet")
    if isinstance(fl, dict) and fl.get("verdict"):     # a sensor folder of `bayesmag fleet`
        why = [*(fl.get("fails_limits") or []), *(["outlier"] if fl.get("outlier") else [])]
        lines += [f"**Fleet verdict: {fl['verdict'].upper()}**"
                  + (f" ({', '.join(why)}; the fleet's fleet_report.md and docs/fleet.md say what each means)."
                     if fl["verdict"] == "fail" else " (every check of the fleet's sign-off met)."), ""]
    for w in m.get("warnings", []):
        lines += [f"> **Warning.** {w}", ""]
    for note in c.params.get("design_notes", []):
        lines += [f"> **Design note.** {note}", ""]
    return lines


def _accuracy_section(c: ReportContext) -> list[str]:
    m = c.metrics
    lines = ["## Accuracy and coverage (test rows)", "", "| stage | metric | x | y | z |", "|---|---|---|---|---|"]

    def row(stage, key, block, pct=False):
        vals = [block[key][a] * (100 if pct else 1) for a in AXES]
        f = (lambda v: f"{v:.1f}%") if pct else (lambda v: f"{v:.4g}")
        lines.append(f"| {stage} | {key} | " + " | ".join(f(v) for v in vals) + " |")

    row("raw", "rmse", m["raw"]); row("raw", "mae", m["raw"])
    for k in ("rmse", "mae", "nll", "crps"):
        row("physics", k, m["physics"])
    row("physics", "coverage", m["physics"], pct=True)
    for name, block in m.get("hybrid", {}).items():
        for k in ("rmse", "mae", "nll", "crps"):
            if k in block:
                row(f"hybrid ({name})", k, block)
        if "coverage" in block:
            row(f"hybrid ({name})", "coverage", block, pct=True)
    level = m["uq"]["level"]
    return lines + ["", f"Coverage is of central {level:.0%} intervals; a trustworthy model is close to {level:.0%}.",
                    ""]


def _field_section(c: ReportContext) -> list[str]:
    f = c.metrics.get("field")
    if not f:
        return []
    h0 = next(iter(f.values()))["heading"]
    lines = ["## Field metrics (test rows)", "",
             "What a compass or drone engineer signs off on: the magnitude residual |B_cal| - |B_ref| (uT) and the "
             "heading error (degrees; heading = atan2(-By, Bx) of a level sensor, x forward, y right, from the "
             f"horizontal components; rows with a horizontal reference field below {h0['min_horizontal_uT']:g} uT "
             f"have no defined heading and are left out: {h0['n_excluded']} rows).", "",
             "| stage | magnitude residual mean (uT) | sd | RMS | max abs | heading error RMS (deg) | 95% abs | max abs |",
             "|---|---|---|---|---|---|---|---|"]
    fmt = lambda d, k, spec: format(d[k], spec) if k in d else "-"  # noqa: E731
    for stage, b in f.items():
        mg, hd = b["magnitude"], b["heading"]
        lines.append(f"| {stage} | {fmt(mg, 'mean', '+.3g')} | {fmt(mg, 'sd', '.3g')} | {fmt(mg, 'rms', '.3g')} | "
                     f"{fmt(mg, 'max_abs', '.3g')} | {fmt(hd, 'rms', '.3g')} | {fmt(hd, 'p95_abs', '.3g')} | "
                     f"{fmt(hd, 'max_abs', '.3g')} |")
    stages = [s for s in f if s != "raw"]
    lines += ["", "Per run (heading error RMS / max abs in degrees, '-' where no row of the run has a defined "
              "heading; magnitude residual RMS in uT):", "",
              "| run | rows | " + " | ".join(f"{s}: heading RMS / max | {s}: magnitude RMS" for s in stages) + " |",
              "|---|---|" + "---|---|" * len(stages)]
    for r in f[stages[0]]["heading"]["per_run"]:
        cells = []
        for s in stages:
            hd, mg = f[s]["heading"]["per_run"][r], f[s]["magnitude"]["per_run"][r]
            cells += [f"{fmt(hd, 'rms', '.3g')} / {fmt(hd, 'max_abs', '.3g')}", fmt(mg, "rms", ".3g")]
        lines.append(f"| {r} | {f[stages[0]]['magnitude']['per_run'][r]['n_rows']} | " + " | ".join(cells) + " |")
    return lines + [""]


def _model_section(c: ReportContext) -> list[str]:
    """The model equation with T0, S and Ks as 3x3 matrices, O and Ko as vectors, each value +- u."""
    th = _thermo(c.params)
    if th is None:
        return []
    note = white_covariance_note(c.params)
    ax = c.params["axes"]
    v = lambda a, n: (ax[a]["values"][n], ax[a]["std"][n])  # noqa: E731
    temp = th.get("temperature", True)
    lines = ["## Calibration model", "",
             "    B_cal = (S + Ks (T - T0)) B_meas + O + Ko (T - T0)" if temp else "    B_cal = S B_meas + O", "",
             f"with B_meas and B_cal column vectors (x, y, z) in uT, T the sensor temperature in C and "
             f"**T0 = {th['t0']:.6g} C** (the reference temperature of this fit; `params.json` model.terms[0].t0). "
             "Row i of S is output axis i. Values +- standard uncertainty u (k = 1)"
             + (" from the white covariance, which understates them here (section Physics parameters):" if note
                else ":"), "",
             "| S (1) | B_x | B_y | B_z |", "|---|---|---|---|"]
    for a in AXES:
        lines.append(f"| {a} | " + " | ".join(gum_format(*v(a, f"S_{b}")) for b in AXES) + " |")
    if temp:
        lines += ["", "| Ks (1/C) | B_x | B_y | B_z |", "|---|---|---|---|"]
        for a in AXES:
            lines.append(f"| {a} | " + " | ".join(gum_format(*v(a, f"Ks_{b}")) for b in AXES) + " |")
    lines += ["", "| axis | O (uT) | " + ("Ko (uT/C) |" if temp else ""), "|---|---|" + ("---|" if temp else "")]
    for a in AXES:
        lines.append(f"| {a} | {gum_format(*v(a, 'O'))} | " + (f"{gum_format(*v(a, 'Ko'))} |" if temp else ""))
    extra = [n for n in c.params["model"]["param_names"]
             if n not in ("S_x", "S_y", "S_z", "Ks_x", "Ks_y", "Ks_z", "O", "Ko")]
    if extra:
        lines += ["", f"Further terms ({', '.join(t['name'] for t in c.params['model']['terms'][1:])}; "
                  f"parameters {', '.join(extra)}) are in the per-axis tables of section Physics parameters."]
    return lines + [""]


def _budget_section(c: ReportContext) -> list[str]:
    return uncertainty_budget(c.metrics, c.params, c.network_parts, c.reference_sd)


def _fit_section(c: ReportContext) -> list[str]:
    return fit_statistics(c.metrics, c.params, c.reference_sd)


def _transfer_section(c: ReportContext) -> list[str]:
    lines = transfer_section(c.metrics)
    table = condition_uncertainties(c.metrics, c.params, c.reference_sd)
    if table:
        lines += condition_table_lines(table, c.metrics["uq"]["level"])
    return lines


def condition_uncertainties(m: dict, params: dict, reference_sd=0.0) -> list[dict]:
    r"""U for a new session at the training domain's corners (hierarchical transfer only; else ``[]``).

    Per condition and axis: :math:`u_c^2 = u_{c,\mathrm{same}}^2 + \tau(x)^2` with the budget's
    same-session :math:`u_c` (mean over the test rows) and the row-dependent transfer sd :math:`\tau(x)` of the
    hierarchical model at that condition (``metrics["transfer"]["per_run"]["conditions"]``), ``k`` by
    Welch-Satterthwaite with the transfer part at infinite dof, ``U = k u_c``. Where the run holds the hybrid's
    new-session budget with its conditions (:func:`hybrid_new_session`), the hybrid's: its within-session parts
    and the transfer sd it adds there. Returns ``[{"field", "temperature", "transfer_sd", "U", "source"}]``
    (``transfer_sd`` and ``U`` per axis, uT; ``source`` ``"physics"`` or ``"hybrid"``).
    """
    tr = m.get("transfer") or {}
    conds = (tr.get("per_run") or {}).get("conditions") if str(tr.get("method", "")).startswith("hierarchical") else None
    if not conds:
        return []
    level = m["uq"]["level"]
    comps = [(c[0], c[1], c[3]) for c in _components(m, params, reference_sd)]
    hb, source = hybrid_new_session(m), "physics"
    if hb is not None and hb.get("conditions"):     # the hybrid's new-session U (expanded_uncertainties)
        conds, comps, source = hb["conditions"], _hybrid_components(m, params, reference_sd, hb), "hybrid"
    factor = (hb.get("interval_factor") or {}) if source == "hybrid" else {}
    out = []
    for c in conds:
        U = {a: _combine([x[1][a] for x in comps] + [c["transfer_sd"][a]], [x[2][a] for x in comps] + [math.inf],
                         level, factor.get(a))["U"] for a in AXES}
        out.append({"field": c["field"], "temperature": c["temperature"], "transfer_sd": c["transfer_sd"], "U": U,
                    "source": source})
    return out


def condition_table_lines(table: list[dict], level: float) -> list[str]:
    """The report.md table of :func:`condition_uncertainties`."""
    lines = [f"Expanded uncertainty U ({level:.0%}) for a new session by condition: the transfer sd of the "
             "hierarchical model at the corners of the training domain (field at the per-axis minimum, zero and "
             "maximum of the training rows; lowest and highest training temperature), added in quadrature to "
             "the same-session u_c of the budget above (uT). A corner of the per-input ranges may combine inputs "
             "no training row combined (e.g. the highest temperature with a large field): the model's "
             "extrapolation there is what the large values say."
             + (" Hybrid: the transfer sd the hybrid predictor adds there (its session model on the out-of-fold "
                "hybrid residuals, or the physics one with the network's own new-session part), added to the "
                "hybrid's within-session u_c of the budget." if table and table[0].get("source") == "hybrid" else ""),
             "",
             "| B x / y / z (uT) | T (C) | transfer sd x / y / z | U new session x / y / z |", "|---|---|---|---|"]
    for r in table:
        lines.append(f"| {' / '.join(f'{v:.4g}' for v in r['field'])} | {r['temperature']:.4g} | "
                     + " / ".join(_u2(r["transfer_sd"][a]) for a in AXES) + " | "
                     + " / ".join(_u2(r["U"][a]) for a in AXES) + " |")
    return lines + [""]


def _domain_section(c: ReportContext) -> list[str]:
    d = c.metrics.get("domain")
    if not d:
        return []
    lines = ["## Calibration domain", "",
             "Training ranges (with margin): " + "; ".join(f"{k} [{lo:.3g}, {hi:.3g}]"
                                                           for k, (lo, hi) in d["training_ranges"].items()) + "."]
    if d.get("training_rate_limits"):
        lines.append("Largest rates seen in training (with margin): " + "; ".join(
            f"{k} {v:.3g}" for k, v in d["training_rate_limits"].items()) + " (uT/s, C/s).")
    return lines + [f"Test rows outside it: {d['n_outside']} of {d['n_rows']}.", ""]


def _hybrid_nuts_section(c: ReportContext) -> list[str]:
    return _hybrid_section(c.metrics) + _nuts_section(c.metrics, c.nuts_rows)


def _parameters_section(c: ReportContext) -> list[str]:
    lines = ["## Physics parameters", ""]
    note = white_covariance_note(c.params)
    if note:
        lines += [f"> **Understated parameter uncertainties.** {note}", ""]
    for ax in AXES:
        lines += _param_table(ax, c.params["axes"][ax], c.corr_threshold)
    return lines


def _figures_section(c: ReportContext) -> list[str]:
    lines = (["## Figures", ""] + [f"![{f}]({f})" for f in c.figures] + [""]) if c.figures else []
    t = c.metrics.get("timings", {})
    if t:
        lines += ["Timings (s): " + ", ".join(f"{k} {v:.3g}" for k, v in t.items()) + "."]
    return lines


#: The certificate's sections, in order: each ``f(ReportContext) -> list[str]`` of Markdown lines.
SECTIONS = (_identity_section, _model_section, _accuracy_section, _field_section, _budget_section, _fit_section,
            _transfer_section, _domain_section, _hybrid_nuts_section, _parameters_section, _figures_section)


def render_report(metrics: dict, params: dict, figures=(), corr_threshold: float = 0.9,
                  network_parts: dict | None = None, reference_sd=0.0, nuts_rows: list[dict] | None = None,
                  sections=SECTIONS) -> str:
    """The certificate as Markdown: every function of ``sections`` applied to one :class:`ReportContext`."""
    ctx = ReportContext(metrics, params, tuple(figures), corr_threshold, network_parts, reference_sd, nuts_rows)
    lines = [ln for sec in sections for ln in sec(ctx)]
    return "\n".join(lines) + "\n"


def transfer_section(m: dict) -> list[str]:
    """report.md lines on the transfer (between-session) part of the budget and the dynamic domain."""
    tr = m.get("transfer")
    if not tr:
        return []
    sd, z = tr["sd"], 1.959963984540054
    lines = ["## Transfer to a new session", ""]
    if tr["method"] == "off":
        return lines + ["Transfer uncertainty is off (`[uq] transfer = \"off\"`): intervals for new recordings "
                        "hold within-session parts only and will be too narrow if the sensor changes between "
                        "sessions.", ""]
    lines.append(f"This calibration transfers to a new session with +/- {_u2(z * sd['x'])} / {_u2(z * sd['y'])} / "
                 f"{_u2(z * sd['z'])} uT (x / y / z; 1.96 x the between-session sd {_u2(sd['x'])} / {_u2(sd['y'])} / "
                 f"{_u2(sd['z'])} uT), added in quadrature to every prediction of a new recording (`bayesmag apply`; "
                 f"column `transfer`); the budget above combines it with the within-session parts (U new session).")
    if tr["method"] == "leave_one_run_out":
        rows = [(r, v) for r, v in tr["per_run"].items()]
        lines += ["Estimated by leaving each training run out (rows inside the other runs' value domain):", "",
                  "| left-out run | in-domain rows | RMSE x / y / z (uT) |", "|---|---|---|"]
        for r, v in rows:
            rm = " / ".join(f"{v['rmse'][a]:.3g}" for a in AXES) if v["rmse"] else "not refitted"
            lines.append(f"| {r} | {v['n_in_domain']} | {rm} |")
    elif tr["method"].startswith("hierarchical"):
        lines[-1] = lines[-1].replace("the between-session sd", "the root-mean-square between-session sd over "
                                      "the training rows")
        lines.append("The between-session sd depends on the row (hierarchical model of per-run parameter changes, "
                     "docs/sessions.md): each row of a new recording gets its own (column `transfer`)."
                     + (" O" + _checked_note(tr)[3:] + "." if _checked_note(tr) else ""))
        if tr.get("warning"):
            lines.append(f"> **Warning.** {tr['warning']}")
    else:
        lines.append(f"> **Warning.** {tr['warning']}")
    hb = hybrid_new_session(m)
    if hb is not None:          # the saved (hybrid) predictor adds its own transfer part: the budget's U new session
        lines.append("The saved calibration is the hybrid predictor, and it adds its own transfer sd to a new session "
                     "(root mean square over the training rows " + " / ".join(_u2(hb["transfer_sd"][a]) for a in AXES)
                     + " uT; `[uq] transfer_networks`, docs/sessions.md): the budget's U new session is the hybrid's.")
    n_new = tr.get("n_test_rows_new_session", 0)
    lines += ["", f"Test rows from runs not in the training data (they include the transfer part): {n_new}."
              + (" The test rows share sessions with the training rows, so their scores above do not include it."
                 if n_new == 0 else ""), ""]
    d = m.get("domain", {})
    if d.get("by_reason"):
        lines += ["Test rows out of domain by reason: " + ", ".join(f"{k} {v}" for k, v in d["by_reason"].items())
                  + ".", ""]
    return lines


def _network_parts(path: Path) -> dict | None:
    """Mean network aleatoric / epistemic sd per axis from predictions.csv, if the hybrid stage ran."""
    import csv
    if not path.exists():
        return None
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or "x_aleatoric_nn" not in rows[0]:
        return None
    out = {}
    for label, col in (("network aleatoric (learned from the residuals)", "aleatoric_nn"),
                       ("network epistemic (MC DropConnect)", "epistemic_nn")):
        out[label] = {a: float(np.mean([float(r[f"{a}_{col}"]) for r in rows])) for a in AXES}
    return out



_INLINE = [(re.compile(r"\*\*(.+?)\*\*"), r"<strong>\1</strong>"), (re.compile(r"`([^`]+)`"), r"<code>\1</code>")]
_CSS = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;line-height:1.4}"
        "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #bbb;padding:2px 6px;"
        "font-size:0.9em}th{background:#eee}blockquote{border-left:4px solid #c90;margin:0.5em 0;"
        "padding:0.2em 0.8em;background:#fff8e8}pre{background:#f4f4f4;padding:0.5em}img{max-width:100%}")


def _inline(text: str) -> str:
    out = html.escape(text, quote=False)
    for pat, rep in _INLINE:
        out = pat.sub(rep, out)
    return out


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def render_html(markdown: str, folder: str | Path | None = None, title: str = "Calibration certificate") -> str:
    """``report.md``'s content as one self-contained HTML page, figures embedded as base64 PNG.

    Handles the Markdown the certificate uses: ``#`` headings, pipe tables, ``>`` quotes, ``-``
    lists, indented code, ``![alt](file.png)`` images (read from ``folder``), ``**bold**`` and
    ``code``. Only the standard library: no dependency.
    """
    folder = Path(folder) if folder is not None else None
    lines = markdown.splitlines()
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>"]
    i, para = 0, []

    def flush():
        if para:
            out.append("<p>" + " ".join(_inline(p) for p in para) + "</p>")
            para.clear()

    while i < len(lines):
        ln = lines[i]
        img = re.fullmatch(r"!\[([^\]]*)\]\(([^)]+)\)", ln.strip())
        if not ln.strip():
            flush()
        elif ln.startswith("#"):
            flush()
            level = len(ln) - len(ln.lstrip("#"))
            out.append(f"<h{level}>{_inline(ln[level:].strip())}</h{level}>")
        elif ln.startswith("|") and i + 1 < len(lines) and re.fullmatch(r"\|[-|: ]+\|?", lines[i + 1].strip()):
            flush()
            head = _cells(ln)
            out.append("<table><thead><tr>" + "".join(f"<th>{_inline(h)}</th>" for h in head) + "</tr></thead><tbody>")
            i += 2
            while i < len(lines) and lines[i].startswith("|"):
                out.append("<tr>" + "".join(f"<td>{_inline(x)}</td>" for x in _cells(lines[i])) + "</tr>")
                i += 1
            out.append("</tbody></table>")
            continue
        elif ln.startswith(">"):
            flush()
            out.append(f"<blockquote>{_inline(ln.lstrip('>').strip())}</blockquote>")
        elif ln.startswith("- "):
            flush()
            out.append("<ul>")
            while i < len(lines) and lines[i].startswith("- "):
                out.append(f"<li>{_inline(lines[i][2:])}</li>")
                i += 1
            out.append("</ul>")
            continue
        elif ln.startswith("    "):
            flush()
            code = []
            while i < len(lines) and lines[i].startswith("    "):
                code.append(html.escape(lines[i][4:]))
                i += 1
            out.append("<pre>" + "\n".join(code) + "</pre>")
            continue
        elif img:
            flush()
            alt, src = img.groups()
            path = folder / src if folder is not None else None
            if path is not None and path.is_file():
                data = base64.b64encode(path.read_bytes()).decode("ascii")
                out.append(f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'
                           f"<figcaption>{html.escape(alt)}</figcaption></figure>")
            else:
                out.append(f"<p>[figure {html.escape(src)} not found]</p>")
        else:
            para.append(ln)
        i += 1
    flush()
    out.append("</body></html>")
    return "\n".join(out) + "\n"


def _axes_null_as_nan(d):
    """Per-axis values written as ``null`` (strict JSON for NaN, jsonio) read back as NaN for the tables."""
    if isinstance(d, dict):
        return {k: (float("nan") if v is None and k in AXES else _axes_null_as_nan(v)) for k, v in d.items()}
    if isinstance(d, list):
        return [_axes_null_as_nan(v) for v in d]
    return d


def write_report(run_dir: str | Path, *, require_marker: bool = True) -> Path:
    """(Re)write ``report.md`` and ``report.html`` (figures embedded) in a run folder from its
    metrics.json and params.json; returns the path of ``report.md``.

    The folder must hold a valid bayesmag marker (``require_marker``; the job itself writes the
    report into its staging folder without one), and an existing report must be one the marker
    lists: a folder or a report that bayesmag did not write is never changed. Each file is written
    to a temporary sibling, renamed into place and listed in the marker.
    """
    from bayesmag._src.app.outdir import MARKER, OutputError, atomic_write_text, marker_problem, marker_status, register

    from bayesmag._src.app.artifact import field_run_error

    run_dir = Path(run_dir)
    field_run_error(run_dir, OutputError)
    out, out_html = run_dir / "report.md", run_dir / "report.html"
    owner, prefix = run_dir, ""
    if require_marker:
        mark = marker_status(run_dir) if run_dir.is_dir() else None
        fleet = _fleet_owner(run_dir) if mark is None else None
        if fleet is not None:                       # sensors/<id>/ of `bayesmag fleet`: the fleet's marker lists it
            owner, mark = fleet
            prefix = run_dir.resolve().relative_to(owner.resolve()).as_posix() + "/"
        problem = marker_problem(mark)
        if problem is not None:
            raise OutputError(f"{run_dir} is not a finished bayesmag run folder ({problem}); `bayesmag report` "
                              f"writes only into folders written by `bayesmag run` (or the sensors/<id>/ folders "
                              f"of `bayesmag fleet`). Give such a folder.")
        for path in (out, out_html):
            if (path.exists() or path.is_symlink()) and (prefix + path.name not in mark["files"]
                                                         or path.is_symlink() or not path.is_file()):
                raise OutputError(f"{path} was not written by bayesmag (its {MARKER} does not list it); it will "
                                  f"not be replaced. Move it away and retry.")
    for f in ("metrics.json", "params.json"):
        if not (run_dir / f).exists():
            raise FileNotFoundError(f"{run_dir} has no {f}: give a folder written by `bayesmag run`.")
    metrics = _axes_null_as_nan(json.loads((run_dir / "metrics.json").read_text()))
    params = _axes_null_as_nan(json.loads((run_dir / "params.json").read_text()))
    figs = sorted(p.name for p in run_dir.glob("*.png"))
    nuts_rows = None
    if (run_dir / "nuts_summary.csv").exists():
        import csv
        with open(run_dir / "nuts_summary.csv", newline="") as f:
            nuts_rows = list(csv.DictReader(f))
    text = render_report(metrics, params, figs, network_parts=_network_parts(run_dir / "predictions.csv"),
                         reference_sd=run_reference_sd(run_dir), nuts_rows=nuts_rows)
    page = render_html(text, run_dir)
    if require_marker:
        from bayesmag._src.app.outdir import recover
        recover(run_dir, files_only=True)   # partial reports of killed processes
        for path, content in ((out, text), (out_html, page)):
            atomic_write_text(path, content)
            register(owner, path)
    else:
        out.write_text(text)
        out_html.write_text(page)
    return out


def _fleet_owner(sensor_dir: Path):
    """``(fleet folder, its marker)`` when ``sensor_dir`` is ``<fleet>/sensors/<id>/`` of a finished
    ``bayesmag fleet`` whose marker lists the sensor's ``metrics.json``; else None."""
    from bayesmag._src.app.outdir import marker_problem, marker_status

    sensor_dir = Path(sensor_dir)
    if not sensor_dir.is_dir() or sensor_dir.resolve().parent.name != "sensors":
        return None
    fleet = sensor_dir.resolve().parent.parent
    mark = marker_status(fleet)
    if marker_problem(mark) is not None or mark.get("kind", "fleet") != "fleet" or not (fleet / "fleet.json").is_file():
        return None
    if f"sensors/{sensor_dir.resolve().name}/metrics.json" not in mark["files"]:
        return None
    return fleet, mark


def run_reference_sd(run_dir: Path):
    """``[uq] reference_sd`` of the run's saved config (0 when absent)."""
    if (Path(run_dir) / "calibration.json").exists():
        cfg = json.loads((Path(run_dir) / "calibration.json").read_text()).get("config", {})
        return cfg.get("uq", {}).get("reference_sd", 0.0)
    return 0.0
