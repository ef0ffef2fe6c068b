"""Files of a discovery (application layer): findings.json, report.md and the figures, written atomically."""

from __future__ import annotations

from pathlib import Path

from bayesmag._src.pipeline.discover.result import DiscoveryResult, jsonable, report_markdown

__all__ = ["write_discovery"]


def write_discovery(res: DiscoveryResult, out: str | Path) -> Path:
    """Write findings.json, report.md and (with ``res.options.figures``) the figures of ``res`` to ``out``
    atomically (a temporary sibling folder renamed at the end); returns ``out``.

    Example:
      >>> res = bayesmag.discover(data)                         # doctest: +SKIP
      >>> bayesmag.write_discovery(res, "runs/my_discovery")    # doctest: +SKIP
    """
    from bayesmag._src.app.outdir import staging_dir
    from bayesmag._src.core.jsonio import write_json

    out = Path(out)
    with staging_dir(out, kind="discover") as tmp:
        figures = []
        if res.options.figures:
            from bayesmag._src.app import discover_plots
            figures = discover_plots.discovery_figures(tmp, res)
        write_json(tmp / "findings.json", jsonable(res.to_json()))
        (tmp / "report.md").write_text(report_markdown(res, figures))
    return out
