"""Reports: every group of a sweep appears in every table and plot (the plotted labels and data are read back
from the matplotlib figures as they are saved)."""

import numpy as np
import pandas as pd
import pytest

from scanreg.app.report.params import ReportParams
from scanreg.app.report.tables import canonical, default_grouping, group_labels, summarize
from scanreg.app.report.write import write_report


def mlflow_like_runs(key: str, values: list[str], seeds: int = 3) -> pd.DataFrame:
    """Runs as ``mlflow.search_runs`` returns them: params are strings exactly as logged ("1.0", "20000")."""
    rows = []
    for i, v in enumerate(values):
        for s in range(seeds):
            rows.append({
                "run_id": f"r{i}{s}", "status": "FINISHED", "start_time": pd.Timestamp("2026-01-01", tz="UTC"),
                f"params.{key}": v, "params.seed": str(s), "tags.group.icp": "point_to_plane",
                "metrics.rotation_error_deg": 0.01 * (i + 1) + 0.001 * s, "metrics.translation_error": 1e-4,
                "metrics.success": 1.0, "metrics.time_total_s": 1.0 + i, "metrics.time_coarse_s": 0.5 + i,
                "metrics.time_repair_s": 0.3, "metrics.time_icp_s": 0.1 * (i + 1),
            })
    df = pd.DataFrame(rows)
    df.attrs.update(experiment="t", uri="sqlite:///x.db", parent=None, parent_tags={})
    return df


@pytest.fixture
def figures(monkeypatch):
    """Every figure saved by the report: {file name: [(tick labels, legend texts, x data of lines, bar
    heights) per axes]}."""
    from matplotlib.figure import Figure

    seen: dict[str, list[dict]] = {}
    save = Figure.savefig

    def spy(self, fname, *a, **k):
        axes = []
        for ax in self.axes:
            if ax.get_label() == "<colorbar>":
                continue
            leg = ax.get_legend()
            axes.append({
                "xticks": [t.get_text() for t in ax.get_xticklabels()],
                "xlabel": ax.get_xlabel(),
                "legend": [t.get_text() for t in leg.get_texts()] if leg else [],
                "lines_x": [list(np.asarray(ln.get_xdata(), float)) for ln in ax.get_lines()
                            if ln.get_label() and not ln.get_label().startswith("_")],
                "bars": [p.get_height() for p in ax.patches],
            })
        seen[str(fname).rsplit("/", 1)[-1]] = axes
        return save(self, fname, *a, **k)

    monkeypatch.setattr(Figure, "savefig", spy)
    return seen


# the README's examples: densities 0.5, 1.0, 2.0 and n_points 5000, 20000 (MLflow gives "1.0" and "20000")
CASES = {"sampler.density": ["0.5", "1.0", "2.0"], "sampler.n_points": ["5000", "20000"]}


@pytest.mark.parametrize("key", list(CASES))
def test_every_group_in_every_plot(tmp_path, figures, key):
    values = CASES[key]
    expected = [canonical(float(v)) for v in values]
    df = mlflow_like_runs(key, values)
    res = write_report(df, ReportParams(enabled=True, group_by=[key]), tmp_path / "a")
    assert list(res["table"]["runs"]) == [3] * len(values)
    succ, et = figures["success.png"][0], figures["errors_times.png"]
    assert succ["xticks"] == expected and succ["xlabel"] == key
    assert len(succ["bars"]) == len(values) and all(h == 100 for h in succ["bars"])
    for ax in et:  # error boxes and stacked stage times: one per group, each with data
        assert ax["xticks"] == expected and ax["xlabel"] == key
    n_stages = 3  # repair, coarse, icp
    bars = np.array(et[1]["bars"]).reshape(n_stages, len(values))
    assert (bars > 0).all(), bars
    # against x: every value is plotted, and the legend does not read "all median"
    write_report(df, ReportParams(enabled=True, group_by=[key], x=key), tmp_path / "b")
    name = f"error_time_vs_{key}.png"
    want_x = sorted(float(v) for v in values)
    for ax in figures[name]:
        assert ax["xlabel"] == key and ax["lines_x"]
        for xs in ax["lines_x"]:
            assert sorted(xs) == want_x
        assert ax["xticks"] == [canonical(v) for v in want_x]
        assert not any(t.startswith("all") for t in ax["legend"]), ax["legend"]
    assert figures[name][0]["legend"] == ["median", "p90"]


def test_groups_by_two_keys_and_per_table(tmp_path, figures):
    a = mlflow_like_runs("sampler.n_points", ["5000", "20000"], seeds=2)
    a["params.data.pair"] = ["p1", "p2"] * 2
    a["tags.group.icp"] = ["horn", "gicp", "horn", "gicp"]
    b = a.copy()
    b["params.sampler.n_points"] = b["params.sampler.n_points"] + ".0"  # the same values, spelt otherwise
    df = pd.concat([a, b], ignore_index=True)
    p = ReportParams(enabled=True, group_by=["group.icp", "sampler.n_points"], per="data.pair")
    res = write_report(df, p, tmp_path)
    labels = {"gicp / 5000", "gicp / 20000", "horn / 5000", "horn / 20000"}
    assert set(res["table"]["_label"]) == labels and list(res["table"]["runs"]) == [2] * 4
    assert set(figures["success.png"][0]["xticks"]) == labels
    assert set(figures["errors_times.png"][0]["xticks"]) == labels
    assert set(res["per"].columns) == labels
    assert set(figures["success_per_data.pair.png"][0]["xticks"]) == labels


