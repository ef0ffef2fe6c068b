"""Discovery of missing physics, one concept per module (the ``bayesmag discover`` command and its config
table live in :mod:`bayesmag._src.app.discover_cli`).

* :mod:`.options` -- :class:`DiscoverOptions` and the declared thresholds;
* :mod:`.frame` -- the sensor-frame joint model (catalogue terms as reading distortions);
* :mod:`.search` -- catalogue search, out-of-sample scoring, forward selection;
* :mod:`.checks` -- drop-one refits, identified coefficients, plausible parameters;
* :mod:`.diagnostics` -- located and unexplained structure, noise floor, time scales;
* :mod:`.result` -- :class:`DiscoveryResult`, findings.json and report.md;
* :mod:`.pipeline` -- :func:`discover`, the stages in order;
"""

from bayesmag._src.pipeline.discover.diagnostics import locate
from bayesmag._src.pipeline.discover.options import DiscoverOptions
from bayesmag._src.pipeline.discover.pipeline import discover
from bayesmag._src.pipeline.discover.result import DiscoveryResult, report_markdown

__all__ = ["discover", "DiscoverOptions", "DiscoveryResult", "locate", "report_markdown"]

