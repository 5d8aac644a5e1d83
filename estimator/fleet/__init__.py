"""Fleet analysis on Dask: many captures and traces, one command, one machine or a cluster.

The top layer: it imports the service layer's pipeline (:mod:`estimator.pipeline.estimates`) and
dask.distributed; nothing below imports it.
"""
