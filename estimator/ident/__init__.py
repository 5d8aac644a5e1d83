"""Identification (numpy/scipy/numba only), in rooms by concern: :mod:`~estimator.ident.fit` (one
injection), :mod:`~estimator.ident.tracking` (the recursive estimator), :mod:`~estimator.ident.learning`
(an injector's own model); the schemas they share (configuration, measurement, estimate, status,
coordinates, simulators) stay here."""
