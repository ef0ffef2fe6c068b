"""What discovery found: :class:`DiscoveryResult`, findings.json and the plain-words report.md."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from bayesmag._src.core.jsonio import write_json
from bayesmag._src.core.data import AXES
from bayesmag._src.pipeline.discover.options import DBIC_MIN, FLOOR_RATIO, LOCATE_FRACTION, LOCATE_P, MIN_GAIN, N_PERM, \
    PIECES, RHO_STRUCTURE, T_IDENT, UNEXPLAINED_FRACTION, Z_DISTINCT, Z_MIN, Z_RUN, DiscoverOptions

__all__ = ["DiscoveryResult", "report_markdown"]


@dataclasses.dataclass
class DiscoveryResult:
    """What :func:`~bayesmag._src.pipeline.discover.discover` found. ``to_json()`` is findings.json
    (written, with report.md and the figures, by :func:`bayesmag.write_discovery`).

    ``findings``: one entry per physical effect, with ``channel`` (the sensor channel it acts
    on; ``"all"`` for whole-sensor effects; None for an output-frame term), ``axis`` (the
    channel, or the output axis of an output-frame term; kept for compatibility), ``outputs``
    (the calibrated outputs it shows in) and ``parameters`` (identified coefficients only;
    the rest under ``not_identified``). ``unexplained``: structure left, per sensor channel."""

    findings: list
    unexplained: list
    located: list
    baseline: dict
    final: dict
    extra_terms: list
    notes: list
    skipped: list
    options: DiscoverOptions
    source: str
    seconds: float
    rejected: list = dataclasses.field(default_factory=list)
    arrays: dict = dataclasses.field(default_factory=dict, repr=False)
    closest_not_accepted: dict | None = None

    @property
    def no_missing_physics(self) -> bool:
        return not self.findings and not self.unexplained

    def to_json(self) -> dict:
        return {
            "source": self.source,
            "no_missing_physics": self.no_missing_physics,
            "frame": "sensor: B_ref = (S + Ks Tc)(u - d) + O + Ko Tc, d acting on one sensor channel",
            "baseline": self.baseline,
            "final": self.final,
            "findings": self.findings,
            "unexplained": self.unexplained,
            "rejected": self.rejected,
            "closest_not_accepted": self.closest_not_accepted,
            "extra_terms": self.extra_terms,
            "located": [{k: v for k, v in l.items() if k not in ("bin_labels", "bin_means")} for l in self.located],
            "notes": self.notes,
            "skipped": self.skipped,
            "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self.options).items()},
            "thresholds": {"z_min": Z_MIN, "min_gain": MIN_GAIN, "dbic_min": DBIC_MIN, "z_distinct": Z_DISTINCT,
                           "t_ident": T_IDENT, "locate_p": LOCATE_P, "locate_fraction": LOCATE_FRACTION,
                           "unexplained_fraction": UNEXPLAINED_FRACTION, "z_run": Z_RUN, "pieces": PIECES,
                           "n_perm": N_PERM, "rho_structure": RHO_STRUCTURE, "floor_ratio": FLOOR_RATIO},
            "seconds": self.seconds,
        }


def jsonable(x):
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    return x


def _outputs_phrase(outs: list) -> str:
    if len(outs) == 3:
        return "all three calibrated outputs"
    if len(outs) == 2:
        return f"the {outs[0]} and {outs[1]} calibrated outputs"
    return f"the {outs[0]} calibrated output" if outs else "no calibrated output above the noise"


def headline(fd: dict) -> str:
    """One sentence per effect, in the frame where it happens."""
    if fd["frame"] == "sensor":
        return (f"the {fd['channel']} sensor channel's {fd['description']}; seen in {_outputs_phrase(fd['outputs'])} "
                f"through the calibration matrix")
    if fd["frame"] == "whole":
        return f"the {fd['description']} (acts on every channel); seen in {_outputs_phrase(fd['outputs'])}"
    return (f"the {fd['axis']} calibrated output's {fd['description']} (an output-frame term: it predicts better "
            f"out of sample than the same term on any sensor channel)")


def report_markdown(res: DiscoveryResult, figures: Sequence[str] = ()) -> str:
    """A plain-words report for a metrologist."""
    L = ["# Discovery of missing physics", "", f"Data: {res.source}", "",
         f"Out-of-sample scores: {res.baseline['cv']}. Discovery took {res.seconds:.1f} s.", "",
         "Effects are modelled where they happen: as distortions of one sensor channel's reading, "
         "B_ref = (S + Ks Tc)(u - d) + O + Ko Tc, fitted jointly over the three outputs. One effect is one finding, "
         "whichever outputs it reaches through the calibration matrix.", ""]
    if res.no_missing_physics:
        L += ["**No missing physics was found.** " + _no_extension(res.closest_not_accepted)
              + " The residual of every sensor channel is close to its high-frequency noise floor "
              f"(lag-1 autocorrelation < {RHO_STRUCTURE} or variance < {FLOOR_RATIO} x the floor) with no located "
              f"structure (thresholds: block z >= {Z_MIN}, gain >= {MIN_GAIN:.0%}, BIC_eff drop >= {DBIC_MIN}; "
              f"located structure is reported when it holds >= {UNEXPLAINED_FRACTION:.0%} of the residual variance "
              f"at block-permutation p <= {LOCATE_P}).", ""]
    L += ["## Before and after, per calibrated output (out of sample unless noted)", "",
          "| output | RMSE before | RMSE after | MAE before | MAE after | lag-1 autocorr. before | after |",
          "|---|---|---|---|---|---|---|"]
    b, f = res.baseline, res.final
    for ax in AXES:
        L.append(f"| {ax} | {b['rmse'][ax]:.4g} | {f['rmse'][ax]:.4g} | {b['mae'][ax]:.4g} | {f['mae'][ax]:.4g} | "
                 f"{b['lag1_autocorrelation'][ax]:.2f} | {f['lag1_autocorrelation'][ax]:.2f} |")
    L += ["", "RMSE/MAE in uT; lag-1 autocorrelation of the in-sample residual.", ""]
    if res.findings:
        L += ["## Findings", ""]
        for i, fd in enumerate(res.findings, 1):
            ev = fd["evidence"]
            ps = ", ".join(f"{k} = {p['value']:.4g} +- {p['se']:.2g}" + (f" {p['unit']}" if p.get("unit") else "")
                           + (f" (95 % interval {p['interval95'][0]:.4g} to {p['interval95'][1]:.4g}"
                              f"{' ' + p['unit'] if p.get('unit') else ''})" if p.get("interval95") else "")
                           for k, p in fd["parameters"].items())
            rb, ra = fd["rmse_before"], fd["rmse_after"]
            L += [f"### {i}. {fd['effect']}: {headline(fd)}", "", f"*{fd['explanation']}*", "",
                  f"- Setting: {fd['setting']}; fitted (+- one standard error, Newey-West, joint fit of the three "
                  f"outputs): {ps}.",
                  "- Out-of-sample RMSE (uT) " + ", ".join(f"{a}: {rb[a]:.4g} -> {ra[a]:.4g}" for a in AXES) + ".",
                  f"- Accepted on the {ev['decided_by']} = {ev['z_decisive']:.2f} (one-sided p = {ev['p_value']:.2g}; "
                  f"threshold {Z_MIN if ev['decided_by'] == 'block z' else Z_RUN:.2f})"
                  + (f", not on the block z = {ev['z']:.2f} (p = {ev['p_value_block']:.2g}), which is below {Z_MIN}"
                     if ev["decided_by"] != "block z" else "")
                  + f"; gain {ev['oos_gain']:.1%} (share of the out-of-sample mean square removed on the output it "
                    f"helps most); BIC_eff change {ev['delta_bic_eff']:.1f}; {_drop_one(ev)}."]
            if ev.get("within_run"):
                w = ev["within_run"]
                L.append(f"- Constant within its runs (what a per-run term claims): not rejected; neighbouring blocks "
                         f"of a run against random order, serial z = {w['serial_z']:.2f} (p = {w['serial_p']:.2g}); an "
                         f"offset per piece of each run (up to {w['pieces']}) gains {w['gain_pieces']:.1%} out of "
                         f"sample (rejected only with z >= {Z_DISTINCT} and a gain >= {MIN_GAIN:.0%}).")
            if fd.get("location"):
                loc = fd["location"]
                L.append(f"- Located at {loc['field']} = {loc['value']:.6g} {loc['unit']}"
                         + (f" in run {loc['run']}" if "run" in loc else "")
                         + f" (95 % interval {loc['interval95'][0]:.6g} to {loc['interval95'][1]:.6g} {loc['unit']}).")
            if ev.get("form", {}).get("tried"):
                L.append("- Form: " + ", ".join(f"{t['form']} against the first-order form: block z = {t['z_vs_first']:.1f}"
                                                 for t in ev["form"]["tried"]) + f"; kept {ev['form']['chosen']}.")
            if fd.get("furthest_run_not_stated"):
                L.append(f"- Not stated: {fd['furthest_run_not_stated']}.")
            if fd.get("applies_to"):
                L.append(f"- Applies to {fd['applies_to']}.")
            if fd.get("not_identified"):
                L.append("- Not identified by these data (dropped, |value| < "
                         f"{T_IDENT} se): " + ", ".join(f"{p['parameter']} = {p['value']:.3g} +- {p['se']:.2g}"
                                                         for p in fd["not_identified"]) + ".")
            if fd["indistinguishable_from"]:
                alts = ", ".join(f"{al['effect']} ({al['where']}, gain {al['oos_gain']:.1%})"
                                 for al in fd["indistinguishable_from"])
                L.append(f"- **Indistinguishable** on these data from: {alts} (gain: share of the out-of-sample "
                         f"mean square removed on the output it helps most).")
            L.append("")
    near = res.closest_not_accepted
    if near:
        L += ["## Closest candidate not accepted", "",
              f"{near['effect']} ({near['where']}): {near['decided_by']} = {near['z_decisive']:.2f} (one-sided p = "
              f"{near['p_value']:.2g}), gain {near['oos_gain']:.1%} (share of the out-of-sample mean square removed on "
              f"the output it helps most), BIC_eff change {near['delta_bic_eff']:.1f}; not accepted because "
              f"{near['not_accepted_because']}.", ""]
    if res.unexplained:
        L += ["## Unexplained structure", "",
              "Nothing in the catalogue explains the following; it is described, not named:", ""]
        for u in res.unexplained:
            where = f"{u['axis']} calibrated output" if u.get("frame") == "output" else f"{u['channel']} sensor channel"
            L.append(f"- {where}: {u['description']}.")
        L.append("")
    if res.rejected:
        L += ["## Rejected", ""] + [f"- {r['effect']} ({r['where']}): {r['reason']}." for r in res.rejected] + [""]
    if res.extra_terms:
        L += ["## Using the extended model", "", "Add to the `[physics]` table of a `bayesmag run` config (there each "
              "output gets its own coefficients, an output-frame approximation of the sensor-frame terms):", "",
              "```toml", "[physics]", "extra_terms = " + _toml_list(res.extra_terms), "```", ""]
        local = sorted({fd["effect"] for fd in res.findings if fd.get("applies_to")})
        if local:
            L += [f"{' and '.join(local)} describe{'s' if len(local) == 1 else ''} the training sessions only (their "
                  f"runs and times): keep {'it' if len(local) == 1 else 'them'} in a model refitted to these runs, but "
                  f"{'it' if len(local) == 1 else 'they'} cannot be applied to a new session.", ""]
    if res.notes:
        L += ["## Notes", ""] + [f"- {n}" for n in res.notes] + [""]
    if figures:
        L += ["## Figures", ""] + [f"![{Path(p).stem}]({Path(p).name})" for p in figures] + [""]
    return "\n".join(L)


def _no_extension(near: dict | None) -> str:
    """The sentence on the search when nothing was accepted: the closest candidate and by how much it missed."""
    if not near:
        return "No catalogue extension improves the thermo-affine model out of sample."
    miss = near.get("short_by", {})
    parts = []
    if "z" in miss:
        parts.append(f"its {near['decided_by']} = {near['z_decisive']:.2f} is {miss['z']:.2f} short of "
                     f"{Z_RUN if near['decided_by'].startswith('run') else Z_MIN:.2f}")
    if "gain" in miss:
        parts.append(f"its gain {near['oos_gain']:.2%} is {miss['gain']:.2%} short of {MIN_GAIN:.0%}")
    if "delta_bic_eff" in miss:
        parts.append(f"its BIC_eff change {near['delta_bic_eff']:.1f} is {miss['delta_bic_eff']:.1f} short of "
                     f"-{DBIC_MIN:g}")
    return (f"No catalogue extension passed the acceptance tests; the closest, {near['effect']} ({near['where']}), "
            f"missed: " + ("; ".join(parts) if parts else near.get("not_accepted_because", "")) + ".")


def _drop_one(ev: dict) -> str:
    """The drop-one statistic that decides (as the acceptance: block z, or the run contrast z_run for a
    run-localised term whose block z falls short), with the block z beside it when it is not the one."""
    by = ev.get("drop_one_decided_by", "block z")
    if by == "block z":
        return f"drop-one given the other findings: block z = {ev['drop_one_z']:.2f} (threshold {Z_MIN})"
    return (f"drop-one given the other findings: {by} = {ev['drop_one_z_decisive']:.2f} (threshold {Z_RUN:.2f}; "
            f"its block z {ev['drop_one_z']:.2f} does not decide)")


def _toml_list(specs: list) -> str:
    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return repr(float(v)) if isinstance(v, float) else str(v)
    items = ["{" + ", ".join(f"{k} = {val(v)}" for k, v in s.items()) + "}" for s in specs]
    return "[" + ", ".join(items) + "]"
