"""Fleet analysis on Dask: many captures and traces, one command, one machine or a cluster.

The top layer, beside the daemon: it builds on the pipeline (:mod:`estimator.pipeline.estimates`)
and dask.distributed, never on the daemon's modules; nothing below imports it.
"""