def test_canonical_labels_are_exact():
    assert [canonical(v) for v in (1.0, 20000, np.int64(20000), 2e4, 0.5, 1e-05, "x")] == \
        ["1", "20000", "20000", "20000", "0.5", "1e-05", "x"]
    # values the old "%.4g" labels merged stay apart
    assert canonical(12345.0) != canonical(12346.0)
    df = pd.DataFrame({"params.k": ["12345", "12346"], "status": ["FINISHED"] * 2})
    assert list(group_labels(df, ["k"])) == ["12345", "12346"]
    assert len(summarize(df, ["k"])) == 2


# ------------------------------------------------------------------------------------------------ intervals
def test_wilson_interval_by_hand():
    from scanreg.app.report.stats import wilson_interval

    # z = 1.959964; k = 5, n = 10: centre (0.5 + z^2/20) / (1 + z^2/10) = 0.5, half z sqrt(0.025 + z^2/400) / (1 + z^2/10)
    z = 1.959963984540054
    half = z * np.sqrt(0.25 / 10 + z * z / 400) / (1 + z * z / 10)
    assert wilson_interval(5, 10) == pytest.approx((0.5 - half, 0.5 + half), abs=1e-12)
    assert wilson_interval(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)  # the textbook values
    # all or none: the interval reaches the bound; 10/10 -> [n / (n + z^2), 1]
    assert wilson_interval(10, 10) == pytest.approx((10 / (10 + z * z), 1.0), abs=1e-12)
    assert wilson_interval(0, 10) == pytest.approx((0.0, z * z / (10 + z * z)), abs=1e-12)
    assert wilson_interval(80, 80)[0] == pytest.approx(0.9542, abs=1e-4)  # 80/80 is not "certainly 100 %"
    assert all(np.isnan(wilson_interval(0, 0)))


def test_bootstrap_median_ci_by_hand():
    """Three values 1, 2, 10: a resample's median is 1 when at least two draws are 1 (7 of the 27 equally likely
    resamples), 10 likewise (7/27), else 2 (13/27). The 2.5 % and 97.5 % quantiles are then 1 and 10; the 30 %
    and 70 % quantiles (a 40 % interval) both 2."""
    from scanreg.app.report.stats import bootstrap_median_ci

    assert bootstrap_median_ci([1, 2, 10]) == (1.0, 10.0)
    assert bootstrap_median_ci([1, 2, 10], level=0.4) == (2.0, 2.0)
    assert bootstrap_median_ci([10, np.nan, 1, 2], seed=0) == bootstrap_median_ci([1, 2, 10], seed=0)  # NaN dropped
    assert bootstrap_median_ci([3.0]) == (3.0, 3.0) and all(np.isnan(bootstrap_median_ci([])))
    # seeded: the same interval every time; a larger sample gives a narrower one around the median
    x = np.random.default_rng(1).normal(size=400)
    lo, hi = bootstrap_median_ci(x)
    assert (lo, hi) == bootstrap_median_ci(x) and lo < np.median(x) < hi
    # the median's standard error for a normal sample is about 1.2533 / sqrt(n): the 95 % interval ~ +-1.96 of it
    assert hi - lo == pytest.approx(2 * 1.96 * 1.2533 / np.sqrt(400), rel=0.3)


def test_iqr_by_hand():
    from scanreg.app.report.stats import iqr_interval

    assert iqr_interval([1, 2, 3, 4, 5]) == (2.0, 4.0)
    assert iqr_interval([1, 2, 3, 4]) == (1.75, 3.25)  # linear interpolation: positions 0.75 and 2.25


