"""Stage implementations, one module per stage family (``pipeline.registry.load_all`` imports them all)."""

MODULES = ("data", "repair", "sampler", "salience", "descriptor", "matcher", "coarse", "icp", "dental")
