"""bayesmag app layer."""