def test_report_cells_have_intervals_and_bins(tmp_path, figures):
    """Every median in report.md carries its interval, success its Wilson interval, named in the text; runs are
    binned by overlap (a failed run takes its pair's overlap); robustness curves per x value."""
    rows = []
    for method in ("a", "b"):
        for pair, ov in (("p1", 0.15), ("p2", 0.5), ("p3", 0.9)):
            for seed in range(4):
                ok = method == "a" or ov > 0.3
                failed = method == "b" and pair == "p1" and seed == 0
                rows.append({"run_id": f"{method}{pair}{seed}", "status": "FAILED" if failed else "FINISHED",
                             "start_time": pd.Timestamp("2026-01-01 10:00", tz="UTC"),
                             "end_time": pd.Timestamp("2026-01-01 10:05", tz="UTC"),
                             "tags.group.method": method, "params.data.pair": pair, "params.seed": str(seed),
                             "params.data.add_noise": str([0.0, 0.002, 0.005, 0.01][seed]),
                             "metrics.gt_overlap": np.nan if failed else ov,
                             "metrics.success": np.nan if failed else float(ok),
                             "metrics.rotation_error_deg": np.nan if failed else 0.1 * (seed + 1),
                             "metrics.keypoint_repeatability": np.nan if failed else 0.2 + 0.1 * seed,
                             "metrics.time_total_s": 2.0})
    df = pd.DataFrame(rows)
    df.attrs.update(experiment="t", uri="sqlite:///x.db", parent=None, parent_tags={})
    p = ReportParams(enabled=True, group_by=["group.method"], per="data.pair", bin_by="gt_overlap",
                     bin_edges=[0.0, 0.4, 1.0], bin_metrics=["keypoint_repeatability"],
                     metrics=["keypoint_repeatability"], x="data.add_noise", curves=["success", "keypoint_repeatability"])
    res = write_report(df, p, tmp_path)
    t = res["table"].set_index("_label")
    assert t.loc["a", "successes"] == 12 and t.loc["b", "successes"] == 8 and t.loc["b", "runs"] == 12
    from scanreg.app.report.stats import bootstrap_median_ci, wilson_interval

    assert (t.loc["b", "success_lo"], t.loc["b", "success_hi"]) == wilson_interval(8, 12)
    assert (t.loc["a", "rotation_error_deg_lo"], t.loc["a", "rotation_error_deg_hi"]) == \
        bootstrap_median_ci(0.1 * (np.arange(12) % 4 + 1))
    md = (tmp_path / "report.md").read_text()
    assert "95 % bootstrap CI of the median" in md and "Wilson 95 %" in md
    assert "| a | 12 | 0 | 12/12 = 100 % [" in md and "run time: 5.0 min wall clock for 24 runs" in md
    bins = pd.read_csv(tmp_path / "by_gt_overlap.csv").set_index(["gt_overlap", "group"])
    assert bins.loc[("[0, 0.4)", "b"), "runs"] == 4 and bins.loc[("[0, 0.4)", "b"), "successes"] == 0
    assert bins.loc[("[0.4, 1]", "b"), "runs"] == 8 and bins.loc[("[0.4, 1]", "b"), "success_rate"] == 1.0
    assert bins.loc[("[0.4, 1]", "a"), "keypoint_repeatability_median"] == pytest.approx(0.35)
    curves = pd.read_csv(tmp_path / "curves_vs_data.add_noise.csv")
    assert list(curves.loc[curves["group"] == "a", "keypoint_repeatability_median"]) == pytest.approx([0.2, 0.3, 0.4, 0.5])
    assert figures["success_by_gt_overlap.png"][0]["legend"] == ["a", "b"]
    assert len(figures["robustness_vs_data.add_noise.png"]) == 2
    with pytest.raises(ValueError, match="bootstrap or iqr"):
        write_report(df, ReportParams(enabled=True, interval="sd"), tmp_path / "x")
    iq = write_report(df, ReportParams(enabled=True, group_by=["group.method"], interval="iqr"), tmp_path / "i")
    assert iq["table"].set_index("_label").loc["a", "rotation_error_deg_lo"] == pytest.approx(0.175)
    assert "interquartile range" in (tmp_path / "i" / "report.md").read_text()


def test_a_group_whose_runs_all_failed_has_zero_successes():
    """A failed run counts as a failure, also when every run of a group failed (it logged no success)."""
    import pandas as pd

    df = pd.DataFrame({"params.k": ["a", "a", "b", "b"], "status": ["FINISHED", "FAILED", "FAILED", "FAILED"],
                       "metrics.success": [1.0, None, None, None]})
    t = summarize(df, ["k"]).set_index("k")
    assert t.loc["a", "successes"] == 1 and t.loc["a", "success_rate"] == 0.5
    assert t.loc["b", "successes"] == 0 and t.loc["b", "success_rate"] == 0.0 and t.loc["b", "success_hi"] > 0


def test_runs_without_ground_truth_are_reported_by_their_fit(tmp_path):
    """A sweep on the user's own files (no data.gt) has no errors and no success: the tables show the fit (rms,
    fitness) beside the times, and the report says why."""
    from scanreg.app.report.tables import console_table, display_table

    df = mlflow_like_runs("icp.name", ["horn", "gicp"])
    df = df.drop(columns=["metrics.rotation_error_deg", "metrics.translation_error", "metrics.success"])
    df["metrics.rms"] = [0.5, 0.7, 0.6, 0.2, 0.3, 0.1]
    df["metrics.fitness"] = 0.8
    t = summarize(df, ["icp.name"])
    console = console_table(t, ["icp.name"]).splitlines()
    assert console[0].split() == ["icp.name", "runs", "failed", "rms", "fitness", "coarse_s", "total_s"]
    df["metrics.input_unit_m"] = 0.001  # (the runs logged their unit: the lengths' heading names it)
    from scanreg.app.report.write import runs_unit

    assert console_table(t, ["icp.name"], unit=runs_unit(df)).split()[3] == "rms_mm"
    df.loc[0, "metrics.input_unit_m"] = 1.0
    assert runs_unit(df) is None
    shown = display_table(t, ["icp.name"], []).set_index("icp.name")
    assert shown.loc["horn", "rms"].startswith("0.6 ") and shown.loc["gicp", "rms"].startswith("0.2 ")
    assert "rotation_error_deg" not in shown and "success [Wilson 95 %]" not in shown
    write_report(df, ReportParams(), tmp_path)
    text = (tmp_path / "report.md").read_text()
    assert "No ground truth (`data.gt`)" in text and "Success: rotation error" not in text


