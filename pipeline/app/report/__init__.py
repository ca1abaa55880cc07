"""``scanreg-report``: MLflow runs -> comparison tables (Markdown, CSV) and plots (PNG).

    scanreg-report                                   # the newest sweep (of any experiment), grouped by what varies
    scanreg-report --experiment bunny_benchmark --group-by group.coarse --per data.pair
    scanreg-report --experiment sampling_density --group-by sampler.density --x sampler.density
    scanreg-report --experiment icp_comparison --compare-to icp_comparison_old

Runs are loaded with ``mlflow.search_runs``; ``--group-by`` takes config keys (``icp.tau``; ``group.coarse`` is
the chosen implementation of a stage group). Per group: runs, failed runs, success rate (rotation error < 2°
and translation error < 1 % of the diagonal, as configured in ``evaluate``; a failed run counts as a failure),
median and 90th-percentile errors, median time per stage. Plots: success rate per group, error and time against
``--x``, success per ``--per`` value (e.g. per scan pair). An experiment file turns the report on with
``report.enabled=true`` so that ``scanreg experiment=NAME`` writes it when its sweep ends.

The package: :mod:`~scanreg.app.report.params` (the ``report`` block), :mod:`~scanreg.app.report.runs` (MLflow
runs as a table), :mod:`~scanreg.app.report.tables` and :mod:`~scanreg.app.report.stats` (grouping, medians,
intervals), :mod:`~scanreg.app.report.plots`, :mod:`~scanreg.app.report.write` (the report and the command).
"""
