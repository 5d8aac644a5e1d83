"""Trace files: the CSV trace format and MDF4 (asammdf)."""
