"""Identification: cost functions, line searches, calibration, recursive estimator (numpy/scipy only)."""