def test_runs_without_ground_truth_in_a_group_with_it_are_not_judged():
    """A group of runs with and without ground truth (scanreg-report --parent all over a run with data.poses and
    one without): success over the judged runs, a failed run still a failure (it said 1/2 for 1 of 1)."""
    from scanreg.app.report.tables import console_table, display_table

    df = pd.DataFrame({"params.k": ["a"] * 4, "status": ["FINISHED", "FINISHED", "FINISHED", "FAILED"],
                       "metrics.success": [1.0, 0.0, None, None], "metrics.time_total_s": [1.0, 2.0, 3.0, None]})
    t = summarize(df, ["k"])
    assert t.loc[0, "successes"] == 1 and t.loc[0, "judged"] == 3 and t.loc[0, "runs"] == 4
    assert console_table(t, ["k"]).splitlines()[1].split()[:4] == ["a", "4", "1", "1/3"]
    assert display_table(t, ["k"], [])["success [Wilson 95 %]"][0].startswith("1/3 = 33 %")


def test_console_table_lines_up_groups_named_in_wide_characters():
    """Groups named by files in Chinese or Japanese (two terminal columns a character): every line of the console
    table takes the same terminal width, and a label too long for its column is cut with an ellipsis to fit."""
    from scanreg.app.report.tables import console_table
    from scanreg.runner.outputs import clipped, text_columns

    df = pd.DataFrame({"params.data.source": ["扫描一号.ply", "scan_b.ply", "スキャン.ply"] * 2, "status": ["FINISHED"] * 6,
                       "metrics.success": [1.0, 0.0, 1.0, 1.0, 1.0, 1.0], "metrics.time_total_s": [1.0] * 6})
    lines = console_table(summarize(df, ["data.source"]), ["data.source"]).splitlines()
    assert len(lines) == 4 and len({text_columns(ln) for ln in lines}) == 1
    assert any("扫描一号.ply" in ln for ln in lines)
    assert clipped("扫描一号.ply", 6) == "扫描…" and text_columns(clipped("扫描一号.ply", 7)) <= 7
    assert clipped("short", 8) == "short"


def test_scan_set_runs_are_tabled_by_their_placed_scans_and_worst_scan():
    """Scan-set runs log no pair errors: the tables show the placed scans and the worst scan's errors (they
    showed '-' under rot_deg and transl, the set's numbers only in report.csv)."""
    from scanreg.app.report.tables import console_table, display_table

    df = pd.DataFrame({"params.multiview.refine_samples": ["5000", "5000", "2000"], "status": ["FINISHED"] * 3,
                       "metrics.success": [1.0, 1.0, 0.0], "metrics.scans_placed": [10.0, 10.0, 9.0],
                       "metrics.scan_rotation_error_max_deg": [0.35, 0.37, 2.5],
                       "metrics.scan_translation_error_max_rel": [0.0017, 0.0019, 0.01],
                       "metrics.time_total_s": [15.0, 16.0, 12.0]})
    t = summarize(df, ["multiview.refine_samples"])
    console = console_table(t, ["multiview.refine_samples"]).splitlines()
    assert console[0].split() == ["multiview.refine_samples", "runs", "failed", "success", "worst_rot_deg",
                                  "worst_transl_rel", "placed", "total_s"]
    assert console[2].split()[:5] == ["5000", "2", "0", "2/2", "0.36"] and console[2].split()[6] == "10"
    # without ground truth the placed scans are the set's only result on the console (it showed the time alone)
    bare = summarize(df.drop(columns=[c for c in df if "error" in c or "success" in c]), ["multiview.refine_samples"])
    assert console_table(bare, ["multiview.refine_samples"]).splitlines()[0].split()[-2] == "placed"
    shown = display_table(t, ["multiview.refine_samples"], []).set_index("multiview.refine_samples")
    assert shown.loc[2000, "scans_placed"].startswith("9 ") and "rms" not in shown


def test_a_group_without_ground_truth_beside_one_with_has_no_success_rate():
    """Runs on files without data.gt tabled beside runs with ground truth (``scanreg-report --parent all``): their
    group shows no success rate ("-"), not 0 successes."""
    df = pd.DataFrame({"params.k": ["gt", "gt", "files"], "status": ["FINISHED"] * 3,
                       "metrics.success": [1.0, 0.0, None], "metrics.rms": [0.1, 0.2, 0.3]})
    t = summarize(df, ["k"]).set_index("k")
    assert t.loc["gt", "success_rate"] == 0.5 and np.isnan(t.loc["files", "success_rate"])


def test_file_names_from_long_group_labels_are_bounded():
    """A group labelled by many varying parameters gives a file name under the file systems' 255 bytes, the
    same for the same label, different for another; short labels stay as they are."""
    from scanreg.app.report.plots import SLUG_CHARS, _slug

    long = " / ".join(f"value{k}" for k in range(100))
    assert len(_slug(long)) == SLUG_CHARS and _slug(long) == _slug(long) != _slug(long + "x")
    assert _slug("icp.name: gicp") == "icp.name_gicp"


