"""Reports: every group of a sweep appears in every table and plot (the plotted labels and data are read back
from the matplotlib figures as they are saved)."""

import numpy as np
import pandas as pd
import pytest

from scanreg.report import ReportParams, canonical, group_labels, summarize, write_report


def mlflow_like_runs(key: str, values: list[str], seeds: int = 3) -> pd.DataFrame:
    """Runs as ``mlflow.search_runs`` returns them: params are strings exactly as logged ("1.0", "20000")."""
    rng = np.random.default_rng(0)
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
