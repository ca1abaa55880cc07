"""The report's plots (PNG, matplotlib)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from scanreg.app.report.stats import interval_name
from scanreg.app.report.tables import STAGES, canonical, column_for, group_labels

def save_figure(fig, path: Path) -> Path:
    """Lay out, write (110 dpi) and close a report figure; returns ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    _plt().close(fig)
    return path


# ---------------------------------------------------------------------------------------------------- plots
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


SLUG_CHARS = 80
"""Longest slug (:func:`_slug`) kept whole; a longer one is cut and ends in a hash of the whole (file names of
at most 255 bytes: a group labelled by many varying parameters)."""


def _slug(s: str) -> str:
    """``s`` as a file name part: runs of other characters than letters, digits, ``_.-`` as one ``_``; cut to
    :data:`SLUG_CHARS` with a hash of the whole when longer (the same label, the same name)."""
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "_", s)
    if len(slug) <= SLUG_CHARS:
        return slug
    import hashlib

    return slug[:SLUG_CHARS - 13] + "_" + hashlib.sha1(slug.encode()).hexdigest()[:12]


def make_plots(df: pd.DataFrame, table: pd.DataFrame, group_by: list[str], out: Path, x: str | None,
               per_t: pd.DataFrame | None) -> list[Path]:
    """Success per group, then errors and times against ``x`` (or per group), then success per ``per`` value.
    Every group of ``table`` appears in every plot: the runs are matched to the rows by the same canonical
    label (:func:`group_labels`)."""
    plt = _plt()
    from matplotlib.ticker import NullLocator

    paths: list[Path] = []
    labels = list(table["_label"]) if "_label" in table else ["all"] * len(table)
    keys = " / ".join(group_by) or "runs"
    ok = df[df["status"] == "FINISHED"].copy()
    ok["_g"] = group_labels(ok, group_by)
    missing = sorted(set(ok["_g"]) - set(labels))
    if missing:  # cannot happen with one labelling function; never drop data without a word
        raise ValueError(f"runs of group(s) {', '.join(missing)} have no row in the table")

    def ticks(ax, names):
        many = len(names) > 4 or max((len(n) for n in names), default=0) > 12
        ax.set_xticks(range(len(names)), names, rotation=45 if many else 0, ha="right" if many else "center",
                      fontsize=7)
        ax.set_xlabel(keys)

    if "success_rate" in table:  # success per method
        fig, ax = plt.subplots(figsize=(max(4.5, 0.6 * len(table) + 2), 3.4))
        ax.bar(range(len(table)), table["success_rate"].fillna(0) * 100, color="tab:blue")
        ticks(ax, labels)
        ax.set_ylabel("success [%]")
        ax.set_ylim(0, 100)
        ax.set_title("success rate (rotation and translation\nerror within the thresholds)", fontsize=9)
        paths.append(save_figure(fig, out / "success.png"))

    if x and "metrics.rotation_error_deg" in ok:
        xc = column_for(x, ok)
        ok["_x"] = pd.to_numeric(ok[xc], errors="coerce")
        others = [k for k in group_by if k != x]
        ok["_g2"] = group_labels(ok, others)
        if ok["_x"].notna().any():
            fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
            for g, d in ok.groupby("_g2", sort=True):
                pre = f"{g} " if others else ""
                s = d.groupby("_x")
                med = s["metrics.rotation_error_deg"].median()
                p90 = s["metrics.rotation_error_deg"].quantile(0.9)
                line = axes[0].plot(med.index, med.values, "o-", label=f"{pre}median")[0]
                axes[0].plot(p90.index, p90.values, "--", color=line.get_color(), label=f"{pre}p90")
                if "metrics.time_total_s" in d:
                    t = s["metrics.time_total_s"].median()
                    axes[1].plot(t.index, t.values, "o-", color=line.get_color(), label=f"{pre}total")
                    if "metrics.time_coarse_s" in d:
                        tc = s["metrics.time_coarse_s"].median()
                        axes[1].plot(tc.index, tc.values, ":", color=line.get_color(), label=f"{pre}coarse")
            axes[0].set_yscale("log")
            axes[0].set_ylabel("rotation error [deg]")
            axes[1].set_ylabel("median time [s]")
            xs = np.sort(ok["_x"].dropna().unique())
            for ax in axes:
                ax.set_xlabel(x)
                if (xs > 0).all() and xs.max() / xs.min() >= 10:
                    ax.set_xscale("log")
                ax.set_xticks(xs, [canonical(v) for v in xs], fontsize=7)
                ax.xaxis.set_minor_locator(NullLocator())  # x only: a log y axis within a decade needs its minor labels
                ax.legend(fontsize=7, title=" / ".join(others) or None, title_fontsize=7)
            paths.append(save_figure(fig, out / f"error_time_vs_{_slug(x)}.png"))
    elif "metrics.rotation_error_deg" in ok and len(ok):  # error distribution and stage times per method
        names = list(dict.fromkeys(labels))
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
        data = [ok.loc[ok["_g"] == n, "metrics.rotation_error_deg"].dropna().clip(lower=1e-3).values for n in names]
        axes[0].boxplot([d if len(d) else [np.nan] for d in data], positions=range(len(names)))
        ticks(axes[0], names)
        axes[0].set_yscale("log")
        axes[0].set_ylabel("rotation error [deg]")
        bottom = np.zeros(len(names))
        for s in STAGES[1:-1]:
            c = f"metrics.time_{s}_s"
            if c not in ok:
                continue
            v = np.array([ok.loc[ok["_g"] == n, c].median() for n in names])
            v = np.nan_to_num(v)
            axes[1].bar(range(len(names)), v, bottom=bottom, label=s)
            bottom += v
        ticks(axes[1], names)
        axes[1].set_ylabel("median time per stage [s]")
        if bottom.any():  # no stage times logged: no legend to draw
            axes[1].legend(fontsize=7)
        paths.append(save_figure(fig, out / "errors_times.png"))

    if per_t is not None and not per_t.empty:
        fig, ax = plt.subplots(figsize=(max(4.0, 0.9 * per_t.shape[1] + 3), max(3.0, 0.22 * len(per_t) + 1.2)))
        im = ax.imshow(per_t.values * 100, aspect="auto", cmap="RdYlGn", vmin=0, vmax=100)
        ax.set_yticks(range(len(per_t)), [str(i) for i in per_t.index], fontsize=7)
        ax.set_xticks(range(per_t.shape[1]), list(per_t.columns), rotation=45 if per_t.shape[1] > 3 else 0,
                      ha="right" if per_t.shape[1] > 3 else "center", fontsize=7)
        ax.set_ylabel(per_t.index.name)
        ax.set_xlabel(keys)  # (the swept key, as every plot names it)
        fig.colorbar(im, ax=ax, label="success [%]")
        paths.append(save_figure(fig, out / f"success_per_{_slug(per_t.index.name)}.png"))
    return paths


