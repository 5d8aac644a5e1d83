"""The CAN contract (``injector.dbc``), shipped inside the package as ``estimator.dbc``."""
