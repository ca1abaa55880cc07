"""scanreg from Python: register a scan given as NumPy arrays and check the result against the known pose.

Run it with ``python examples/register_arrays.py`` (the tests run it too). It samples pymeshfix's Stanford bunny
twice (two independent samplings, as two scans of one object would be), moves one by a known rigid transform,
registers it back with the default pipeline, then runs one stage on its own.
"""

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

import scanreg
from scanreg.types import RunContext
from scanreg.geometry import Cloud, barycentric_sample, bbox_centre, make_T, transform_errors
from scanreg.io import read_mesh

mesh = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")  # about 60 units across
target = barycentric_sample(mesh, 20000, np.random.default_rng(0))[0]
source_in_target = barycentric_sample(mesh, 20000, np.random.default_rng(1))[0]

T_true = make_T(Rotation.from_euler("xyz", [35, -60, 110], degrees=True).as_matrix(), np.array([8.0, -3.0, 5.0]))
# source points in their own frame: T_true maps them back onto the target
source = (source_in_target - T_true[:3, 3]) @ T_true[:3, :3]

res = scanreg.register(source, target, gt=T_true)
# measured where the source is (its box centre), as the run's translation_error is: at the frame's origin a
# rotation error of a scan far from it would read as a translation
rot, trans = transform_errors(res.T_target_source, T_true, at=bbox_centre(source))
print(f"rotation error {rot:.4f} deg, translation error {trans:.4f} (input units), "
      f"rms {res.metrics['rms']:.4f}, ICP iterations {len(res.histories['icp_rms']) - 1}")
print("artifacts:", ", ".join(Path(p).name for p in res.artifacts))
assert rot < 0.5 and res.success, "registration failed"

# one stage on its own: built from the registry by name, its Params validated
icp = scanreg.build_stage("icp", "horn", tau=1e-9)
ctx = RunContext(seed=0)  # the run's facts a stage may use (no run_dir: nothing is written)
refined = icp.refine(Cloud(target), Cloud(source), res.T_target_source, float(res.metrics["spacing"]), ctx)
print(f"horn ICP from that pose: {refined.iterations} iterations, "
      f"rotation error {transform_errors(refined.T_target_source, T_true)[0]:.4f} deg")
