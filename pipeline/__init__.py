"""scanreg framework: registries, configuration, I/O, runner, tracking and reports."""
