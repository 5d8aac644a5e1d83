"""Pure numerical model: parameters, PSA + valve dynamics, simulators (numpy/scipy only)."""
