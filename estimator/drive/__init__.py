"""Drive compensation: the amplifier's standard drive (:mod:`.standard`), the target every valve is
driven to (:mod:`.target`) and the per-injector correction of that drive (:mod:`.correction`).

Pure: numpy and the model and identification layers; no clocks, files or bus (a current table is read
by the pipeline and handed in as arrays).
"""
