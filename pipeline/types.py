"""The run's vocabulary: the values that the pipeline's steps and stages take and return.

- :class:`RunContext`: read-only facts of one run (seed, run folder, verbosity) that stages may use besides
  their own parameters;
- :class:`Problem`: what a data provider loads (source, target, ground truth, landmarks);
- :class:`Repaired`, :class:`CoarseResult`, :class:`IcpResult`: what a repair, a coarse and a fine stage return;
- :class:`PreparedScan`: one scan loaded, repaired, sampled and measured (``scanreg.runner.prepare_scan``);
- :class:`PairResult`: one pair registered (``scanreg.runner.register_pair``);
- :class:`Result`: one run, as the CLI writes it and the Python API returns it.

Distances in parameters are in input units or in sampling spacings (:class:`Distances`, :func:`to_abs`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, Optional

import numpy as np

from scanreg.errors import ConfigError
from scanreg.geometry import Cloud, Geometry, Mesh


class Distances(str, Enum):
    """How a stage reads its distance parameters."""

    spacing = "spacing"
    """Multiples of the run's sampling spacing (median nearest-neighbour distance, see ``estimate_spacing``)."""
    absolute = "absolute"
    """Input units (the units of the mesh or cloud files: mm for dental scans, m for the Stanford bunny)."""


def to_abs(value: float | None, unit: Distances, spacing: float) -> float | None:
    """A distance parameter in input units (None stays None)."""
    if value is None:
        return None
    return float(value) * spacing if unit == Distances.spacing else float(value)


@dataclass(frozen=True)
class RunContext:
    """What a stage may use besides its own parameters: facts of the run, fixed before it starts."""

    seed: int = 0
    """The run's seed (``seed`` of the config)."""
    run_dir: Optional[Path] = None
    """The folder the run writes into (None: nothing is written)."""
    verbose: bool = False
    """Full tracebacks and the stages' own chatter."""
    in_sweep: bool = False
    """The run is a job of a Hydra multirun sweep (``repair.cache: auto`` caches repaired meshes only then)."""
    cores: Optional[int] = None
    """The cores a stage may keep busy at once (None: every core of the machine). Steps that run several stages
    at once give each its share, so that none starts helper processes the cores are already busy for; results
    never depend on it."""

    def __post_init__(self):
        object.__setattr__(self, "seed", checked_seed(self.seed))

    def rng(self, salt: int = 0) -> np.random.Generator:
        """A generator seeded by the run's seed and ``salt`` (each use its own salt)."""
        return np.random.default_rng([self.seed, salt])


def checked_seed(value: Any) -> int:
    """``value`` as a run's seed: an integer >= 0 (NumPy's generators take no other), or its digits as a string
    (``seed='7'``, an environment variable); else a ConfigError."""
    if isinstance(value, str) and value.strip().isdigit():
        value = int(value.strip())
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise ConfigError(f"seed must be an integer >= 0, got {value!r}")
    return int(value)


@dataclass
class Problem:
    """A registration problem as a data provider loads it: find ``T_target_source``."""

    source: Geometry
    target: Geometry
    T_gt: Optional[np.ndarray] = None
    """Ground-truth ``T_target_source`` when known."""
    landmarks: Optional[tuple[np.ndarray, np.ndarray]] = None
    """Picked pairs ``(target points (K, 3), source points (K, 3))``."""
    info: dict = field(default_factory=dict)
    """Numbers about the case, logged as metrics (e.g. ``gt_overlap``)."""
    target_labels: Optional[np.ndarray] = None
    """A part number per face of a target mesh (e.g. tooth numbers), for per-part deviation statistics."""
    label_name: str = "part"
    """What a part is called in metric names (``tooth``)."""
    target_generated: bool = False
    """The target was made by the provider (not read from a file as it is): the run writes it beside the result."""


@dataclass
class Repaired:
    """What a repair stage returns: the mesh to go on with, and its audit (unprefixed metric names:
    ``before_faces``, ``after_faces``, ``removed_area_share``, ...; empty when nothing was audited)."""

    mesh: Mesh
    metrics: dict[str, float] = field(default_factory=dict)