def test_the_latest_sweep_is_the_newest_with_runs(tmp_path):
    """A sweep that a typo stopped (icp=point_to_plane,gcip) leaves a FAILED parent run without runs under it: the
    report takes the newest sweep that has runs (it said 'no runs found' and named no other)."""
    import mlflow

    from scanreg.app.report.runs import latest_sweep_experiment, load_runs

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = mlflow.MlflowClient(uri)
    exp = client.create_experiment("scanreg")
    good = client.create_run(exp, tags={"scanreg.sweep": "parent"})
    for k in range(2):
        child = client.create_run(exp, tags={"mlflow.parentRunId": good.info.run_id})
        client.log_metric(child.info.run_id, "rotation_error_deg", 0.1 * (k + 1))
    stopped = client.create_run(exp, tags={"scanreg.sweep": "parent"}, start_time=good.info.start_time + 1000)
    client.set_terminated(stopped.info.run_id, "FAILED")
    df = load_runs("scanreg", uri, parent="latest")
    assert df.attrs["parent"] == good.info.run_id and len(df) == 2
    assert latest_sweep_experiment(uri) == "scanreg"


def test_a_metric_no_run_has_is_said(tmp_path, capsys):
    """--metrics with a typo showed no column and said nothing; now a warning names the close ones."""
    df = mlflow_like_runs("icp.name", ["horn", "gicp"])
    df["metrics.gt_rmse"] = 0.01
    write_report(df, ReportParams(metrics=["gt_rmse_typo"]), tmp_path, plots=False)
    out = capsys.readouterr()
    assert "no run has the metric 'gt_rmse_typo'; did you mean gt_rmse?" in out.out + out.err


def test_a_changed_experiment_sweep_keeps_the_experiments_report():
    """Re-running one job of an experiment (experiment=my_icp icp=horn data.pair=...) replaced the experiment's
    report with a one-run one; overrides that change the runs now send the report to a folder of their own, those
    that only change how the sweep runs or is filed do not."""
    from omegaconf import OmegaConf

    from scanreg.app.report.write import _changed_runs

    def cfg(*task):
        return OmegaConf.create({"hydra": {"overrides": {"task": list(task)}}})

    assert _changed_runs(cfg("experiment=my_icp", "launch=serial", "hydra.sweep.dir=x", "tracking.experiment=e")) == []
    assert _changed_runs(cfg("experiment=my_icp", "icp=horn", "data.pair=bun045:bun090")) == [
        "icp=horn", "data.pair=bun045:bun090"]
    assert _changed_runs(cfg("+experiment=my_icp", "hydra/launcher=ray", "~seed")) == ["~seed"]


def test_default_groups_are_the_methods_with_the_cases_apart():
    """A sweep of methods over pairs: grouped by the method (each pair's group held one run), the pairs in the
    per-case table; a sweep over pairs alone: grouped by the pair."""
    from scanreg.app.report.tables import default_grouping

    df = pd.DataFrame({"tags.group.icp": ["horn", "gicp"] * 2, "params.icp.name": ["horn", "gicp"] * 2,
                       "params.data.pair": ["a:b", "a:b", "b:c", "b:c"], "params.seed": ["0"] * 4})
    assert default_grouping(df) == (["group.icp"], "data.pair")
    assert default_grouping(df, per="data.x") == (["group.icp"], "data.x")
    assert default_grouping(df[df["tags.group.icp"] == "horn"]) == (["data.pair"], None)


def test_failed_runs_are_counted_by_reason_and_group(tmp_path):
    """The failed runs' section listed each reason once; now with its count and the groups it hit."""
    df = mlflow_like_runs("icp.name", ["horn", "gicp"])
    df.loc[[0, 3], "status"] = "FAILED"
    df["tags.error"] = None
    df.loc[[0, 3], "tags.error"] = "sampler.n_points: must be > 0"
    df["metrics.input_unit_m"] = 0.001
    write_report(df, ReportParams(), tmp_path, plots=False)
    text = (tmp_path / "report.md").read_text()
    runs = pd.read_csv(tmp_path / "runs.csv")  # every run, prefixes off, for one's own statistics
    assert len(runs) == len(df) and list(runs["status"]).count("FAILED") == 2 and "icp.name" in runs
    groups = sorted({str(df.loc[k, "params.icp.name"]) for k in (0, 3)})
    assert f"- sampler.n_points: must be > 0 (2 runs; {'; '.join(groups)})" in text
    assert "degrees and input units (mm), their medians and quantiles over the runs that finished" in text


