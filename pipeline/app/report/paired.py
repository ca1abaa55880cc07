"""Paired comparison of methods on the same cases: a report's groups (the methods) compared two by two on the
runs they share a case with, where the unpaired intervals of the main table cannot tell two methods apart.

A run's case is what it was given, not how it worked: the values of the data keys (``data.*``, e.g.
``data.pair``, ``data.pose_seed``) and of the seeds, less the report's own group keys. Two groups' runs of the
same case form a pair. Per pair of groups:

- success, as McNemar's exact test: of the cases that only one of the two solved, is either side more often
  the one? The two-sided binomial test of ``min(b, c)`` of ``b + c`` at 1/2 (``b``: cases only the first solved,
  ``c``: only the second); a failed run is a failure.
- each metric (rotation error, time, ...), on the cases where both runs finished and logged it: the median of the
  differences second minus first, with its bootstrap interval (:func:`~scanreg.app.report.stats.bootstrap_median_ci`),
  how often each side was lower, and the two-sided Wilcoxon signed-rank test (Wilcoxon 1945; ties dropped).

With more than two groups every pair is tested, and each p-value also gets Holm's step-down adjustment over the
pairs (Holm 1979), per metric, so that "any difference" is not found by testing many pairs.
"""

from __future__ import annotations

from itertools import combinations
from pathlib import Path

import numpy as np
import pandas as pd

from scanreg.app.report.stats import bootstrap_median_ci
from scanreg.app.report.tables import fmt_value, is_seed_key, to_markdown

MAX_GROUPS = 8
"""With more groups than this (28 pairs), the paired section is left out: the per-case table says more."""


def case_keys(df: pd.DataFrame, group_by: list[str]) -> list[str]:
    """The parameter columns that name a run's case (module docstring): data keys and seeds that vary between
    the runs, none of the group keys."""
    own = {f"params.{k}" for k in group_by}
    keys = []
    for c in sorted(df.columns):
        if not c.startswith("params.") or c in own:
            continue
        k = c[len("params."):]
        if (k.startswith("data.") or is_seed_key(k)) and df[c].nunique(dropna=False) > 1:
            keys.append(c)
    return keys


def holm(p: list[float]) -> list[float]:
    """Holm's step-down adjusted p-values of ``p`` (NaN stays NaN): the k-th smallest of m times (m - k + 1),
    made non-decreasing, at most 1."""
    p = np.asarray(p, float)
    out = np.full(len(p), np.nan)
    ok = np.flatnonzero(np.isfinite(p))
    m = len(ok)
    if not m:
        return out.tolist()
    order = ok[np.argsort(p[ok], kind="stable")]
    adj = np.minimum(1.0, np.maximum.accumulate(p[order] * (m - np.arange(m))))
    out[order] = adj
    return out.tolist()


def mcnemar_exact(first_only: int, second_only: int) -> float:
    """Two-sided exact McNemar p-value: the binomial test of the discordant cases at 1/2 (1 when there are none)."""
    from scipy.stats import binomtest

    n = first_only + second_only
    return 1.0 if n == 0 else float(binomtest(min(first_only, second_only), n, 0.5).pvalue)


def wilcoxon_p(d: np.ndarray) -> float:
    """Two-sided Wilcoxon signed-rank p-value of the paired differences ``d`` (zeros dropped; 1 when all are zero,
    NaN with none)."""
    from scipy.stats import wilcoxon

    if not len(d):
        return float("nan")
    if not np.any(d != 0):
        return 1.0
    return float(wilcoxon(d, zero_method="wilcox", alternative="two-sided").pvalue)


