"""Plots and tables of an evaluation, in the style of the paper's figures.

Input is the ``results`` dict written to ``metrics.json`` by ``gmmgp eval``::

    {"methods": {"gmmgp": {"field": binned metrics, "train_seconds": {...},
                           "test_seconds": float, "surface": {...} | None}, ...},
     "bins": [[lo, hi], ...], ...}

Figures (PNG, written atomically): RMSE against distance for the SDF and the EDF
(paper Fig. rmse), log-likelihood against distance for the SDF and the EDF
(Fig. ll), training and testing times per method (Fig. time_compare).
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np

from ._atomic import atomic_path, atomic_write_text
from ._json import jsonable

__all__ = ["plot_metrics", "metrics_rows", "write_metrics_csv", "write_metrics_json",
           "markdown_table", "METHOD_STYLE"]

#: Colour and marker per method, the same in every figure.
METHOD_STYLE = {
    "gmmgp": ("tab:red", "o"),
    "hgmm": ("tab:blue", "s"),
    "gpis": ("tab:green", "^"),
    "loggpis": ("tab:purple", "v"),
}
_METRICS = (("rmse_sdf", "RMSE SDF (m)"), ("rmse_edf", "RMSE EDF (m)"),
            ("ll_sdf", "log-likelihood SDF"), ("ll_edf", "log-likelihood EDF"))


def _style(name):
    return METHOD_STYLE.get(name.split(":")[0], ("tab:gray", "d"))


def _centres(bins):
    return [0.5 * (lo + hi) for lo, hi in bins]


def _finite(v):
    return v is not None and isinstance(v, (int, float)) and math.isfinite(v)


def plot_metrics(results: dict, out_dir, prefix: str = "", title: str = "") -> list:
    """Write the paper-style figures of ``results`` into ``out_dir``.

    Returns
    -------
    list of Path: ``{prefix}rmse_sdf.png``, ``rmse_edf.png``, ``ll_sdf.png``,
    ``ll_edf.png``, ``times.png`` and the 2 x 3 overview ``metrics.png``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    methods = results["methods"]
    x = _centres(results["bins"])
    written = []

    def panel(ax, key, label):
        for name, res in methods.items():
            y = res["field"][key]
            if not any(_finite(v) for v in y):
                continue
            c, m = _style(name)
            ax.plot(x, [v if _finite(v) else np.nan for v in y], marker=m, color=c,
                    label=name)
        ax.set_xlabel("distance to training points (m)")
        ax.set_ylabel(label)
        if key.startswith("rmse"):
            ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)

    def times_panel(ax):
        names = list(methods)
        train = [sum(methods[n]["train_seconds"].values()) for n in names]
        test = [methods[n]["test_seconds"] for n in names]
        idx = np.arange(len(names))
        ax.bar(idx - 0.2, train, 0.4, label="training", color="tab:orange")
        ax.bar(idx + 0.2, test, 0.4, label="testing", color="tab:cyan")
        ax.set_xticks(idx, names)
        ax.set_ylabel("time (s)")
        ax.set_yscale("log")
        nq = results.get("n_queries")
        ax.set_title(f"training / testing ({nq} queries)" if nq else "training / testing",
                     fontsize=9)
        ax.legend(fontsize=8)
        ax.grid(True, axis="y", alpha=0.3)

    for key, label in _METRICS:
        fig, ax = plt.subplots(figsize=(4.5, 3.4), constrained_layout=True)
        panel(ax, key, label)
        if title:
            ax.set_title(title, fontsize=9)
        written.append(_save(fig, out_dir / f"{prefix}{key}.png"))
        plt.close(fig)
    fig, ax = plt.subplots(figsize=(4.5, 3.4), constrained_layout=True)
    times_panel(ax)
    written.append(_save(fig, out_dir / f"{prefix}times.png"))
    plt.close(fig)

    fig, axs = plt.subplots(2, 3, figsize=(13, 7), constrained_layout=True)
    for ax, (key, label) in zip([axs[0, 0], axs[0, 1], axs[1, 0], axs[1, 1]], _METRICS):
        panel(ax, key, label)
    times_panel(axs[0, 2])
    _surface_panel(axs[1, 2], methods)
    if title:
        fig.suptitle(title)
    written.append(_save(fig, out_dir / f"{prefix}metrics.png"))
    plt.close(fig)
    return written


def _surface_panel(ax, methods):
    names = [n for n, r in methods.items() if r.get("surface")]
    if not names:
        ax.axis("off")
        ax.text(0.5, 0.5, "no surface metrics", ha="center", va="center")
        return
    idx = np.arange(len(names))
    ch = [methods[n]["surface"]["chamfer"] for n in names]
    h95 = [methods[n]["surface"]["hausdorff95"] for n in names]
    ax.bar(idx - 0.2, ch, 0.4, label="Chamfer", color="tab:olive")
    ax.bar(idx + 0.2, h95, 0.4, label="Hausdorff 95 %", color="tab:brown")
    ax.set_xticks(idx, names)
    ax.set_ylabel("surface to reference (m)")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)