def test_per_case_errors_and_console_counts(tmp_path):
    """--per showed success alone; the median rotation error per case and group is beside it (finished runs), and
    the console's success is the count of runs, as report.md has it (0.5 read as a rate of what)."""
    from scanreg.app.report.tables import console_table, per_errors

    df = pd.DataFrame({"params.k": ["a", "a", "b", "b"], "params.case": ["x", "y", "x", "y"],
                       "status": ["FINISHED", "FINISHED", "FINISHED", "FAILED"],
                       "metrics.rotation_error_deg": [0.5, 1.5, 3.0, None], "metrics.success": [1, 1, 0, None],
                       "metrics.translation_error": [0.1, 0.1, 0.1, None]})
    e = per_errors(df, ["k"], "case")
    assert e.loc["x", "a"] == 0.5 and e.loc["y", "a"] == 1.5 and e.loc["x", "b"] == 3.0 and np.isnan(e.loc["y", "b"])
    t = summarize(df, ["k"])
    lines = console_table(t, ["k"]).splitlines()
    assert lines[1].split()[:4] == ["a", "2", "0", "2/2"] and lines[2].split()[:4] == ["b", "2", "1", "0/2"]


def test_holm_and_mcnemar_and_wilcoxon_by_hand():
    """Holm's adjustment, McNemar's exact test and the signed-rank test against direct computations."""
    from math import comb

    from scanreg.app.report.paired import holm, mcnemar_exact, wilcoxon_p

    # Holm: sorted 0.01, 0.02, 0.04 times 3, 2, 1 -> 0.03, 0.04, 0.04 (made non-decreasing); NaN kept
    assert np.allclose(holm([0.04, 0.01, float("nan"), 0.02]), [0.04, 0.03, np.nan, 0.04], equal_nan=True)
    assert holm([0.9, 0.8]) == [1.0, 1.0]
    assert np.allclose(holm([0.01, 0.011, 0.04]), [0.03, 0.03, 0.04])  # 0.022 raised to the 0.03 before it
    # McNemar exact: 1 of 9 discordant cases one way: 2 * P(X <= 1), X ~ Bin(9, 1/2)
    assert mcnemar_exact(8, 1) == pytest.approx(2 * (comb(9, 0) + comb(9, 1)) / 2 ** 9)
    assert mcnemar_exact(0, 0) == 1.0
    # signed ranks of 6 differences, all of one sign: the exact two-sided p is 2 / 2^6
    assert wilcoxon_p(np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])) == pytest.approx(2 / 64)
    assert wilcoxon_p(np.zeros(4)) == 1.0 and np.isnan(wilcoxon_p(np.zeros(0)))


def test_paired_section_pairs_runs_by_case(tmp_path):
    """Two methods on the same 8 cases (pair x pose seed): the paired table pairs each case's runs, counts the
    cases only one solved, and takes the median of the differences on the cases both finished; a method on other
    cases does not pair; a case run twice in a group leaves the section out."""
    from scanreg.app.report.paired import paired_table

    rows = []
    for method, err in (("a", 1.0), ("b", 0.5)):
        for i, (pair, seed) in enumerate([(p, s) for p in ("p1", "p2", "p3", "p4") for s in ("0", "1")]):
            ok = not (method == "a" and i in (0, 1, 2))  # a fails 3 cases that b solves
            rows.append({"params.method.name": method, "params.data.pair": pair, "params.data.pose_seed": seed,
                         "params.seed": "0", "status": "FAILED" if method == "a" and i == 0 else "FINISHED",
                         "metrics.success": float(ok), "metrics.rotation_error_deg": err + 0.01 * i,
                         "metrics.time_total_s": 2.0 if method == "a" else 1.0 + 0.1 * i,
                         "start_time": pd.Timestamp("2026-01-01", tz="UTC")})
    df = pd.DataFrame(rows)
    df.loc[df["status"] == "FAILED", ["metrics.rotation_error_deg", "metrics.time_total_s"]] = np.nan
    df.attrs.update(experiment="t", uri="sqlite:///x.db", parent=None, parent_tags={})
    labels = df["params.method.name"]
    t = paired_table(df, labels, ["method.name"], ["rotation_error_deg", "time_total_s"])
    r = t.iloc[0]
    assert (r["first"], r["second"], r["cases"]) == ("a", "b", 8)
    assert (r["both_succeeded"], r["first_only"], r["second_only"], r["neither"]) == (5, 0, 3, 0)
    assert r["success_p"] == pytest.approx(2 / 8)  # 0 of 3 discordant cases one way: 2 * (1/2)^3
    # b - a on the 7 cases both finished: -0.5 each (same offsets), b lower in all 7
    assert r["rotation_error_deg_n"] == 7 and r["rotation_error_deg_diff_median"] == pytest.approx(-0.5)
    assert (r["rotation_error_deg_second_lower"], r["rotation_error_deg_first_lower"]) == (7, 0)
    assert r["rotation_error_deg_p"] == pytest.approx(2 / 2 ** 7)
    expected = np.median([1.0 + 0.1 * i - 2.0 for i in range(1, 8)])
    assert r["time_total_s_diff_median"] == pytest.approx(expected)
    # the report writes it
    write_report(df, ReportParams(group_by=["method.name"]), tmp_path, plots=False)
    text = (tmp_path / "report.md").read_text()
    assert "## Paired comparison on the same cases" in text and "0 / 3 (0.250)" in text
    assert pd.read_csv(tmp_path / "paired.csv")["cases"].tolist() == [8]
    # a third method on other cases: no pair with it; a case twice in one group: no section
    c = df[df["params.method.name"] == "b"].copy()
    c["params.method.name"], c["params.data.pair"] = "c", "q" + c["params.data.pair"]
    both = pd.concat([df, c], ignore_index=True)
    t3 = paired_table(both, both["params.method.name"], ["method.name"], ["rotation_error_deg"])
    assert t3[["first", "second"]].values.tolist() == [["a", "b"]]
    twice = pd.concat([df, df.iloc[:1]], ignore_index=True)
    assert paired_table(twice, twice["params.method.name"], ["method.name"], ["rotation_error_deg"]) is None
    # a case key that some runs lack (scan-set runs beside pair runs: no data.pair): no traceback (pandas 3's
    # astype(str) kept the missing value, and joining the keys failed on it); those runs are one case of their own
    gap = df.copy()
    gap.loc[gap.index[:2], "params.data.pair"] = np.nan
    t4 = paired_table(gap, gap["params.method.name"], ["method.name"], ["rotation_error_deg"])
    assert t4 is not None and t4.iloc[0]["cases"] == 6  # two of a's runs without a pair: not paired with b's


