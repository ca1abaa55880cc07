"""The contract of each stage family, written once: what a new stage implements.

A stage is a class registered by name in its family's registry (:mod:`scanreg.stages.registry`), with a typed
``Params`` dataclass (one docstring per field, units included) and a constructor that takes the params (and, for
a coarse stage, the helper stages it ``uses``). The methods below are all the pipeline calls; every stage takes
values and returns values, and keeps nothing of one run for the next.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Optional, Protocol, runtime_checkable

if TYPE_CHECKING:
    import numpy as np

    from scanreg.geometry import Cloud, Geometry, Mesh
    from scanreg.stages.coarse.base import Described
    from scanreg.types import CoarseResult, IcpResult, Problem, Repaired, RunContext, ScanSet, ViewEdge


@runtime_checkable
class DataProvider(Protocol):
    """``data=NAME``: loads the registration problem."""

    def require(self) -> None:
        """Raise a :class:`~scanreg.errors.ConfigError` when a setting the provider needs is missing (checked
        before a run starts). A provider may also have ``preflight()`` (optional; see
        :class:`~scanreg.stages.data.base.Provider`): what can be checked without reading a scan, run by a sweep
        for every job before the first starts; without it the sweep runs ``require``."""

    def load(self, ctx: RunContext) -> Problem | ScanSet:
        """The source, the target, and what is known about them (ground truth, landmarks); or, from a scan-set
        provider, every scan of one object."""


@runtime_checkable
class RepairStage(Protocol):
    """``repair=NAME``: repairs a mesh and reports what changed."""

    def applies_to(self, role: str) -> bool:
        """Whether the mesh of ``role`` (``source`` or ``target``) is repaired."""

    def repair(self, mesh: Mesh, ctx: RunContext) -> Repaired:
        """The repaired mesh and its audit."""


@runtime_checkable
class Sampler(Protocol):
    """``sampler=NAME``: turns a mesh into points (clouds pass through, optionally thinned)."""

    def sample(self, geometry: Geometry, ctx: RunContext) -> Cloud:
        """The points (with normals when the mesh has them) of a mesh or a cloud."""


@runtime_checkable
class Salience(Protocol):
    """``salience=NAME``: a keypoint detector."""

    def keypoints(self, cloud: Cloud, spacing: float) -> np.ndarray:
        """Sorted indices of the keypoints among ``cloud``'s points; ``spacing``: the cloud's sampling spacing
        (input units), the unit of distances given in spacings."""


@runtime_checkable
class Descriptor(Protocol):
    """``descriptor=NAME``: a local shape descriptor."""

    def compute(self, cloud: Cloud, keypoints: np.ndarray, spacing: float) -> np.ndarray:
        """(K, D) descriptors of ``cloud.points[keypoints]``."""


@runtime_checkable
class Matcher(Protocol):
    """``matcher=NAME``: pairs of similar descriptors."""

    def match(self, desc_target: np.ndarray, desc_source: np.ndarray) -> np.ndarray:
        """(M, 2) int array of ``(target index, source index)``, sorted."""


@runtime_checkable
class CoarseStage(Protocol):
    """``coarse=NAME``: an initial ``T_target_source`` from any starting pose. ``uses`` names the helper
    families (``salience``, ``descriptor``, ``matcher``) its constructor takes."""

    uses: tuple[str, ...]

    def align(self, target: Cloud, source: Cloud, spacing: float, ctx: RunContext,
              landmarks: Optional[tuple[np.ndarray, np.ndarray]] = None) -> CoarseResult:
        """``spacing``: the pair's sampling spacing (input units); ``landmarks``: picked pairs ``(target, source)``
        when the problem has them. A stage may also have ``second_look(target, source, spacing, ctx, first,
        fitness) -> CoarseResult | None`` (optional; ``lo_ransac`` has one): a second estimate of a pair whose
        ``first`` estimate the fine stage refined to a pose that keeps only ``fitness`` of the source on the
        target (``icp_fitness``), or None when it makes none; the pipeline refines it too and keeps the pose
        that keeps more of the source (:func:`scanreg.runner.steps.second_look`)."""

    def describe_set(self, clouds: list[Cloud], spacing: float, ctx: RunContext) -> list[Described]:
        """Every scan of a set described once (:class:`~scanreg.stages.coarse.base.CoarseBase` describes a scan
        by its cloud; a feature-based stage computes its keypoints and descriptors here)."""

    def align_described(self, target: Described, source: Described, ctx: RunContext,
                        budget: int | None = None) -> CoarseResult:
        """One pair of a set from the scans' descriptions (``budget``: at most this many hypotheses)."""


@runtime_checkable
class FineStage(Protocol):
    """``icp=NAME``: refines a transform (ICP and its variants)."""

    def refine(self, target: Cloud, source: Cloud, T_init: np.ndarray, spacing: float, ctx: RunContext,
               target_mesh: Optional[Mesh] = None, start_is_estimate: bool = True) -> IcpResult:
        """``T_init``: the start (the coarse stage's result); ``target_mesh``: the target's triangles when it is a
        mesh (closest points on them instead of on its points); ``start_is_estimate``: False when ``T_init`` is
        the inputs' own pose rather than a coarse stage's estimate (``coarse=none``), so that the stage may search
        a wider basin."""


@runtime_checkable
class GraphStage(Protocol):
    """``graph=NAME``: the poses of many scans from their registered pairs (a pose graph)."""

    def solve(self, n: int, edges: list[ViewEdge], spacing: float, diagonal: float, anchor: int,
              ctx: RunContext) -> tuple[list[Optional[np.ndarray]], dict[str, float]]:
        """Each scan's ``T_world_scan`` (the anchor's frame is the world; None: not placed) from the edges,
        whose ``accepted`` and ``reason`` it sets; and its numbers (``graph_*``)."""


@runtime_checkable
class SurfaceStage(Protocol):
    """``surface=NAME``: one surface from the merged points of a scan set."""

    def reconstruct(self, points: Cloud, from_meshes: bool, spacing: float, ctx: RunContext) -> Optional[Mesh]:
        """A mesh of the surface the points (with normals) sample, or None when the stage makes none
        (``from_meshes``: the scans were meshes)."""


PROTOCOLS: dict[str, type] = {
    "data": DataProvider, "repair": RepairStage, "sampler": Sampler, "salience": Salience,
    "descriptor": Descriptor, "matcher": Matcher, "coarse": CoarseStage, "icp": FineStage, "graph": GraphStage,
    "surface": SurfaceStage,
}
"""Each stage family's contract; a class registered in a family must have its methods."""
