"""Simulated injector node and the bench that scores the estimator against its truth."""