def test_an_interrupted_sweeps_unstarted_runs_are_said_not_grouped(tmp_path):
    """A sweep ended with Ctrl-C leaves a KILLED run that logged no config: every parameter then seemed to vary,
    and the report failed ('runs of group(s) ... have no row in the table'). It is left out of the tables and
    said under the failed runs; the finished runs are reported."""
    import mlflow

    from scanreg.app.report.runs import load_runs

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = mlflow.MlflowClient(uri)
    exp = client.create_experiment("scanreg")
    parent = client.create_run(exp, tags={"scanreg.sweep": "parent"})
    for name, seed in (("horn", "0"), ("horn", "1"), ("gicp", "0"), ("gicp", "1")):
        child = client.create_run(exp, tags={"mlflow.parentRunId": parent.info.run_id, "group.icp": name})
        for k, v in (("icp.name", name), ("seed", seed), ("sampler.n_points", "5000")):
            client.log_param(child.info.run_id, k, v)
        client.log_metric(child.info.run_id, "rotation_error_deg", 0.1)
        client.set_terminated(child.info.run_id, "FINISHED")
    killed = client.create_run(exp, tags={"mlflow.parentRunId": parent.info.run_id})
    client.set_terminated(killed.info.run_id, "KILLED")
    # a job stopped while its config was being logged (part of it logged, the run left RUNNING)
    cut = client.create_run(exp, tags={"mlflow.parentRunId": parent.info.run_id, "group.icp": "gicp"})
    client.log_param(cut.info.run_id, "icp.name", "gicp")
    # a run that failed with its whole config is a failure of its group, as ever
    failed = client.create_run(exp, tags={"mlflow.parentRunId": parent.info.run_id, "group.icp": "horn"})
    for k, v in (("icp.name", "horn"), ("seed", "2"), ("sampler.n_points", "5000")):
        client.log_param(failed.info.run_id, k, v)
    client.set_terminated(failed.info.run_id, "FAILED")
    df = load_runs("scanreg", uri, parent="latest")
    assert len(df) == 5 and df.attrs["unlogged"] == 2 and list(df["status"]).count("FAILED") == 1
    assert default_grouping(df)[0] == ["group.icp"]
    write_report(df, ReportParams(), tmp_path / "out", plots=True)
    text = (tmp_path / "out" / "report.md").read_text()
    assert "- 2 run(s) ended before logging their config (an interrupted sweep's jobs): in no table" in text