def _save(fig, path: Path) -> Path:
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=120)
    return path


def metrics_rows(results: dict) -> list:
    """One row per (method, bin) plus an ``all`` row per method (for CSV and tables)."""
    rows = []
    for name, res in results["methods"].items():
        f = res["field"]
        train = sum(res["train_seconds"].values())
        surf = res.get("surface") or {}
        for i, (lo, hi) in enumerate(f["bins"]):
            rows.append(dict(method=name, bin_lo=lo, bin_hi=hi, n=f["n"][i],
                             rmse_sdf=f["rmse_sdf"][i], rmse_edf=f["rmse_edf"][i],
                             ll_sdf=f["ll_sdf"][i], ll_edf=f["ll_edf"][i],
                             train_seconds=train, test_seconds=res["test_seconds"],
                             chamfer=surf.get("chamfer"), hausdorff=surf.get("hausdorff")))
        a = f["all"]
        rows.append(dict(method=name, bin_lo=f["bins"][0][0], bin_hi=f["bins"][-1][1],
                         n=a["n"], rmse_sdf=a["rmse_sdf"], rmse_edf=a["rmse_edf"],
                         ll_sdf=a["ll_sdf"], ll_edf=a["ll_edf"], train_seconds=train,
                         test_seconds=res["test_seconds"], chamfer=surf.get("chamfer"),
                         hausdorff=surf.get("hausdorff"), all=True))
    return rows


def write_metrics_csv(results: dict, path) -> Path:
    """``metrics.csv``: one row per method and bin; the ``all`` rows span every bin."""
    cols = ["method", "bin_lo", "bin_hi", "n", "rmse_sdf", "rmse_edf", "ll_sdf", "ll_edf",
            "train_seconds", "test_seconds", "chamfer", "hausdorff"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols + ["all_bins"])
    for r in metrics_rows(results):
        w.writerow([_fmt_csv(r.get(c)) for c in cols] + [int(bool(r.get("all")))])
    return atomic_write_text(path, buf.getvalue())


def _fmt_csv(v):
    if v is None:
        return ""
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else repr(v)
    return v


def write_metrics_json(results: dict, path) -> Path:
    """``metrics.json`` with NaN written as null (strict JSON)."""
    return atomic_write_text(path, json.dumps(jsonable(results, nan_as_null=True), indent=2))


def markdown_table(results: dict, metrics=("rmse_sdf", "rmse_edf", "ll_sdf", "ll_edf")) -> str:
    """Markdown tables: the field metrics (one row per metric and method, one column
    per distance bin, plus all bins together), then times and surface distances."""
    bins = results["bins"]
    names = {"rmse_sdf": "RMSE SDF (mm)", "rmse_edf": "RMSE EDF (mm)",
             "ll_sdf": "LL SDF", "ll_edf": "LL EDF"}
    heads = ["metric", "method"] + [f"{lo:g}-{hi:g} m" for lo, hi in bins] + ["all"]
    lines = ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for m in metrics:
        scale = 1000.0 if m.startswith("rmse") else 1.0
        for name, res in results["methods"].items():
            vals = res["field"][m] + [res["field"]["all"][m]]
            if not any(_finite(v) for v in vals):
                continue
            lines.append("| " + " | ".join([names.get(m, m), name]
                                            + [_fmt_md(v, scale) for v in vals]) + " |")
    lines += ["", "| method | train s | test s | Chamfer mm | Hausdorff mm | "
              "Hausdorff 95 % mm |", "|---|---|---|---|---|---|"]
    for name, res in results["methods"].items():
        surf = res.get("surface") or {}
        lines.append("| " + " | ".join([
            name, f"{sum(res['train_seconds'].values()):.2f}", f"{res['test_seconds']:.2f}",
            _fmt_md(surf.get("chamfer"), 1000.0), _fmt_md(surf.get("hausdorff"), 1000.0),
            _fmt_md(surf.get("hausdorff95"), 1000.0)]) + " |")
    n = results["methods"][next(iter(results["methods"]))]["field"]["n"]
    lines += ["", f"Queries per bin: {', '.join(str(k) for k in n)}. LL = mean predictive "
              "log-likelihood (nats); '-' = not applicable (Log-GPIS has no sign) or empty."]
    return "\n".join(lines) + "\n"


def _fmt_md(v, scale=1.0):
    if not _finite(v):
        return "-"
    v = v * scale
    return f"{v:.1f}" if abs(v) >= 10 else f"{v:.2f}"
