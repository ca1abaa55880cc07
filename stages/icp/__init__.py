"""Fine registration (``icp=NAME``): ICP and its variants, all on one shared machinery
(:mod:`scanreg.stages.icp.base`)."""

from scanreg.stages.icp import gicp, open3d, plane, point  # noqa: F401  (registers the stages)
