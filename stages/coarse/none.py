"""``coarse=none``: fine registration starts from the inputs' own pose."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanreg.geometry import Cloud
from scanreg.stages.coarse.base import CoarseBase
from scanreg.stages.registry import COARSE
from scanreg.types import CoarseResult, RunContext


@COARSE.register("none")
class NoCoarse(CoarseBase):
    """Start fine registration from the identity (the inputs are assumed roughly aligned)."""

    @dataclass
    class Params:
        pass


    def align(self, target: Cloud, source: Cloud, spacing: float, ctx: RunContext,
              landmarks=None) -> CoarseResult:
        return CoarseResult(np.eye(4), estimated=False)