def test_a_report_into_a_folder_removes_what_the_previous_report_wrote(tmp_path):
    """Every ad-hoc sweep reports into outputs/reports/scanreg/: a new report left the previous one's per-case
    tables and plots beside its own (a researcher's trial). The files a report wrote are listed in the folder,
    and the next report removes them first; other files stay."""
    df = mlflow_like_runs("icp.name", ["horn", "gicp"])
    df["params.data.pair"] = ["a:b", "c:d"] * (len(df) // 2)
    write_report(df, ReportParams(per="data.pair"), tmp_path, plots=False)
    assert (tmp_path / "per.csv").is_file()
    (tmp_path / "mine.txt").write_text("kept")
    write_report(df.drop(columns="params.data.pair"), ReportParams(), tmp_path, plots=False)  # (no cases)
    assert not (tmp_path / "per.csv").exists() and (tmp_path / "report.md").is_file()
    assert (tmp_path / "mine.txt").read_text() == "kept"
    assert "report.md" in (tmp_path / ".scanreg-report-files").read_text().split()


def test_the_share_of_runs_whose_coarse_stage_fell_back_or_looked_again_is_shown_when_any_did():
    """A sweep over salience measures at few points: ISS and cn_l3 both fell back to uniform keypoints and gave the
    same transform, and the report did not say so (a researcher's trial). The share per group is shown when any
    run fell back, and only then."""
    from scanreg.app.report.tables import console_table, display_table

    df = mlflow_like_runs("salience.name", ["iss", "uniform"])
    df["metrics.coarse_fallback"] = [1.0, 1.0, 0.0, 0.0, 0.0, 0.0]
    table = summarize(df, ["salience.name"])
    assert list(table["coarse_fallback_share"]) == pytest.approx([2 / 3, 0.0])
    assert "coarse_fallback (share of runs)" in display_table(table, ["salience.name"], [])
    assert "fallback" in console_table(table, ["salience.name"], width=200).splitlines()[0]
    df["metrics.coarse_fallback"] = 0.0
    assert "coarse_fallback_share" not in summarize(df, ["salience.name"])
    # likewise the share of runs whose coarse stage looked at the pair a second time
    df["metrics.coarse_second_look"] = [0.0, 1.0, 0.0, 0.0, 0.0, 0.0]
    table = summarize(df, ["salience.name"])
    assert list(table["coarse_second_look_share"]) == pytest.approx([1 / 3, 0.0])
    assert "coarse_second_look (share of runs)" in display_table(table, ["salience.name"], [])
    assert "second_look" in console_table(table, ["salience.name"], width=200).splitlines()[0]


def test_per_case_tables_order_the_groups_by_value():
    """A density sweep's per-case tables and heat map sorted the groups as text ('1000000 | 200000 | 2000000 |
    500000', a researcher's trial); they come in the summary's order, by value."""
    from scanreg.app.report.tables import per_errors, per_table

    df = mlflow_like_runs("sampler.n_points", ["2000000", "200000", "1000000", "500000"])
    df["params.data.pair"] = "a:b"
    order = ["200000", "500000", "1000000", "2000000"]
    assert list(per_table(df, ["sampler.n_points"], "data.pair").columns) == order
    assert list(per_errors(df, ["sampler.n_points"], "data.pair").columns) == order
    assert list(summarize(df, ["sampler.n_points"])["_label"]) == order


def test_an_unknown_group_by_key_is_a_config_error():
    """--group-by with a key no run has: a config error (the CLI's exit 2, as its docs say), naming what varies."""
    from scanreg.app.report.tables import column_for
    from scanreg.errors import ConfigError

    df = mlflow_like_runs("icp.name", ["horn", "gicp"])
    with pytest.raises(ConfigError, match=r"unknown group-by key 'icp.nme'; e.g. icp.name"):
        column_for("icp.nme", df)


def test_x_without_numbers_is_a_config_error(tmp_path):
    """--x icp.name: its plot and curves vanished without a word (a researcher's trial); now one config line."""
    from scanreg.errors import ConfigError

    df = mlflow_like_runs("icp.name", ["horn", "gicp"])
    with pytest.raises(ConfigError, match=r"report x 'icp.name' has no numbers \(horn, gicp\)"):
        write_report(df, ReportParams(x="icp.name"), tmp_path, plots=False)
    write_report(mlflow_like_runs("sampler.n_points", ["2000", "4000"]), ReportParams(x="sampler.n_points"), tmp_path,
                 plots=False)


def test_the_recorded_command_writes_the_same_report_again(tmp_path):
    """report.md records the scanreg-report command that wrote it, with the runs pinned: re-run after a newer
    sweep, it reads the same sweep and applies the same configured settings (--config: the title, per-case
    table and bins of the experiment), and writes the same table (it recorded --group-by/--x/--per only, so a
    configured report came back with other groups, and 'latest' read the newer sweep)."""
    import re
    import shlex

    import mlflow

    from scanreg.app.report.write import main

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = mlflow.MlflowClient(uri)
    exp = client.create_experiment("icp_comparison")

    def sweep(start, offset):
        parent = client.create_run(exp, tags={"scanreg.sweep": "parent"}, start_time=start)
        for k, (icp, pair) in enumerate([(i, p) for i in ("horn", "gicp") for p in ("a:b", "c:d")]):
            run = client.create_run(exp, tags={"mlflow.parentRunId": parent.info.run_id}, start_time=start + k + 1)
            rid = run.info.run_id
            for key, v in (("group.icp", icp), ("data.pair", pair)):
                client.log_param(rid, key, v)
            for key, v in (("rotation_error_deg", offset + 0.1 * k), ("translation_error", 0.01 * k),
                           ("translation_error_rel", 0.001), ("success", 1.0), ("gt_overlap", 0.3 + 0.2 * k),
                           ("gt_rmse", 0.02), ("icp_iterations", 10 + k), ("time_total_s", 1.0 + k)):
                client.log_metric(rid, key, v)
            client.set_terminated(rid, "FINISHED", end_time=start + k + 2)
        client.set_terminated(parent.info.run_id, "FINISHED", end_time=start + 10)
        return parent.info.run_id

    first = sweep(1_000_000, 0.0)
    out = tmp_path / "report"
    assert main(["--config", "icp_comparison", "--uri", uri, "--out", str(out), "--no-plots"]) == 0
    text = (out / "report.md").read_text()
    assert text.startswith("# ICP variants from a nearby start")
    command = re.search(r"^- report: `(.*)`, ", text, re.M).group(1)
    assert f"--parent {first}" in command and "--config icp_comparison" in command
    table = (out / "report.csv").read_text()
    sweep(2_000_000, 5.0)  # a newer sweep: 'latest' now
    args = shlex.split(command)
    assert args[0] == "scanreg-report" and main(args[1:]) == 0
    assert (out / "report.csv").read_text() == table
    assert (out / "report.md").read_text().startswith("# ICP variants from a nearby start")
