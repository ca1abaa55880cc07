"""``repair=none``: meshes pass through unchanged and unaudited."""

from __future__ import annotations

from dataclasses import dataclass

from scanreg.config import Context
from scanreg.geometry import Mesh
from scanreg.registry import REPAIR


@REPAIR.register("none")
class NoRepair:
    """Leave meshes as they are (no audit)."""

    @dataclass
    class Params:
        pass

    def __init__(self, params: Params):
        self.p = params

    def run(self, mesh: Mesh, ctx: Context) -> Mesh:
        return mesh

    def repair(self, mesh: Mesh, ctx: Context, prefix: str, sweep: bool = False) -> tuple[Mesh, dict[str, float]]:
        return mesh, {}