@dataclass
class CoarseTrace:
    """What a coarse stage compared, for the evaluation (``scanreg.eval.metrics.field_metrics``): each only
    when the stage has it. Positions are in the clouds' own frames."""

    keypoints_target: Optional[np.ndarray] = None
    keypoints_source: Optional[np.ndarray] = None
    matches_target: Optional[np.ndarray] = None
    """The descriptor matches' target points (before RANSAC)."""
    matches_source: Optional[np.ndarray] = None
    ransac_inliers: Optional[np.ndarray] = None
    """Mask over the matches: accepted by RANSAC."""
    spacing: Optional[float] = None
    """The spacing of the clouds the keypoints were detected on (the coarse stage may thin the clouds)."""


@dataclass
class CoarseResult:
    """What a coarse stage returns."""

    T_target_source: np.ndarray
    metrics: dict[str, float] = field(default_factory=dict)
    """``coarse_*`` numbers (keypoints, matches, inliers, ...)."""
    trace: Optional[CoarseTrace] = None
    histories: dict[str, list[float]] = field(default_factory=dict)
    """Per-item series logged as MLflow step metrics (e.g. ``landmark_residual``)."""
    estimated: bool = True
    """False when the pose is the inputs' own, not an estimate (``coarse=none``): the fine stage may then
    search a wider basin (``icp.basin``)."""


@dataclass
class Correspondences:
    """Pairs at a pose: aligned source points and their closest target points, in the target frame."""

    source: np.ndarray
    """The source points moved by the pose (N, 3)."""
    target: np.ndarray
    """Their closest target points (N, 3)."""
    normals: Optional[np.ndarray]
    """The target normals there (N, 3), or None when the target has none."""
    distances: np.ndarray
    """``|source - target|`` (N,), input units."""


@dataclass
class IcpResult:
    """What a fine stage returns."""

    T_target_source: np.ndarray
    iterations: int
    """Number of transform updates made."""
    rms_history: list[float]
    """RMS distance of the pairs used at each iterate, before its update; the last entry at the final pose."""
    converged: bool
    final_distances: Optional[np.ndarray] = None
    """Closest-point distances of the source at the final pose, bounded by ``max_correspondence_distance`` (inf
    beyond)."""
    metrics: dict[str, float] = field(default_factory=dict)
    """``icp_*`` numbers (fitness, inlier RMS, acceptance test, pair limits)."""
    final_limit: Optional[float] = None
    """The pair limit at the last iterate (input units; None: unlimited)."""
    final_pairs: Optional[Correspondences] = None
    """The pairs the stage keeps at the pose it returns (its distance, normal and trim rejections at the final
    pair limit, on the target it searches): what the pose covariance is computed from."""


@dataclass
class PreparedScan:
    """One scan ready to register: loaded, repaired, sampled, measured (``scanreg.runner.prepare_scan``)."""

    name: str
    """What the scan is called in messages and metric names (``source``, ``target``, a file name)."""
    geometry: Geometry
    """As loaded (the input's pose and units)."""
    surface: Geometry
    """The surface registration and evaluation see: the repaired mesh (its scanned side) or the cloud."""
    cloud: Cloud
    """The sampled points (with normals when the surface has them)."""
    spacing: float
    """Median nearest-neighbour distance of ``cloud`` (input units)."""
    repair: dict[str, float] = field(default_factory=dict)
    """The repair's audit (unprefixed names; empty without one)."""
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds per step: ``repair``, ``sample``."""

    @property
    def mesh(self) -> Optional[Mesh]:
        """The repaired mesh, or None for a cloud."""
        return self.surface if isinstance(self.surface, Mesh) else None


@dataclass
class PairResult:
    """One pair registered (``scanreg.runner.register_pair``): the coarse and the fine stage's results."""

    coarse: CoarseResult
    icp: IcpResult
    spacing: float
    """The pair's sampling spacing: the larger of the two scans' (input units)."""
    diagonal: float
    """The target cloud's bounding-box diagonal (input units)."""
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds per step: ``coarse``, ``icp``."""

    @property
    def T_target_source(self) -> np.ndarray:
        return self.icp.T_target_source

    @property
    def metrics(self) -> dict[str, float]:
        """The coarse and fine stages' numbers, as one run logs them."""
        icp = self.icp
        return {**self.coarse.metrics, "icp_iterations": icp.iterations, "icp_converged": float(icp.converged),
                "icp_rms": icp.rms_history[-1], **icp.metrics}

    @property
    def histories(self) -> dict[str, list[float]]:
        return {**self.coarse.histories, "icp_rms": list(self.icp.rms_history)}


