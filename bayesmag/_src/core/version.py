"""The package version, written once (``bayesmag.__version__``, saved calibrations, run markers, ``--version``)."""

__version__ = "0.1.0"
