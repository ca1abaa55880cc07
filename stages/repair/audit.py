"""The audited repair shared by every backend: :class:`GuardParams` (each backend's ``Params`` extend it) and
:class:`AuditedRepair`, whose :meth:`~AuditedRepair.repair` runs the backend, audits the mesh before and after
and applies the guard.

Mesh repair backends, and the audit that reports what a repair changed and guards against destroyed models.

Every backend's ``Params`` include the guard (:class:`GuardParams`). After a repair the audit compares the input
and the output:
- topology and size before and after (:func:`audit_mesh`);
- the one-sided Hausdorff distances input -> output (how far the input surface is from the repaired one, large
  where parts were removed) and output -> input (large where holes were filled);
- the share of the input surface that is no longer there.

The run fails with one clear line when the repair removed more than ``max_removed_area`` of the surface, or
moved it by more than ``max_hausdorff`` of the diagonal. This is MeshFix's known failure of reducing a dental
bridge to one tooth, or of eating an open scan whose outer border was capped. Open scans are made watertight
without that loss by ``open_border=shell`` (:func:`close_as_shell`).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace

import numpy as np

from scanreg.config import Context
from scanreg.errors import StageError
from scanreg.geometry import Mesh, bbox_diagonal, row_norms
from scanreg.shell import close_as_shell
from scanreg.topology import audit_mesh, boundary_loop_sizes, surface_distances


@dataclass
class GuardParams:
    apply_to: str = "both"
    """Which input meshes are repaired: ``source``, ``target`` or ``both`` (a CT surface made of separate
    teeth must not lose all but its largest component, so the dental case repairs the source only)."""
    check_only: bool = False
    """Audit what the repair would do (the before/after table and the guard) but go on with the unrepaired
    mesh; a guard violation is then reported, not fatal."""
    max_removed_area: float = 0.10
    """Fail when more than this share of the input surface is gone after the repair (see
    ``removed_tolerance``)."""
    max_hausdorff: float = 0.01
    """Fail when a point of the input surface lies farther than this share of the bounding-box diagonal
    from the repaired surface (one-sided Hausdorff distance, input -> output)."""
    max_hausdorff_edges: float = 2.0
    """The Hausdorff limit is at least this many median edge lengths of the input: on a coarse mesh one
    triangle can span more than ``max_hausdorff`` of the diagonal, and dropping a sliver at a ragged border
    must not fail the run (0: the diagonal share alone)."""
    removed_tolerance: float = 0.002
    """An input surface point counts as removed when it lies farther than this share of the bounding-box
    diagonal from the repaired surface."""
    audit_samples: int = 20000
    """Points sampled on each surface to measure the Hausdorff distances and the removed share."""
    open_border: str = "cap"
    """What becomes of an open scan's outer border, the longest boundary loop (with ``max_hole_edges`` set:
    every loop longer than that). ``cap``: filled like any hole (MeshFix's way; right for closed models with
    holes, but on an open scan the cap cuts through the surface and the guard fails the run). ``open``: left
    open. ``shell``: the scan is closed as a thin shell, its surface plus an offset copy ``shell_thickness``
    behind it, joined along the border: watertight without changing or removing any scanned surface; samplers
    and the evaluation use the scanned side only."""
    shell_thickness: float = 0.001
    """``open_border=shell``: distance of the back side behind the surface, as a share of the bounding-box
    diagonal (less where the space behind the surface is narrower, see :func:`close_as_shell`)."""

    def check(self):
        if self.apply_to not in ("source", "target", "both"):
            raise ValueError(f"apply_to must be source, target or both, got '{self.apply_to}'")
        if self.open_border not in ("cap", "open", "shell"):
            raise ValueError(f"open_border must be cap, open or shell, got '{self.open_border}'")
        if not self.shell_thickness > 0:
            raise ValueError(f"shell_thickness must be > 0, got {self.shell_thickness}")



def repair_with_audit(stage, mesh: Mesh, ctx: Context, prefix: str) -> tuple[Mesh, dict[str, float]]:
    """Run ``stage`` on ``mesh``, audit before/after under ``prefix`` (``repair_``/``target_repair_``), apply
    the guard. Returns the mesh to go on with and the metrics."""
    p: GuardParams = stage.p
    before = audit_mesh(mesh)
    if p.open_border != "cap" and getattr(p, "fill_holes", getattr(p, "close_holes", False)):
        sizes = boundary_loop_sizes(mesh)
        if len(sizes) and not p.max_hole_edges:  # keep loops over half the longest (the outer border) open
            stage = copy.copy(stage)
            stage.p = replace(p, max_hole_edges=int(sizes.max()) // 2)
    out = stage.run(mesh, ctx)
    if p.open_border == "shell":
        out = close_as_shell(out, p.shell_thickness * bbox_diagonal(out.vertices))
    after = audit_mesh(out)
    m = {f"{prefix}before_{k}": v for k, v in before.items()}
    m.update({f"{prefix}after_{k}": v for k, v in after.items()})
    diag = bbox_diagonal(mesh.vertices)
    d_in = surface_distances(mesh, out, p.audit_samples, ctx.seed)
    d_out = surface_distances(out, mesh, p.audit_samples, ctx.seed + 1)
    removed = float((d_in > p.removed_tolerance * diag).mean())
    m.update({
        f"{prefix}hausdorff_max": float(d_in.max()),
        f"{prefix}hausdorff_mean": float(d_in.mean()),
        f"{prefix}hausdorff_max_rel": float(d_in.max() / diag),
        f"{prefix}hausdorff_mean_rel": float(d_in.mean() / diag),
        f"{prefix}hausdorff_added_max": float(d_out.max()),
        f"{prefix}hausdorff_added_max_rel": float(d_out.max() / diag),
        f"{prefix}removed_area_share": removed,
    })
    problems = []
    if removed > p.max_removed_area:
        problems.append(f"removed {removed:.1%} of the surface (limit repair.max_removed_area={p.max_removed_area:g})")
    v, f = mesh.vertices, mesh.faces
    edge = float(np.median(row_norms(v[f[:, [1, 2, 0]]] - v[f]))) if len(f) else 0.0
    limit = max(p.max_hausdorff * diag, p.max_hausdorff_edges * edge)
    m[f"{prefix}hausdorff_limit_rel"] = float(limit / diag)
    if d_in.max() > limit:
        problems.append(f"moved it by up to {d_in.max() / diag:.2%} of the diagonal (limit "
                        f"{limit / diag:.2%}: repair.max_hausdorff={p.max_hausdorff:g}, or "
                        f"repair.max_hausdorff_edges={p.max_hausdorff_edges:g} median edges if more)")
    m[f"{prefix}guard_ok"] = float(not problems)
    if problems:
        msg = (f"repair={stage.name}: {mesh.source}: the repair {' and '.join(problems)}; it would destroy part "
               "of the model. An open scan's outer border capped by hole filling does this: close the scan as a "
               "thin shell with repair.open_border=shell, keep the border open with repair.open_border=open, or "
               "inspect with repair.check_only=true")
        if not p.check_only:
            raise StageError(msg, metrics=m)
        print(f"warning: {msg}")
    return (mesh if p.check_only else out), m




class AuditedRepair:
    """Base of the repair backends: ``run(mesh, ctx)`` is the backend itself, :meth:`repair` the audited run."""

    p: GuardParams

    def repair(self, mesh: Mesh, ctx: Context, prefix: str) -> tuple[Mesh, dict[str, float]]:
        """The backend on ``mesh`` with the audit and the guard (:func:`repair_with_audit`)."""
        return repair_with_audit(self, mesh, ctx, prefix)
