"""What every coarse stage shares: the default way to register many scans (each pair from its clouds), which a
stage that describes each scan once (``lo_ransac``) replaces."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from scanreg.geometry import Cloud
from scanreg.types import CoarseResult, RunContext


@dataclass
class Described:
    """A scan as a coarse stage sees it, made once for every pair of a set it takes part in."""

    cloud: Cloud
    spacing: float
    """The spacing distances in spacings refer to (input units); one for the whole set."""
    keypoints: Optional[np.ndarray] = None
    descriptors: Optional[np.ndarray] = None
    fallback: Optional["Described"] = None
    """The same cloud described with other keypoints, made when a pair first needs it (``lo_ransac``'s uniform
    keypoints when its configured ones fail)."""


class CoarseBase:
    """Base of the coarse stages: keeps the params; scans of a set are described by their clouds alone and each
    pair registered by :meth:`align`."""

    uses: tuple[str, ...] = ()

    def __init__(self, params):
        self.p = params

    def describe_set(self, clouds: list[Cloud], spacing: float, ctx: RunContext) -> list[Described]:
        """Every scan of a set described once (``spacing``: the set's sampling spacing)."""
        return [Described(c, spacing) for c in clouds]

    def align_described(self, target: Described, source: Described, ctx: RunContext,
                        budget: int | None = None) -> CoarseResult:
        """One pair of a set (``budget``: at most this many hypotheses, for a stage that draws them)."""
        return self.align(target.cloud, source.cloud, max(target.spacing, source.spacing), ctx)
