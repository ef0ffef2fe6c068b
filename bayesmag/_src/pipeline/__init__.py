"""bayesmag pipeline layer."""
