"""bayesmag core layer."""
