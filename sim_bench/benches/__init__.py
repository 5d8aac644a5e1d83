"""The benches that score the estimator against the simulated hardware's truth: each prints a table,
writes JSON and exits 1 on a miss of its own targets (:mod:`sim_bench.benches.targets`)."""
