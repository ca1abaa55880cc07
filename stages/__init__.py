"""Stage implementations, one module per stage family. They register themselves by name when imported;
``scanreg.registry.load_all`` imports every module listed under the ``scanreg.stages`` entry-point group
(pyproject.toml), so that the framework never imports a stage module by name and other packages can add stages."""
