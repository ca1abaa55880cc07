"""Reproduction: MeshLab's self-intersection selection depends on the process's history (found 2026-11-23), and
the check that scanreg's repair no longer does (its exact test, scanreg.intersect, replaced MeshLab's).

Seen as: first_contact run twice at the same commit, bun315:top3 pose 1 gave 1.04 deg in one sweep and 0.25 deg
in the other (the source's repair left 70 581 vs 70 652 faces); the same job run alone gave 1.04 deg every time.
MeshLab's ``compute_selection_by_self_intersections_per_face`` on the very same arrays of a posed top3 scan
returned 70 faces in a fresh process and 139 after two repairs in the same process (fresh MeshSets agree at each
moment). Ruled out: the rounding mode, flush-to-zero/denormals-are-zero, a left-over selection, the OpenMP thread
count, malloc reuse (MALLOC_PERTURB_, a fixed MALLOC_MMAP_THRESHOLD_), Python's GC, the x87 control word and
MXCSR's control bits. MeshLab's test is also numerically fragile on this scan: the same faces scaled by 1000,
shifted by 5 or divided by 1000 gave 39, 56 and 26 faces (cnr-isti-vclab/meshlab#50); the exact test finds none in
any of these frames. Suspected mechanism (not confirmed): vcg's ``TestFaceFaceIntersection`` reads the segment
parameters ``a, b`` of ``IntersectionSegmentTriangle`` on a path that may leave them unset (stack contents).

This script repairs the posed scan four times in one process (fresh copies, memory allocated in between) and
prints, per round, MeshLab's count on the same input (it may change) and the exact count and the repaired mesh's
hash (they must not). Every round tests afresh: since #32 the exact test keeps no process-wide memo of recent
meshes (it reuses an earlier outcome only when given one, ``previous``), so there is nothing to clear between
rounds (this script called ``forget_recent()`` before), and MeshFix's sessions run in forked children
(:func:`scanreg.process.run_isolated`) while the audit runs in this process.

Run: ``.venv/bin/python experiments/benchmarks/si_state_repro.py`` (about 1 min; needs ../shared/data). Exit 0
when the repair is the same every round.
"""

from __future__ import annotations

import copy
import hashlib
import pathlib
import sys

import numpy as np


def main() -> int:
    import pymeshlab
    from scipy.spatial.transform import Rotation

    from scanreg.api import build_stage
    from scanreg.geometry import transform_geometry
    from scanreg.io import read_mesh, shared_data_dir
    from scanreg.mesh.intersect import self_intersecting_faces
    from scanreg.types import RunContext

    path = shared_data_dir() / "stanford_bunny" / "top3.ply"
    if not path.exists():
        print(f"skipped: {path} is absent (../shared/data)")
        return 0
    m0 = read_mesh(path)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, 1.2, -0.7]).as_matrix()
    T[:3, 3] = [0.01, 0.02, -0.03]
    posed = transform_geometry(T, copy.deepcopy(m0))
    v, f = np.ascontiguousarray(posed.vertices), np.ascontiguousarray(posed.faces, dtype=np.int32)
    stage = build_stage("repair", "meshfix")
    junk, counts, exact, hashes = [], [], [], []
    for k in range(4):
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(v, f))
        ms.compute_selection_by_self_intersections_per_face()
        counts.append(int(ms.current_mesh().selected_face_number()))
        exact.append(int(self_intersecting_faces(v, f).sum()))
        ctx = RunContext(seed=0, run_dir=pathlib.Path("."))
        out = stage.repair(transform_geometry(T, copy.deepcopy(m0)), ctx).mesh
        hashes.append(hashlib.sha1(out.vertices.tobytes() + out.faces.tobytes()).hexdigest()[:10])
        print(f"round {k}: the same input's self-intersecting faces: MeshLab {counts[-1]}, exact {exact[-1]}; "
              f"repaired mesh {len(out.faces)} faces, {hashes[-1]}", flush=True)
        junk.append([np.random.rand(1000 * (k + 1)) for _ in range(200)])
    print("MeshLab's count " + ("stayed the same" if len(set(counts)) == 1 else "CHANGED") + " in this process")
    same = len(set(exact)) == 1 and len(set(hashes)) == 1
    print("the exact count and the repair: " + ("the same every round" if same else "NOT deterministic"))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