@dataclass
class Result:
    """What one run produced: the transform, every metric, the per-iteration series and the files written."""

    T_target_source: Optional[np.ndarray]
    """4x4 transform mapping source points into the target frame (input units)."""
    metrics: dict[str, float] = field(default_factory=dict)
    """Every metric the run logs (the names of ``result.json`` and MLflow: ``rms``, ``rotation_error_deg``, ...)."""
    histories: dict[str, list[float]] = field(default_factory=dict)
    """Per-iteration series, e.g. ``icp_rms`` (MLflow step metric ``icp_rms_step``)."""
    run_dir: Optional[Path] = None
    """The folder holding the artifacts."""
    artifacts: list[Path] = field(default_factory=list)
    """Files written: ``result.json``, ``T_target_source.txt``, ``aligned_source.ply``, deviation maps, ..."""
    run_id: Optional[str] = None
    """The MLflow run id when the run was tracked."""
    children: list[tuple[str, dict[str, float]]] = field(default_factory=list)
    """The runs inside this one, each a name and its metrics: a scan set's registered pairs (MLflow: child runs)."""
    scanset: Any = None
    """A scan set's registration (``scanreg.runner.scanset.SetRegistration``: poses, edges, merged points, surface)."""

    @property
    def success(self) -> Optional[bool]:
        """With ground truth: rotation and translation errors under the ``evaluate.success_*`` limits."""
        s = self.metrics.get("success")
        return None if s is None else bool(s)

    def to_json(self) -> dict[str, Any]:
        """``result.json``'s content: the transform and every metric."""
        T = self.T_target_source
        return {"T_target_source": None if T is None else T.tolist(), **self.metrics}


@dataclass
class Reconstruction:
    """What a scan set's run produced (:func:`scanreg.reconstruct`)."""

    poses: dict[str, np.ndarray]
    """Each placed scan's name -> its 4x4 ``T_world_scan`` (the world: the first scan's frame, in sorted order)."""
    merged: Optional[Any]
    """The placed scans' points in the world frame, voxel-merged (a ``Cloud`` with normals and
    ``extra['scan']``, each point's scan index)."""
    mesh: Optional[Any]
    """The surface reconstructed from them and repaired (a ``Mesh``), or None (``surface=none``, clouds)."""
    metrics: dict[str, float] = field(default_factory=dict)
    """The set's metrics, as ``result.json`` and MLflow hold them."""
    unplaced: dict[str, str] = field(default_factory=dict)
    """The scans left out of the model, each with why."""
    groups: list[list[str]] = field(default_factory=list)
    """The scans connected by verified pairs, the model's group first."""
    run_dir: Optional[Path] = None
    artifacts: list[Path] = field(default_factory=list)
    """``poses.json``, ``merged.ply``, ``reconstruction.ply``, ``view3d.html``, ``result.json``, ..."""
    run_id: Optional[str] = None


@dataclass
class ScanSet:
    """Many scans of one object, to register into one model (what a scan-set data provider loads)."""

    scans: list[Geometry]
    names: list[str]
    """Each scan's name (its file name), in the order of ``scans`` (sorted: the first is the world frame)."""
    poses_gt: Optional[list[Optional[np.ndarray]]] = None
    """The true ``T_world_scan`` of each scan in any common world frame, when known (None for a scan without)."""
    order: str = "unordered"
    """What the order of the scans says: ``sequential`` (neighbours in the list overlap), ``turntable`` (and the
    last overlaps the first), ``unordered``."""
    info: dict = field(default_factory=dict)
    """Numbers about the set, logged as metrics."""
    reference: Optional[Geometry] = None
    """A reference surface in the world frame of ``poses_gt``, to measure the reconstruction against."""


@dataclass
class ViewEdge:
    """One pair of a scan set registered and verified: ``T_i_j`` maps scan ``j`` into scan ``i``'s frame."""

    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray
    """6x6 information of the error ``(w, t)`` about ``centre`` (the inverse of the pose covariance)."""
    centre: np.ndarray
    """The centre of the pairs the fine stage kept (scan ``i``'s frame)."""
    fitness: float
    """Share of scan ``j``'s points within the inlier distance of scan ``i`` (and the other way, the smaller)."""
    inlier_rms: float
    """RMS distance of those points, in sampling spacings."""
    normal_agreement: float
    """Share of those points whose normals agree with the target's (cosine above 0.5)."""
    accepted: bool = False
    reason: str = ""
    """Why the edge was rejected (empty when accepted)."""
    metrics: dict[str, float] = field(default_factory=dict)
    """The pair's registration metrics (as a pair run logs them)."""
