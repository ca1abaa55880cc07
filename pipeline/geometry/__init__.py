"""The geometry core: containers (:class:`Mesh`, :class:`Cloud`), rigid transforms, surface sampling, voxel
grids and neighbour searches. Pure functions of arrays; nothing here imports a stage, the runner or the app.

The names below are re-exported from the submodules, so ``from scanreg.geometry import Mesh, apply_T`` works.
"""

from scanreg.geometry.arrays import col_max, col_min, cross3, row_norms, rows_all, rows_any
from scanreg.geometry.containers import (Cloud, Geometry, Mesh, bbox_centre, bbox_diagonal, points_of, random_subset,
                                         submesh, validate_mesh, validate_points)
from scanreg.geometry.neighbours import (ClosestPoints, estimate_normals, estimate_spacing, far_offset, neighbourhoods,
                                         orient_normals, to_o3d, to_o3d_mesh)
from scanreg.geometry.surface import (area_weighted_draws, barycentric_sample, face_normals, points_on_faces,
                                      triangle_areas_normals, vertex_normals)
from scanreg.geometry.transforms import (apply_T, horn_quaternion, invert_T, kabsch_batch, kabsch_svd, make_T,
                                         half_turns, principal_axes, principal_box_diagonal, random_pose,
                                         rigid_points_normals, rotate_normals,
                                         rotation_angle_deg, rotation_from_cross_covariance, transform_errors,
                                         transform_geometry)
from scanreg.geometry.voxels import (LOCALITY_SPAN, in_cells_around, locality_ordered, morton_order, sparse_voxel_mask,
                                     voxel_cells, voxel_count, voxel_groups, voxel_occupancy, voxel_representatives)

__all__ = [
    "LOCALITY_SPAN", "ClosestPoints", "Cloud", "Geometry", "Mesh", "apply_T", "area_weighted_draws",
    "barycentric_sample", "bbox_centre", "bbox_diagonal", "col_max", "col_min", "cross3", "estimate_normals",
    "estimate_spacing",
    "face_normals", "far_offset", "horn_quaternion", "in_cells_around", "invert_T", "kabsch_batch", "kabsch_svd",
    "locality_ordered", "make_T",
    "morton_order", "neighbourhoods", "orient_normals", "points_of", "points_on_faces", "principal_axes", "half_turns",
    "principal_box_diagonal", "random_pose",
    "random_subset", "rigid_points_normals", "rotate_normals", "rotation_angle_deg", "rotation_from_cross_covariance",
    "row_norms", "rows_all", "rows_any",
    "sparse_voxel_mask", "submesh", "to_o3d", "to_o3d_mesh", "transform_errors", "transform_geometry",
    "triangle_areas_normals", "validate_mesh", "validate_points", "vertex_normals", "voxel_cells", "voxel_groups",
    "voxel_count", "voxel_occupancy", "voxel_representatives",
]
