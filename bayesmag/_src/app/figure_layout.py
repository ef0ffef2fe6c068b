"""Fixed figure margins in inches: the layout :meth:`~matplotlib.figure.Figure.tight_layout` would find for
this project's figures, without its extra pass over every tick label (a third of a job's figure time); and
``plt``, pyplot on the Agg backend imported at the first figure, not when a plot module is imported (the
command's process builds the figure tasks without matplotlib; the figure process imported it at its start)."""

from __future__ import annotations

__all__ = ["fixed_layout", "plt"]


class _Pyplot:
    """``matplotlib.pyplot`` (Agg backend), imported on first attribute access."""

    def __getattr__(self, name: str):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as pyplot

        return getattr(pyplot, name)


plt = _Pyplot()


def fixed_layout(fig, *, left: float = 1.0, right: float = 0.2, bottom: float = 0.6, top: float = 0.7,
                 wspace: float = 0.95, hspace: float = 0.8) -> None:
    """Place ``fig``'s subplot grid with margins and gaps given in inches (not fractions).

    ``left``/``bottom``: room for tick labels and axis labels; ``top``: the suptitle and panel titles;
    ``wspace``/``hspace``: between panels (their tick labels, axis labels and titles). The numbers fit
    labels of up to about seven characters at the default font size (what ``tight_layout`` measured on
    the job's figures: ``benchmarks/bench_figures.py --layout``).

    Example:
        >>> import matplotlib.pyplot as plt
        >>> fig, axes = plt.subplots(2, 3, figsize=(12, 6))
        >>> fixed_layout(fig)
        >>> round(fig.subplotpars.left * 12, 3)
        1.0
    """
    w, h = fig.get_size_inches()
    axes = [ax for ax in fig.axes if ax.get_subplotspec() is not None]
    nrows, ncols = axes[0].get_subplotspec().get_gridspec().get_geometry() if axes else (1, 1)
    inner_w, inner_h = w - left - right, h - bottom - top
    ax_w = (inner_w - (ncols - 1) * wspace) / ncols
    ax_h = (inner_h - (nrows - 1) * hspace) / nrows
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h,
                        wspace=wspace / ax_w if ncols > 1 else 0.2, hspace=hspace / ax_h if nrows > 1 else 0.2)
