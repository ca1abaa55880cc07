"""experiments/benchmarks/end_to_end.py without running the benchmark: every case group composes to the command a
user runs (issue #34's raw-mesh cases with no repair override), the raw pairs are the >= 40 % overlap ones, the
table's repair share and ratios are the stated medians, and a section rewritten in place leaves the rest."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, SHARED
from scanreg.app.config import compose
from scanreg.stages.registry import DATA, load_all
from scanreg.types import RunContext

SCRIPT = ROOT / "experiments" / "benchmarks" / "end_to_end.py"
spec = importlib.util.spec_from_file_location("end_to_end", SCRIPT)
e2e = importlib.util.module_from_spec(spec)
spec.loader.exec_module(e2e)


def test_case_builders_cover_every_group_and_compose():
    cases = e2e.build_cases(e2e.GROUPS)
    by = {g: [c for c in cases if c["group"] == g] for g in e2e.GROUPS}
    assert [len(by[g]) for g in e2e.GROUPS] == [12, 6, 2, 8, 6]
    assert [c["pair"] for c in by["bunny_raw"]] == list(e2e.RAW_PAIRS) and len(set(e2e.RAW_PAIRS)) == 8
    assert len({c["seed"] for c in by["bunny_raw"]}) == 8  # each pair under its own random pose
    assert len(e2e.build_cases(["bunny_raw"], all_pairs=True)) == 80  # experiment=first_contact's runs
    assert e2e.build_cases(["closed_defects", "dental"]) == by["dental"] + by["closed_defects"]
    for g in e2e.GROUPS:
        cfg = compose([*e2e.case_overrides(by[g][0]), "tracking=none"])
        # only bunny (the point-cloud comparison of issue #16) turns the repair off
        assert cfg.repair.name == ("none" if g == "bunny" else "meshfix"), g
        assert cfg.tracking.name == "none"
    cfg = compose([*e2e.case_overrides(by["closed_defects"][1]), "tracking=none"])
    assert cfg.data.name == "files" and cfg.data.source == cfg.data.target == e2e.CLOSED_MESH
    assert cfg.data.pose_seed == 1 and cfg.data.max_angle_deg == 180
    with pytest.raises(ValueError, match="unknown case group"):
        e2e.case_overrides({"group": "nope", "seed": 0})


def test_closed_defects_case_loads_with_its_truth():
    load_all()
    case = {"group": "closed_defects", "seed": 3}
    cfg = compose([*e2e.case_overrides(case), "tracking=none"])
    p = DATA.build(cfg.data).load(RunContext(seed=0, run_dir=ROOT))
    assert p.source.faces.shape == p.target.faces.shape  # both meshes, the same file
    # the truth maps the posed source back onto the target, vertex for vertex
    moved = p.source.vertices @ p.T_gt[:3, :3].T + p.T_gt[:3, 3]
    np.testing.assert_allclose(moved, p.target.vertices, atol=1e-9)
    assert not np.allclose(p.T_gt, np.eye(4))


def test_raw_pairs_have_at_least_40_percent_overlap():
    if not (SHARED / "stanford_bunny").is_dir():
        pytest.skip(f"real scan data not available: {SHARED}")
    load_all()
    overlaps = []
    for pair in e2e.RAW_PAIRS:
        cfg = compose(["data=stanford", f"data.pair={pair}", "tracking=none"])
        overlaps.append(DATA.build(cfg.data).load(RunContext(seed=0, run_dir=ROOT)).info["gt_overlap"])
    assert min(overlaps) >= 0.4 and max(overlaps) > 0.85, overlaps
    assert overlaps == sorted(overlaps, reverse=True)  # PAIRS is in decreasing overlap, RAW_PAIRS a stride of it


def _row(group, method, total_reg, repair=0.0, process=1.0, total=None):
    r = {"case": {"group": group, "seed": 0}, "method": method, "error": "", "success": True, "process_s": process,
         "rotation_error_deg": 0.1, "time_load_s": 0.1, "time_repair_s": repair, "time_sample_s": 0.1,
         "time_coarse_s": 0.1, "time_icp_s": 0.1, "time_registration_s": total_reg}
    if total is not None:
        r["time_total_s"] = total
    return r


def test_case_table_repair_share_and_ratios():
    rows = [_row("bunny_raw", "scanreg", 3.0, repair=1.0, total=4.0, process=6.0),
            _row("bunny_raw", "scanreg", 5.0, repair=3.0, total=6.0, process=8.0),
            _row("bunny_raw", "open3d", 1.0, process=2.0), _row("bunny_raw", "open3d", 3.0, process=4.0),
            _row("bunny", "scanreg", 1.0, total=1.0)]
    lines = e2e.case_table(rows, e2e.RAW_GROUPS)
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    assert len(lines) == 4  # header, rule, the two bunny_raw rows; bunny is not in this table
    cells = {ln.split("|")[2].strip(): dict(zip(head, (c.strip() for c in ln.strip("|").split("|"))))
             for ln in lines[2:]}
    sr, o3 = cells["scanreg"], cells["open3d"]
    assert sr["repair share"].startswith("0.38 ")  # median of 1/4 and 3/6
    assert sr["ratio registration"] == "2.00" and sr["ratio total"] == "2.50" and sr["ratio process"] == "2.33"
    assert o3["repair share"] == "-" and o3["ratio total"] == "1" and o3["success"] == "2/2"


def test_a_section_is_replaced_in_place(tmp_path):
    md = tmp_path / "e2e.md"
    md.write_text("# title\n\nOther table (x):\n\n| a |\n|---|\n| 1 |\n\nBenchmark wall time 1 s.\n")
    intro = f"{e2e.RAW_HEADING}\n\nmeasured (commit 1):"
    e2e.replace_table(md, intro, ["| b |", "|---|", "| 2 |"], "raw")
    e2e.replace_table(md, intro.replace("commit 1", "commit 2"), ["| b |", "|---|", "| 3 |"], "raw")
    text = md.read_text()
    assert text.count(e2e.RAW_HEADING) == 1 and "commit 1" not in text and "| 2 |" not in text
    assert "measured (commit 2):\n\n| b |\n|---|\n| 3 |\n" in text
    assert "Other table (x):\n\n| a |\n|---|\n| 1 |\n" in text and "Benchmark wall time 1 s." in text
