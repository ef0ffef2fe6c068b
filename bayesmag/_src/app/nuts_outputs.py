"""Files of a NUTS run (application layer: the library returns a :class:`NutsResult`, this writes it): ``nuts.nc`` (netCDF-4, all InferenceData groups), summary CSV/Markdown, figures."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bayesmag._src.pipeline.nuts import NutsResult

__all__ = ["write_nuts_outputs"]


def _write_netcdf(idata, path: Path) -> None:
    """All groups to one netCDF-4 file; pointwise groups in float32 (halves the largest arrays)."""
    path = Path(path)
    if path.exists():
        path.unlink()
    mode = "w"
    for g in idata.groups():
        ds = idata[g]
        enc = {}
        for v in ds.data_vars:
            e = {"zlib": True, "complevel": 1, "shuffle": True}
            if g in ("log_likelihood", "posterior_predictive") and ds[v].dtype == np.float64:
                e["dtype"] = "float32"
            enc[v] = e
        ds.to_netcdf(path, mode=mode, group=g, engine="h5netcdf", encoding=enc)
        mode = "a"


def _fmt(v) -> str:
    if isinstance(v, str):
        return v
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return ""
    if isinstance(v, (int, np.integer)):
        return str(v)
    a = abs(v)
    return f"{v:.4g}" if a == 0 or 1e-3 <= a < 1e5 else f"{v:.4e}"


def _markdown(res: NutsResult) -> str:
    df = res.summary
    cols = list(df.columns)
    lines = ["# NUTS cross-check of the physics posterior", ""]
    s = res.settings
    lines.append(f"{s['chains']} chains x {s['draws']} draws (warm-up {s['warmup']}, target_accept "
                 f"{s['target_accept']}, {s['chain_method']}, {s['parametrisation']} parametrisation), "
                 f"{s['likelihood']} likelihood, {s['n_rows']} rows; "
                 f"{res.seconds.get('total', float('nan')):.1f} s in total "
                 f"({res.seconds.get('sampling', float('nan')):.1f} s sampling, "
                 f"{res.seconds.get('compile', float('nan')):.1f} s compiling).")
    lines += ["", "## Verdicts", ""]
    for ax, v in res.verdicts.items():
        lines.append(f"- **{ax}**: {v}")
    if res.warnings:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in res.warnings]
    lines += ["", "## Largest correlation differences (NUTS - LM)", ""]
    for ax in res.axes:
        top = res.crosscheck[ax]["largest_corr_differences"]
        ev = res.crosscheck[ax]["whitened_eigenvalue_range"]
        items = ", ".join(f"{t['a']}-{t['b']} {t['corr_nuts']:.6f} vs {t['corr_lm']:.6f}" for t in top)
        lines.append(f"- **{ax}**: {items}; whitened covariance eigenvalues {ev[0]:.3f}-{ev[1]:.3f} (1 = LM exact)")
    lines += ["", "## Summary", "", "mean_diff_lm_sd = (mean_NUTS - theta_LM) / sd_LM; sd_ratio = sd_NUTS / sd_LM.",
              "", "| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for _, r in df.iterrows():
        cells = []
        for c in cols:
            v = r[c]
            if c == "r_hat" and isinstance(v, float) and np.isfinite(v):
                cells.append(f"{v:.4f}")
            elif c.startswith("ess_") and isinstance(v, float) and np.isfinite(v):
                cells.append(f"{v:.0f}")
            else:
                cells.append(_fmt(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_nuts_outputs(res: NutsResult, folder: str | Path, *, figures: bool = True) -> list[Path]:
    """Write ``nuts.nc``, ``nuts_summary.csv``, ``nuts_summary.md`` (and figures) into ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = [folder / "nuts.nc", folder / "nuts_summary.csv", folder / "nuts_summary.md"]
    _write_netcdf(res.idata, out[0])
    res.summary.to_csv(out[1], index=False, float_format="%.10g")
    out[2].write_text(_markdown(res))
    if figures:
        from bayesmag._src.app.nuts_plots import nuts_figures
        out += nuts_figures(folder, res)
    return out

