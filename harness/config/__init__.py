"""The run configuration: the pydantic model of a YAML config, and its sections (target,
timing thresholds, corner cases)."""
