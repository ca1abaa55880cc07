"""The run-level settings that are no stage's: how a scan set is registered and merged (the ``multiview`` block of
the config; the ``evaluate`` block is :class:`scanreg.eval.metrics.EvalParams`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional


@dataclass
class MultiviewParams:
    """How a scan set is registered and merged (the ``multiview`` block of the config)."""

    all_pairs: int = 20
    """Sets of at most this many scans register every pair; larger ones the pairs ``order`` or the global
    descriptor suggest."""
    window: int = 2
    """``order: sequential`` or ``turntable`` (larger sets): each scan is paired with the next this many."""
    neighbours: int = 5
    """``order: unordered`` (larger sets): each scan is paired with this many scans of the most similar shape
    (a histogram of the distances between its points, scaled by their spread)."""
    rescue_pairs: int = 10
    """Larger sets: a scan that the candidate pairs leave outside the largest group of joined scans is paired with
    up to this many more of that group's scans (the most similar shapes first)."""
    max_edge_ratio: Optional[float] = 8.0
    """The model (merged points and surface) leaves out a scan mesh's faces whose longest edge is more than this
    many times the edges at their corners (the lower quartile of the edge lengths at each corner, the largest of
    the three): a range scan triangulated as a grid bridges each depth jump (one ear before the other) with long
    thin faces, which merged into the model made a sheet between the bunny's ears
    (:func:`scanreg.mesh.jumps.depth_jump_faces`). At 8 the 10 Stanford scans lose 80-780 faces each, CT
    surfaces, closed and adaptive meshes none. The registration samples every face, as a pair run does. null: the
    model takes every face."""
    repair_scans: bool = False
    """Repair every scan with the configured backend before sampling it. Off: the scans are sampled as scanned
    (their holes and ragged borders do not hinder registration) and the model made from them is repaired once."""
    coarse_budget: int = 1024
    """At most this many hypotheses per pair for a coarse stage that draws them: pairs that do not overlap
    would otherwise draw the stage's full ``max_iterations``."""
    predict: bool = True
    """A pair of scans that accepted pairs already connect starts the fine stage from the pose they predict (and
    is skipped when that pose leaves them apart); off: every pair from any pose, by the coarse stage."""
    predict_min_fitness: float = 0.2
    """Only accepted pairs that overlap at least this much (share of points, 0..1) predict poses: a false pair
    that passed the verification overlaps little, and its predictions would skip the pairs that outvote it."""
    predict_max_inlier_rms: float = 1.45
    """... and whose inlier RMS is at most this many spacings (``max_inlier_rms`` accepts up to 1.6; a scan whose
    only accepted pair fits more loosely is not placed, in a set of 3 or more): the 10
    Stanford scans as bare points put ear_back 159 deg off through two false pairs that agree, at 1.57 spacings
    (the right pairs there: 0.7-1.37), whose predictions skipped the right pairs that would outvote them."""
    pair_samples: int = 5000
    """Points of a pair's source scan that the fine stage pairs with the target (spread over it; 0: all): a
    pair's pose is a start that the multi-view refinement finishes, and needs no more."""
    inlier_distance: float = 3.0
    """A pair's point is in the overlap when its closest point on the other scan lies within this many sampling
    spacings (at the registered pose)."""
    spacing_ratio: float = 1.5
    """The scans' sampling spacings, sorted, split into groups wherever one is more than this factor finer than
    the one before; each group takes its largest (scans alike: one group, the largest spacing of all). A scan
    sampled more coarsely (another resolution, another object) does not coarsen the others: a pair is
    registered, verified and refined at the larger of its two scans' spacings (what ``inlier_distance``,
    ``refine_distances`` and the stages' distances in spacings refer to there), and the merge and the surface
    take the finest of the main group's (``merge_voxel``). The 10 Stanford bunny scans lie within 1.12 of each
    other, no two neighbours in the sorted order more than 1.03 apart."""
    min_fitness: float = 0.1
    """An edge is kept only when this share (0..1) of each scan's points is in the overlap ..."""
    max_inlier_rms: float = 1.6
    """... their RMS distance is at most this many spacings (a wrong pose leaves its overlap's points spread over
    the whole inlier distance: about 1.8 spacings; a right one near the sampling noise: 1.2-1.5) ..."""
    min_normal_agreement: float = 0.8
    """... and the share of them whose normals agree with the other scan's (cosine above 0.5) is at least this
    share of what the scans' normals reach among themselves (each point's with its nearest neighbour's, the
    lower of the two scans, :meth:`~scanreg.geometry.ClosestPoints.normal_coherence`): clean scans' normals
    agree on 0.93-0.98 of the points, so about 0.75-0.78 is needed; scans with noise of 0.37 spacings agree on
    0.75-0.78 and right pairs on 0.71-0.77, which an absolute 0.8 rejected, every pair of a noisy set."""
    refine_distances: list[float] = field(default_factory=lambda: [3.0, 1.5])
    """Multi-view refinement: its pair limits, in sampling spacings, one after the other; []: no refinement."""
    refine_iterations: int = 10
    """Multi-view refinement: most Gauss-Newton steps per pair limit."""
    refine_samples: int = 5000
    """Multi-view refinement: points of each scan paired with the others (spread over it)."""
    merge_voxel: float = 1.0
    """The merged cloud keeps one point per voxel of this edge, in sampling spacings (0: every point)."""
    success_rotation_deg: float = 0.5
    """With ground truth, a scan is within tolerance when its rotation error is below this (degrees) ..."""
    success_translation: float = 0.0025
    """... and its translation error (the shift of its centroid) below this share of the model's diagonal (its
    box along its principal axes, ``model_diagonal``)."""
    false_edge_rotation_deg: float = 2.0
    """With ground truth, an accepted edge is false when its transform is off by more than this (degrees) ..."""
    false_edge_translation: float = 0.01
    """... or moves the centroid of the scan it places by more than this share of the model's diagonal."""

    def check(self):
        if self.all_pairs < 2 or self.window < 1 or self.neighbours < 1:
            raise ValueError("all_pairs must be >= 2, window and neighbours >= 1")
        shares = ("min_fitness", "min_normal_agreement", "predict_min_fitness")
        positive = ("coarse_budget", "inlier_distance", "max_inlier_rms", "predict_max_inlier_rms", "refine_iterations",
                    "refine_samples",
                    "success_rotation_deg", "success_translation", "false_edge_rotation_deg", "false_edge_translation")
        for names, ok, what in ((shares, lambda v: 0 <= v <= 1, "in [0, 1]"), (positive, lambda v: v > 0, "> 0"),
                                (("rescue_pairs", "pair_samples", "merge_voxel"), lambda v: v >= 0, ">= 0"),
                                (("spacing_ratio",), lambda v: v > 1, "> 1")):
            bad = [n for n in names if not ok(getattr(self, n))]
            if bad:
                raise ValueError(f"{' and '.join(bad)} must be {what}, got "
                                 + ", ".join(f"{n}={getattr(self, n)}" for n in bad))
        if self.max_edge_ratio is not None and not self.max_edge_ratio > 1:
            raise ValueError(f"max_edge_ratio must be > 1 or null, got {self.max_edge_ratio}")
        if not all(d > 0 for d in self.refine_distances):
            raise ValueError(f"refine_distances must be > 0 (spacings), got {list(self.refine_distances)}")
