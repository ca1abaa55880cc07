"""``repair=none``: meshes pass through unchanged and unaudited."""

from __future__ import annotations

from dataclasses import dataclass

from scanreg.geometry import Mesh
from scanreg.stages.registry import REPAIR
from scanreg.types import Repaired, RunContext


@REPAIR.register("none")
class NoRepair:
    """Leave meshes as they are (no audit)."""

    @dataclass
    class Params:
        pass

    def __init__(self, params: Params):
        self.p = params

    def applies_to(self, role: str) -> bool:
        """False: no scan has anything done to it (so none is handed to a process of its own for it)."""
        return False

    def repair(self, mesh: Mesh, ctx: RunContext) -> Repaired:
        return Repaired(mesh)
