"""Progress bars only where someone watches them: a terminal or a Jupyter kernel, never a log file or a pipe."""

from __future__ import annotations

import sys

__all__ = ["interactive_output"]


def interactive_output(stream=None) -> bool:
    """Whether ``stream`` (default ``sys.stderr``, where the bars are drawn) is watched by a person.

    True for a terminal (``isatty``) or inside a Jupyter kernel (tqdm draws widgets there); False for a
    file, a pipe or captured output, where a bar's carriage returns only fill the log.

    Example:
        >>> import io
        >>> interactive_output(io.StringIO())
        False
    """
    stream = sys.stderr if stream is None else stream
    try:
        if stream.isatty():
            return True
    except (AttributeError, ValueError):        # no isatty, or a closed stream
        pass
    ipython = sys.modules.get("IPython")
    shell = ipython.get_ipython() if ipython is not None and hasattr(ipython, "get_ipython") else None
    return type(shell).__name__ == "ZMQInteractiveShell"
