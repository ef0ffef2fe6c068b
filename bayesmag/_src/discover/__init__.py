"""Discovery of missing physics, one concept per module.

* :mod:`.options` -- :class:`DiscoverOptions` and the declared thresholds;
* :mod:`.frame` -- the sensor-frame joint model (catalogue terms as reading distortions);
* :mod:`.search` -- catalogue search, out-of-sample scoring, forward selection;
* :mod:`.checks` -- drop-one refits, identified coefficients, plausible parameters;
* :mod:`.diagnostics` -- located and unexplained structure, noise floor, time scales;
* :mod:`.result` -- :class:`DiscoveryResult`, findings.json and report.md;
* :mod:`.pipeline` -- :func:`discover`, the stages in order;
* :mod:`.app` -- the ``bayesmag discover`` command and its config table.
"""

from .diagnostics import locate
from .options import DiscoverOptions
from .pipeline import discover
from .result import DiscoveryResult, report_markdown

__all__ = ["discover", "DiscoverOptions", "DiscoveryResult", "locate", "report_markdown", "main",
           "build_parser", "load_discover_config"]


def main(argv=None) -> int:
    """``bayesmag discover`` (see :mod:`.app`)."""
    from .app import main as _main
    return _main(argv)


def load_discover_config(path, overrides=()):
    """(Config, DiscoverOptions) from a TOML file (see :mod:`.app`)."""
    from .app import load_discover_config as _load
    return _load(path, overrides)


def build_parser():
    """The ``bayesmag discover`` argument parser (see :mod:`.app`)."""
    from .app import build_parser as _build
    return _build()
