"""scanreg: repair, sample and register 3D scans (Moroz & Shvandt 2019), config-driven and tracked.

The Python API (see :mod:`scanreg.api`)::

    import scanreg
    res = scanreg.register(source, target)        # paths, (N, 3)/(N, 6) arrays or Open3D geometries
    res.T_target_source, res.metrics, res.histories, res.artifacts
    cfg = scanreg.compose(["icp=gicp"])           # a run config with overrides
    stage = scanreg.build_stage("icp", "horn", tau=1e-6)

Layers, each importing only itself and the layers below (``tests/test_layers.py`` enforces it):
the app (``app``, ``api``, ``report``, ``tracking``) > the runner (``runner``, ``deviation``) > the stages
(``scanreg.stages``) > the geometry core (``registry``, ``config``, ``errors``, ``geometry``, ``io``, ``metrics``,
``closest``, ``topology``, ``shell``).
"""

from scanreg import _o3d_lazy

_o3d_lazy.install()  # Open3D's plotly/dash viewer imported on first use, not by every scanreg process

__all__ = ["Result", "build_stage", "compose", "register"]


def __getattr__(name: str):
    # lazy: importing a core module (scanreg.geometry) must not import the runner, Hydra or MLflow
    if name in __all__:
        from scanreg import api

        return getattr(api, name)
    raise AttributeError(f"module 'scanreg' has no attribute {name!r}")
