"""Fixed-seed reference runs: record what the pipeline computes, then check that a change keeps it bit for bit.

    python experiments/benchmarks/reference_runs.py --record   # writes reference_runs.json
    python experiments/benchmarks/reference_runs.py --check    # runs again and compares

Each case is one ``scanreg`` command line (tracking off) whose ``result.json`` is kept: the transform and every
metric. ``--check`` reports, per case, whether ``T_target_source`` is identical bit for bit and which metrics
changed (timings excluded). Cases that need ``../shared/data`` are skipped when it is absent. A refactor must keep
every transform identical; the suite's ``tests/test_reference_runs.py`` checks a subset to a tight tolerance.

Bit for bit holds on one machine. On another CPU the cases that go through Open3D's ray casting (Embree, which
picks its float32 kernels by instruction set: AVX2 or AVX-512) may differ in the last digits, and an ICP that stops
on a threshold may then stop one iteration apart (:data:`CPU_DEPENDENT`). To check a change on such a machine,
record a baseline of the unchanged code there first and compare with it:

    python experiments/benchmarks/reference_runs.py --record --reference /tmp/here.json
    (change the code)
    python experiments/benchmarks/reference_runs.py --check --reference /tmp/here.json
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
REFERENCE = HERE / "reference_runs.json"
SHARED = ROOT.parent / "shared" / "data"

CASES: dict[str, list[str]] = {
    # the demo as ./run demo runs it
    "demo": ["data=synthetic"],
    # first contact: two raw Stanford range scans as files, no overrides (MeshFix repair, open borders)
    "bunny_raw_pair": ["data.source=shared:stanford_bunny/bun045.ply", "data.target=shared:stanford_bunny/bun000.ply"],
    # the Stanford pair under a random pose, no repair, every coarse/descriptor/salience variant
    "stanford": ["data=stanford", "repair=none"],
    "stanford_h3p_cn_l3": ["data=stanford", "repair=none", "descriptor=histogram3p", "salience=cn_l3"],
    "stanford_cp_min_ratio_uniform": ["data=stanford", "repair=none", "salience=cp_min_ratio", "coarse.sampling=uniform"],
    "stanford_fpfh_ransac": ["data=stanford", "repair=none", "coarse=open3d_fpfh_ransac", "icp=open3d"],
    "stanford_fgr": ["data=stanford", "repair=none", "coarse=open3d_fgr"],
    # ICP alone from a small pose, every variant
    "icp_only_horn": ["data=stanford", "repair=none", "data.pre_align=true", "data.max_angle_deg=5",
                      "data.max_translation=0.01", "data.rotate_about=centroid", "coarse=none", "icp=horn"],
    "icp_only_point_to_plane": ["data=stanford", "repair=none", "data.pre_align=true", "data.max_angle_deg=5",
                                "data.max_translation=0.01", "data.rotate_about=centroid", "coarse=none"],
    "icp_only_gicp": ["data=stanford", "repair=none", "data.pre_align=true", "data.max_angle_deg=5",
                      "data.max_translation=0.01", "data.rotate_about=centroid", "coarse=none", "icp=gicp"],
    "icp_only_anderson": ["data=stanford", "repair=none", "data.pre_align=true", "data.max_angle_deg=5",
                          "data.max_translation=0.01", "data.rotate_about=centroid", "coarse=none", "icp=anderson"],
    # the 3DMatch fragment pair
    "pairs_3dmatch": ["data=pairs_3dmatch"],
    "pairs_3dmatch_perturbed": ["data=pairs_3dmatch", "data.add_noise=0.002", "data.add_outliers=0.2", "data.crop=0.8"],
    # the dental case: MeshFix on the cast, landmarks, ICP on the CT's triangles, deviation map
    "dental": ["experiment=dental"],
    # samplers and the MeshLab backend on the demo mesh
    "demo_meshlab_poisson": ["data=synthetic", "repair=meshlab", "sampler=poisson_disk"],
    "demo_vertices": ["data=synthetic", "sampler=vertices", "seed=3"],
    "demo_open3d_uniform": ["data=synthetic", "sampler=open3d_uniform", "repair=none"],
}
CPU_DEPENDENT: dict[str, tuple[float, float]] = {
    # the cast-scan-like source is made by casting rays onto the CT's crowns, and ICP pairs with the CT's
    # triangles, both through Open3D's ray casting (Embree's float32 kernels, chosen by the CPU). Measured on
    # 2026-11-26 between the machine that recorded it and an AVX-512 one: the source's area 3711.19636211 against
    # 3711.19637070 mm^2; ICP stopped after 18 iterations instead of 26; the transforms 4.6e-5 deg apart, their
    # largest entry difference 5.6e-5 mm (3.7e-6 of the largest translation entry); rotation error 0.017667
    # against 0.017656 deg.
    "dental": (1e-5, 1.5e-4),
}
"""Cases whose result depends on the CPU's instruction set, and what tests/test_reference_runs.py allows there:
the largest difference of a transform entry, relative to the largest translation entry, and of the rotation
error in degrees (about 3x the differences measured between two machines)."""

NEEDS_SHARED = {k for k, v in CASES.items() if any("stanford" in a or "3dmatch" in a or "dental" in a or
                                                 "shared:" in a for a in v)}
TIMINGS = ("time_", "_time_s", "backend_time", "audit_time")


def run_case(name: str, overrides: list[str], folder: Path) -> dict:
    out = folder / name
    cmd = [sys.executable, "-m", "scanreg.app", *overrides, "tracking=none", f"hydra.run.dir={out}"]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=folder)
    if r.returncode != 0:
        return {"error": (r.stderr.strip().splitlines() or ["?"])[-1]}
    return json.loads((out / "result.json").read_text())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--record", action="store_true", help="write reference_runs.json")
    ap.add_argument("--check", action="store_true", help="compare with reference_runs.json")
    ap.add_argument("--reference", type=Path, default=REFERENCE,
                    help="the reference file to write or compare with (default: reference_runs.json)")
    ap.add_argument("cases", nargs="*", help="only these cases")
    a = ap.parse_args()
    names = a.cases or list(CASES)
    have_shared = SHARED.is_dir()
    ref = json.loads(a.reference.read_text()) if a.reference.exists() else {}
    results, failed = {}, 0
    with tempfile.TemporaryDirectory(prefix="scanreg-ref-") as tmp:
        for name in names:
            if name in NEEDS_SHARED and not have_shared:
                print(f"{name}: skipped (../shared/data absent)")
                continue
            res = run_case(name, CASES[name], Path(tmp))
            results[name] = res
            if not a.check:
                print(f"{name}: {'error: ' + res['error'] if 'error' in res else 'recorded'}")
                continue
            old = ref.get(name)
            if old is None:
                print(f"{name}: no reference")
                continue
            same_T = res.get("T_target_source") == old.get("T_target_source") and "error" not in res
            changed = []
            for k in sorted(set(old) | set(res)):
                if k == "T_target_source" or any(t in k for t in TIMINGS):
                    continue
                x, y = old.get(k), res.get(k)
                if x == y or (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)):
                    continue
                changed.append(f"{k}: {x} -> {y}")
            failed += not same_T
            print(f"{name}: transform {'identical' if same_T else 'CHANGED'}; {len(changed)} metric(s) changed")
            for c in changed[:20]:
                print(f"    {c}")
    if a.record:
        a.reference.write_text(json.dumps({**ref, **results}, indent=1, allow_nan=True) + "\n")
        print(f"wrote {a.reference}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
