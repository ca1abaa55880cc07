"""Mesh repair backends, and the audit that reports what a repair changed and guards against destroyed models.

Every backend's ``Params`` include the guard (:class:`GuardParams`): parts below ``min_component_share`` of the
largest part's area are removed on purpose (specks) and reported, the rest kept; ``open_border=auto`` keeps a
one-sided scan's outer border open and caps a closed model's holes; the audit compares the kept input parts with
the output, and the run fails with one line naming the parameter to change when the repair removed more than
``max_removed_area`` of the kept surface or moved its 99 % quantile by more than ``max_displacement_edges``
median edge lengths (see :mod:`scanreg.stages.repair.audit`).
"""

from scanreg.stages.repair import meshfix, meshlab, none  # noqa: F401  (registers the backends)
from scanreg.stages.repair.audit import AuditedRepair, GuardParams, repair_with_audit  # noqa: F401
