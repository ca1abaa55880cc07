"""Coarse (global) registration (``coarse=NAME``): an initial ``T_target_source`` from any starting pose."""

from scanreg.stages.coarse import landmarks, lo_ransac, none, open3d  # noqa: F401  (registers the stages)
