"""Simulated injector node and the bench that scores the estimator against its truth."""

import estimator as _estimator  # noqa: F401  (first: it limits BLAS to one thread before numpy loads)