def plot_bins(bt: pd.DataFrame, bin_by: str, out: Path) -> Path:
    """Success per bin, one bar per group, with the Wilson interval as error bars."""
    plt = _plt()
    bins = list(dict.fromkeys(bt[bin_by]))
    groups = list(dict.fromkeys(bt["group"]))
    w = 0.8 / max(1, len(groups))
    fig, ax = plt.subplots(figsize=(max(5.0, 0.35 * len(bins) * len(groups) + 2.5), 3.6))
    for j, g in enumerate(groups):
        d = bt[bt["group"] == g].set_index(bin_by).reindex(bins)
        xs = np.arange(len(bins)) + (j - (len(groups) - 1) / 2) * w
        r = d["success_rate"].to_numpy(float) * 100
        err = np.vstack([r - d["success_lo"].to_numpy(float) * 100, d["success_hi"].to_numpy(float) * 100 - r])
        ax.bar(xs, np.nan_to_num(r), w, yerr=np.nan_to_num(err), capsize=2, label=g)
    ax.set_xticks(range(len(bins)), [f"{b}\n(n={int(bt[bt[bin_by] == b]['runs'].iloc[0])})" for b in bins],
                  fontsize=7)
    ax.set_xlabel(bin_by)
    ax.set_ylabel("success [%] (Wilson 95 %)")
    ax.set_ylim(0, 105)
    ax.legend(fontsize=7)
    return save_figure(fig, out / f"success_by_{_slug(bin_by)}.png")


def plot_curves(ct: pd.DataFrame, x: str, curves: list[str], out: Path, how: str) -> Path:
    """Robustness curves: each metric of ``curves`` against ``x``, one line per group, its interval as a band."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(curves), figsize=(4.2 * len(curves), 3.6), squeeze=False)
    for ax, m in zip(axes[0], curves):
        col, lo, hi = ("success_rate", "success_lo", "success_hi") if m == "success" else \
            (f"{m}_median", f"{m}_lo", f"{m}_hi")
        if col not in ct:
            ax.set_title(f"{m}: not logged", fontsize=8)
            continue
        scale = 100 if m == "success" else 1
        for g, d in ct.groupby("group", sort=True):
            d = d.sort_values(x)
            line = ax.plot(d[x], d[col] * scale, "o-", label=g)[0]
            ax.fill_between(d[x], d[lo] * scale, d[hi] * scale, color=line.get_color(), alpha=0.15)
        if m == "success":
            ax.set_ylim(0, 105)
        ax.set_xlabel(x)
        ax.set_ylabel("success [%] (Wilson 95 %)" if m == "success" else f"{m}\n(median, {interval_name(how)})",
                      fontsize=8)
        ax.set_xticks(sorted(ct[x].unique()), [canonical(v) for v in sorted(ct[x].unique())], fontsize=7)
        ax.legend(fontsize=7)
    return save_figure(fig, out / f"robustness_vs_{_slug(x)}.png")
