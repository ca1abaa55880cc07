"""The application layer: the ``scanreg`` command (:mod:`~scanreg.app.cli`, the Hydra application
:mod:`~scanreg.app.main`, its start-up measures :mod:`~scanreg.app.startup`, scan files given by position
:mod:`~scanreg.app.arguments`), composing configs
(:mod:`~scanreg.app.config`), MLflow tracking (:mod:`~scanreg.app.tracking`, the sweep callback
:mod:`~scanreg.app.sweep`), reports (:mod:`~scanreg.app.report`) and ``scanreg-stages``
(:mod:`~scanreg.app.stages_cli`)."""
