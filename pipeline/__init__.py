"""scanreg: repair, sample and register 3D scans (Moroz & Shvandt 2019), config-driven and tracked.

The Python API (see :mod:`scanreg.api`)::

    import scanreg
    res = scanreg.register(source, target)        # paths, (N, 3)/(N, 6) arrays or Open3D geometries
    res.T_target_source, res.metrics, res.histories, res.artifacts
    rec = scanreg.reconstruct("scans/")           # many scans of one object into one model
    rec.poses, rec.merged, rec.mesh, rec.metrics
    cfg = scanreg.compose(["icp=gicp"])           # a run config with overrides
    stage = scanreg.build_stage("icp", "horn", tau=1e-6)

The layers, each importing only itself and the layers below (``tests/test_layers.py`` enforces it):

- ``scanreg.app`` and ``scanreg.api``: the command, the Hydra application, tracking, reports;
- ``scanreg.runner``: the steps of a run (``prepare_scan``, ``register_pair``, ``evaluate_pair``);
- ``scanreg.stages``: the stage families and their registries (``scanreg.stages.*``);
- ``scanreg.eval``: checks, metrics, pose uncertainty, deviation maps, the 3D view;
- ``scanreg.io``, ``scanreg.mesh``, ``scanreg.geometry``: readers and writers, the repair's mesh kernel, the
  geometry core; ``scanreg.types``, ``scanreg.errors``, ``scanreg.process`` beneath them all.
"""

__all__ = ["Reconstruction", "Result", "build_stage", "compose", "reconstruct", "register", "run_config"]


def __getattr__(name: str):
    # lazy: importing a core module (scanreg.geometry) must not import the runner, Hydra or MLflow
    if name in __all__:
        from scanreg import api

        return getattr(api, name)
    raise AttributeError(f"module 'scanreg' has no attribute {name!r}")


def __dir__() -> list[str]:
    # the API's names for dir() and tab completion, though they load lazily
    return sorted({*globals(), *__all__})