def paired_table(df: pd.DataFrame, labels: pd.Series, group_by: list[str], metrics: list[str]) -> pd.DataFrame | None:
    """One row per pair of groups (``labels``: each run's group label) with the paired tests of the module
    docstring; None when there is nothing to pair: fewer than two groups or more than :data:`MAX_GROUPS`, no
    case key, a case run more than once in a group (which run would pair?), or no pair of groups sharing two
    cases."""
    keys = case_keys(df, group_by)
    names = sorted(labels.unique())
    if not keys or not 2 <= len(names) <= MAX_GROUPS:
        return None
    # (map(str), not astype(str): pandas 3 keeps a missing value missing there, and join then fails on it)
    case = df[keys].apply(lambda c: c.map(str)).agg(" | ".join, axis=1)
    if pd.DataFrame({"g": labels, "c": case}).duplicated().any():
        return None
    finished = df["status"] == "FINISHED"
    has_success = "metrics.success" in df
    success = finished & (df["metrics.success"].fillna(0) > 0.5) if has_success else None
    rows = []
    for a, b in combinations(names, 2):
        ia = pd.Series(df.index[labels == a], index=case[labels == a].values)
        ib = pd.Series(df.index[labels == b], index=case[labels == b].values)
        shared = ia.index.intersection(ib.index)
        if len(shared) < 2:
            continue
        ra, rb = ia[shared].values, ib[shared].values
        row = {"first": a, "second": b, "cases": len(shared)}
        if has_success:
            sa, sb = success[ra].values, success[rb].values
            row.update({"both_succeeded": int((sa & sb).sum()), "first_only": int((sa & ~sb).sum()),
                        "second_only": int((~sa & sb).sum()), "neither": int((~sa & ~sb).sum())})
            row["success_p"] = mcnemar_exact(row["first_only"], row["second_only"])
        for m in metrics:
            c = f"metrics.{m}"
            if c not in df:
                continue
            both = finished[ra].values & finished[rb].values
            xa, xb = df.loc[ra, c].values.astype(float), df.loc[rb, c].values.astype(float)
            ok = both & np.isfinite(xa) & np.isfinite(xb)
            d = xb[ok] - xa[ok]
            row[f"{m}_n"] = int(ok.sum())
            row[f"{m}_diff_median"] = float(np.median(d)) if len(d) else float("nan")
            row[f"{m}_diff_lo"], row[f"{m}_diff_hi"] = bootstrap_median_ci(d)
            row[f"{m}_second_lower"] = int((d < 0).sum())
            row[f"{m}_first_lower"] = int((d > 0).sum())
            row[f"{m}_p"] = wilcoxon_p(d)
        rows.append(row)
    if not rows:
        return None
    table = pd.DataFrame(rows)
    table.attrs["keys"] = keys
    for c in [c for c in table.columns if c.endswith("_p")]:
        table[f"{c}_holm"] = holm(table[c].tolist())
    return table


def _p(v: float) -> str:
    return "–" if not np.isfinite(v) else ("< 0.001" if v < 0.001 else f"{v:.3f}")


def paired_markdown(table: pd.DataFrame, metrics: list[str]) -> list[str]:
    """The paired section's lines: what it tests, then one table row per pair of groups."""
    multiple = len(table) > 1
    lines = [
        "Runs paired by their case (the same data keys and seeds: `" + "`, `".join(k[len("params."):] for k in
                                                                                  table.attrs.get("keys", []))
        + "`), two groups at a time. Success: cases only the first / only the second solved, McNemar's exact "
        "p. Metrics: the median of second minus first over the cases both finished [95 % bootstrap CI], how "
        "many cases the second / the first was lower, Wilcoxon signed-rank p."
        + (" p-values adjusted over the pairs by Holm's method (holm); paired.csv has the unadjusted ones too."
           if multiple else " paired.csv has the numbers."), ""]
    show = pd.DataFrame({"first": table["first"], "second": table["second"], "cases": table["cases"]})
    pcol = "success_p_holm" if multiple else "success_p"
    if "success_p" in table:
        show["success: first only / second only (p)"] = [
            f"{r.first_only} / {r.second_only} ({_p(getattr(r, pcol))})" for r in table.itertuples()]
    for m in metrics:
        if f"{m}_p" not in table:
            continue
        col = f"{m}_p_holm" if multiple else f"{m}_p"
        show[f"{m}: second - first [CI]; second / first lower (p)"] = [
            "–" if not r[f"{m}_n"] else
            f"{fmt_value(r[f'{m}_diff_median'])} [{fmt_value(r[f'{m}_diff_lo'])}, {fmt_value(r[f'{m}_diff_hi'])}]; "
            f"{r[f'{m}_second_lower']} / {r[f'{m}_first_lower']} ({_p(r[col])})"
            for _, r in table.iterrows()]
    return lines + [to_markdown(show), ""]


def paired_section(df: pd.DataFrame, labels: pd.Series, group_by: list[str], metrics: list[str], out: Path) -> list[str]:
    """The report's paired section (:func:`paired_table`, written to ``out``/paired.csv) as markdown lines; none
    when there is nothing to pair or no metric is asked for."""
    table = paired_table(df, labels, group_by, metrics) if metrics else None
    if table is None:
        return []
    table.to_csv(out / "paired.csv", index=False)
    return ["## Paired comparison on the same cases", "", *paired_markdown(table, metrics)]
