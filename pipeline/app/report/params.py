"""What the report of a sweep shows (the ``report`` block of the config)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional


@dataclass
class ReportParams:
    """What the report of an experiment's sweep shows (the ``report`` block of the config)."""

    enabled: bool = False
    """Write the report when a ``-m`` sweep (or an experiment run as one) ends."""
    out: Optional[str] = None
    """Folder for report.md, report.csv and the PNG plots; null: outputs/reports/<experiment>. Relative paths
    are taken from the current directory. The committed reports in experiments/ are rewritten only when asked
    (``report.out=experiments/NAME``)."""
    group_by: list[str] = field(default_factory=list)
    """Config keys whose values are the compared methods (e.g. ``[group.salience]``); empty: the parameters
    that vary between the runs."""
    x: Optional[str] = None
    """A numeric swept key to plot errors and times against (e.g. ``sampler.density``); null: no such plot."""
    per: Optional[str] = None
    """A key to show success per value of (e.g. ``data.pair``): a table and a heat map; null: none."""
    title: Optional[str] = None
    """Heading of the report; null: the experiment name."""
    notes: Optional[str] = None
    """A paragraph put under the heading (what the experiment asks, how to read it)."""
    metrics: list[str] = field(default_factory=list)
    """Further metrics whose median per group the table shows (e.g. ``dev_rms_um``, ``landmark_coarse_rms``)."""
    interval: str = "bootstrap"
    """The interval shown beside every median: ``bootstrap`` (percentile 95 % confidence interval of the median,
    2000 seeded resamples of the group's runs) or ``iqr`` (interquartile range, 25th to 75th percentile). Success
    rates always get the Wilson 95 % score interval."""
    paired: list[str] = field(default_factory=lambda: ["rotation_error_deg", "time_total_s"])
    """Metrics compared case by case between every two groups, when the runs share cases (the same data keys
    and seeds): the median paired difference with its interval and Wilcoxon's signed-rank test, beside
    McNemar's exact test of success (:mod:`scanreg.app.report.paired`); empty: no paired section."""
    bin_by: Optional[str] = None
    """A per-run metric (e.g. ``gt_overlap``, a share 0..1) whose bins get their own success table and plot; null:
    none."""
    bin_edges: list[float] = field(default_factory=lambda: [0.0, 0.1, 0.2, 0.4, 0.6, 0.8, 1.0])
    """Edges of the ``bin_by`` bins (left-closed, the last also right-closed), in that metric's unit."""
    bin_metrics: list[str] = field(default_factory=list)
    """Metrics whose median (with its interval) per bin and group the report also tabulates."""
    curves: list[str] = field(default_factory=list)
    """Metrics plotted against ``x`` (robustness curves), one panel each: ``success`` as a rate with its Wilson
    band, any other as the median with its interval band (e.g. ``[success, keypoint_repeatability]``)."""
    showcase: Optional[dict[str, Any]] = None
    """Config values selecting one run to show in detail (e.g. ``{data.noise: 0.02, data.pick_error: 0.3}``):
    its key metrics, its per-part table and its PNG pictures are copied into the report; null: none."""
