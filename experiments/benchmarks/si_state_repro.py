"""Reproduction: MeshLab's self-intersection selection depends on the process's history (found 2026-11-23).

Seen as: first_contact run twice at the same commit, bun315:top3 pose 1 gave 1.04 deg in one sweep and 0.25 deg
in the other (the source's repair left 70 581 vs 70 652 faces); the same job run alone gives 1.04 deg every time.
The repair of a posed top3 scan, repeated in one process (fresh copies, memory allocated in between), is the same
twice, then differs from the third time on: MeshLab's ``compute_selection_by_self_intersections_per_face`` on the
very same input returns 70 faces in rounds 1-2 and 139 from round 3 on, also on fresh MeshSets built from the
same arrays at that moment. Ruled out: the rounding mode (``fegetround`` unchanged), flush-to-zero/denormals-are-
zero on the main thread, a selection left over (none before the call), OpenMP thread count (1 and 2 both give 70 in
a process that has run no repair), a race (three calls in a row agree). So some state that an earlier repair
leaves behind changes MeshLab's test. Narrowed down (wrapping the audit's steps and counting the same input after
each): the count flips during the second repair's ``collapse_folds`` (scanreg.topology), between its two
``fold_counts`` calls (each leaves the count as it found it), i.e. while ``near`` selects the neighbourhood with
SciPy k-d tree queries and ``submesh`` cuts it out; none of pymeshfix's clean / fill / degeneracy removal,
Open3D's raycasting, MeshLab's sliver collapse or clean-up filters, or MeshLab's tests on small submeshes,
repeated alone in a fresh process, flips it; nor do MALLOC_PERTURB_ or a fixed MALLOC_MMAP_THRESHOLD_ remove it,
nor disabling Python's GC. The x87 control word and MXCSR's control bits stay the same (only MXCSR's sticky
denormal flag gets set, earlier than the flip; clearing the flags before each test changes nothing).
The test itself is numerically fragile on this scan: the same faces scaled by 1000, shifted by 5 or divided by
1000 give 39, 56 and 26 self-intersecting faces (MeshLab's known false positives, cnr-isti-vclab/meshlab#50). Single runs are deterministic (a fresh process each); sweep jobs share
worker processes and may not be.

Run: ``.venv/bin/python experiments/benchmarks/si_state_repro.py`` (about 1.5 min; needs ../shared/data).
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
    from scanreg.config import Context, shared_data_dir
    from scanreg.geometry import transform_geometry
    from scanreg.io import read_mesh

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
    junk, counts, hashes = [], [], []
    for k in range(4):
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(v, f))
        ms.compute_selection_by_self_intersections_per_face()
        counts.append(int(ms.current_mesh().selected_face_number()))
        out, _ = stage.repair(transform_geometry(T, copy.deepcopy(m0)),
                              Context(seed=0, run_dir=pathlib.Path(".")), "repair_")
        hashes.append(hashlib.sha1(out.vertices.tobytes() + out.faces.tobytes()).hexdigest()[:10])
        print(f"round {k}: self-intersecting faces of the same input {counts[-1]}; repaired mesh "
              f"{len(out.faces)} faces, {hashes[-1]}", flush=True)
        junk.append([np.random.rand(1000 * (k + 1)) for _ in range(200)])
    same = len(set(counts)) == 1 and len(set(hashes)) == 1
    print("deterministic in this process" if same else "NOT deterministic: the same input gave different results")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
