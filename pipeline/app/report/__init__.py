"""``scanreg-report``: MLflow runs -> comparison tables (Markdown, CSV) and plots (PNG).

The command and what a report holds: :mod:`~scanreg.app.report.write`.

The package: :mod:`~scanreg.app.report.params` (the ``report`` block), :mod:`~scanreg.app.report.runs` (MLflow
runs as a table), :mod:`~scanreg.app.report.tables` and :mod:`~scanreg.app.report.stats` (grouping, medians,
intervals), :mod:`~scanreg.app.report.plots`, :mod:`~scanreg.app.report.write` (the report and the command).
"""
