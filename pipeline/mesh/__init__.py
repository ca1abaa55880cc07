"""The mesh kernel of the repair: topology and statistics, the exact self-intersection test, sliver collapse,
surface distances, and closing an open scan as a thin shell. Pure functions of arrays (and of meshes, whose
measurements are remembered on them); no forks, threads or process state."""
