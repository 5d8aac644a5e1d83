"""Learning an injector's own model: the electrical calibration of its structural parameters, the
self-calibration that collects and judges its windows, the per-injector lifecycle, and the lab
calibration of eq. 25."""
