"""Mesh repair backends, and the audit that reports what a repair changed and guards against destroyed models.

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

from scanreg.stages.repair import meshfix, meshlab, none  # noqa: F401  (registers the backends)
from scanreg.stages.repair.audit import AuditedRepair, GuardParams, repair_with_audit  # noqa: F401
