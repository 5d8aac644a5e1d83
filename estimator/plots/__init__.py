"""PNG figures: an identification's cost surface and fits, a bus capture over time (needs matplotlib)."""
