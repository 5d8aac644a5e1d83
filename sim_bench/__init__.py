"""The simulated injector node and the benches that score the estimator against its truth, in two
rooms: :mod:`sim_bench.hardware` (plant, amplifiers, parts and lots, node, hub) and
:mod:`sim_bench.benches` (each bench, its targets and the published figures)."""
