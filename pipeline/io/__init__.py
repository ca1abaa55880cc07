"""Reading and writing meshes, point clouds, transforms, Stanford ``.conf`` poses and landmark pairs (see
:mod:`scanreg.io.readers`); paths with ``pkg:`` and ``shared:`` names (:mod:`scanreg.io.paths`)."""

from scanreg.io.clouds import detect_columns
from scanreg.io.paths import expand_path, resolve_path, shared_data_dir
from scanreg.io.readers import (CLOUD_EXTS, MESH_EXTS, read_geometry, read_input, read_landmarks, read_mesh,
                                read_stanford_conf, read_transform)
from scanreg.io.writers import write_atomic, write_ply, write_transform

__all__ = ["CLOUD_EXTS", "MESH_EXTS", "detect_columns", "expand_path", "read_geometry", "read_input",
           "read_landmarks", "read_mesh", "read_stanford_conf", "read_transform", "resolve_path",
           "shared_data_dir", "write_ply", "write_transform"]
