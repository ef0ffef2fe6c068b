"""Catalogue of candidate physics: model extensions that discovery can name (filled by issue #5)."""

from .physics import EXTRA_TERMS  # noqa: F401
