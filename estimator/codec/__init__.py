"""CAN codec: DBC load, frames <-> typed records, per-injection validity (cantools, numpy)."""
