"""Piezo injector estimator: identify N_u and L_h from amplifier current and voltage."""

__version__ = "0.3.0"
