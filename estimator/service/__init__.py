"""Service: bus, pipeline, daemon, sd_notify (the only layer that imports python-can)."""
