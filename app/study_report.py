"""The study table and page: `study.csv` (one row per specimen) and `study.html`.

Built from the folders' reports (app/study_task.py), each carrying its results.json;
columns and figures are described in docs/study.md. Degrees in every column and on every axis
[conventions §1]; a parameter's interval is its posterior 95% interval (2.5-97.5%), or, without
a posterior, the least-squares value +- 1.96 standard errors.
"""

from __future__ import annotations

import csv
import datetime
import html
import io
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from .study_task import FAILED, FITTED, INTERRUPTED, SKIPPED, FolderReport

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from ._jsontypes import JSONObject, Record

Z95 = 1.959963984540054
"""The 97.5% quantile of the standard normal: a least-squares 95% interval is +- Z95 stderr."""
FIGURES = "study-figures"
MAX_CATEGORIES = 30
"""A string metadata key with more distinct values than this gets no plot (not a grouping)."""
BASE_COLUMNS = (
    "folder",
    "output",
    "status",
    "error",
    "note",
    "chosen_model",
    "chi2",
    "dof",
    "reduced_chi2",
    "n_used",
    "posterior",
    "layer_um",
    "material",
    "wedges_deg",
    "n_photos",
)
RUN_COLUMNS = (
    "measure_s",
    "fit_s",
    "posterior_s",
    "started_utc",
    "elapsed_s",
    "host",
    "pid",
    "peak_rss_mb",
    "jax_cache",
)
PARAMETER_FIELDS = ("", "_lo95", "_hi95", "_stderr", "_from")
"""Per parameter P: P (posterior median, least-squares value, or the fixed value), P_lo95 and
P_hi95 (the interval), P_stderr (least squares) and P_from (posterior, least_squares, fixed)."""


# --- rows -----------------------------------------------------------------------------------


def parameter_cells(results: JSONObject) -> dict[str, Record]:
    """{name: {value, lo95, hi95, stderr, from}} of every free and fixed parameter."""
    cells: dict[str, Record] = {}
    for rec in results.get("parameters", []):
        ls, po = rec["least_squares"], rec.get("posterior")
        se = ls.get("stderr")
        if po is not None:
            cell = {"value": po["median"], "lo95": po["p2_5"], "hi95": po["p97_5"]}
            cell["from"] = "posterior"
        elif se is not None:
            cell = {"value": ls["value"], "lo95": ls["value"] - Z95 * se}
            cell |= {"hi95": ls["value"] + Z95 * se, "from": "least_squares"}
        else:
            cell = {"value": ls["value"], "lo95": None, "hi95": None, "from": "least_squares"}
        cells[rec["name"]] = cell | {"stderr": se}
    for name, value in results.get("fixed_parameters", {}).items():
        if name not in cells:
            cells[name] = {"value": value, "lo95": None, "hi95": None, "stderr": None}
            cells[name]["from"] = "fixed"
    return cells


def study_row(report: FolderReport) -> Record:
    """One row of the study table: the folder, its status, fit, scene, metadata and run."""
    results = report.get("results") or {}
    scene = report.get("scene") or {}
    run = report.get("run") or {}
    diagnostics = results.get("diagnostics", {})
    ls = diagnostics.get("least_squares", {})
    # an up-to-date result's timings are those of the earlier run that fitted it
    timings = diagnostics.get("timings_s", {}) if report["status"] == FITTED else {}
    row: Record = {
        "folder": report["folder"],
        "output": report["output"] if results else "",
        "status": report["status"],
        "error": report.get("error") or "",
        "note": report.get("note") or "",
        "chosen_model": results.get("model_selection", {}).get("chosen", ""),
        "chi2": ls.get("chi2"),
        "dof": ls.get("dof"),
        "reduced_chi2": ls.get("reduced_chi2"),
        "n_used": ls.get("n_used"),
        "posterior": results.get("settings", {}).get("posterior") if results else None,
        "layer_um": scene.get("layer_um"),
        "material": scene.get("material"),
        "wedges_deg": ";".join(f"{w:g}" for w in scene.get("wedges_deg", [])),
        "n_photos": scene.get("n_photos"),
    }
    row |= {f"meta.{k}": v for k, v in scene.get("metadata", {}).items()}
    for name, cell in parameter_cells(results).items():
        for suffix in PARAMETER_FIELDS:
            row[f"{name}{suffix}"] = cell[suffix.lstrip("_") or "value"]
    row |= {k: timings.get(k) for k in RUN_COLUMNS[:3]}
    row |= {k: run.get(k) for k in RUN_COLUMNS[3:]}
    if run.get("started") is not None:
        when = datetime.datetime.fromtimestamp(run["started"], datetime.UTC)
        row["started_utc"] = when.isoformat(timespec="milliseconds")
    return row


def columns(rows: Sequence[Record]) -> list[str]:
    """Base columns, then metadata, then parameters (first appearance order), then the run."""
    seen = dict.fromkeys(key for row in rows for key in row)  # ordered, unique
    fixed = set(BASE_COLUMNS) | set(RUN_COLUMNS)
    meta = [k for k in seen if k.startswith("meta.")]
    params = [k for k in seen if k not in fixed and not k.startswith("meta.")]
    return [*BASE_COLUMNS, *meta, *params, *RUN_COLUMNS]


def sort_rows(reports: Sequence[FolderReport]) -> list[Record]:
    """The rows of the table, in the order of the folders' paths."""
    return [study_row(r) for r in sorted(reports, key=lambda r: r["folder"])]


def csv_text(rows: Sequence[Record]) -> str:
    """The study table as CSV text (empty cells for missing values)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns(rows), restval="", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _cell(v) for k, v in row.items()})
    return buf.getvalue()


def _cell(v: object) -> object:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    return v  # floats as repr: the shortest text that reads back exactly


# --- files ----------------------------------------------------------------------------------


def write_study(out: Path, reports: Sequence[FolderReport]) -> None:
    """study.csv, the figures and study.html in OUT (each file replaced only when complete)."""
    from .outputs import atomic_text, staged_folder

    rows = sort_rows(reports)
    with atomic_text(out / "study.csv") as fh:
        fh.write(csv_text(rows))
    with staged_folder(out / FIGURES, force=True, command="study") as tmp:
        figures = write_figures(rows, tmp)
    with atomic_text(out / "study.html") as fh:
        fh.write(study_html(rows, figures))


def parameters_of(rows: Sequence[Record]) -> list[str]:
    """Parameters that some row fitted (not only fixed), in column order."""
    cols = columns(rows)
    names = [c for c in cols if f"{c}_from" in cols]
    return [n for n in names if any(r.get(f"{n}_from") not in (None, "fixed") for r in rows)]


def plot_axes(rows: Sequence[Record]) -> list[tuple[str, bool]]:
    """The x axes worth a figure: (column, numeric) for layer_um and every metadata key whose
    values differ between specimens (strings: at most MAX_CATEGORIES groups)."""
    keys = ["layer_um", *[c for c in columns(rows) if c.startswith("meta.")]]
    axes = []
    for key in keys:
        values = [r.get(key) for r in rows if r.get(key) is not None]
        distinct = set(values)
        numeric = all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
        if len(distinct) >= 2 and (numeric or len(distinct) <= MAX_CATEGORIES):
            axes.append((key, numeric))
    return axes


def write_figures(rows: Sequence[Record], folder: Path) -> list[tuple[str, str]]:
    """Every parameter per specimen, and against each varying x axis; [(title, file)]."""
    from .figures import save

    done = [r for r in rows if r["status"] in (FITTED, SKIPPED)]
    params = parameters_of(done)
    if not done or not params:
        return []
    labels = [r["output"] for r in done]  # unique, unlike the folders' names
    figures = [("every parameter per specimen", "by_specimen.png")]
    save(parameter_figure(done, params, list(range(len(done))), labels, "specimen"),
         folder / figures[0][1])  # fmt: skip
    for key, numeric in plot_axes(done):
        values = [r.get(key) for r in done]
        keep = [i for i, v in enumerate(values) if v is not None]
        sub = [done[i] for i in keep]
        if numeric:
            x, ticks = [float(values[i]) for i in keep], None
        else:
            groups = sorted({str(values[i]) for i in keep})
            x, ticks = [groups.index(str(values[i])) for i in keep], groups
        name = "vs_" + re.sub(r"[^A-Za-z0-9_-]+", "_", key) + ".png"
        save(parameter_figure(sub, params, x, ticks, key), folder / name)
        figures.append((f"every parameter against {key}", name))
    return [(title, f"{FIGURES}/{name}") for title, name in figures]


def parameter_figure(
    rows: Sequence[Record],
    params: Sequence[str],
    x: Sequence[float],
    ticks: Sequence[str] | None,
    xlabel: str,
) -> Figure:
    """One panel per parameter: value with its 95% interval against x (hollow = fixed)."""
    import matplotlib.pyplot as plt
    import numpy as np

    from .figures import fixed_layout

    ncol = min(3, len(params))
    nrow = math.ceil(len(params) / ncol)
    bottom = 1.4 if ticks is not None else 0.55  # inches: room for slanted labels
    size = (4.2 * ncol, 2.6 * nrow + bottom + 0.2)
    fig, axes = plt.subplots(nrow, ncol, figsize=size, squeeze=False)
    xs = np.asarray(x, float)
    for ax, name in zip(axes.flat, params, strict=False):
        y = np.array([_num(r.get(name)) for r in rows])
        lo = np.array([_num(r.get(f"{name}_lo95")) for r in rows])
        hi = np.array([_num(r.get(f"{name}_hi95")) for r in rows])
        fixed = np.array([r.get(f"{name}_from") == "fixed" for r in rows])
        err = np.vstack([np.nan_to_num(y - lo), np.nan_to_num(hi - y)])
        ax.errorbar(xs[~fixed], y[~fixed], yerr=err[:, ~fixed], fmt="o", ms=4, capsize=2)
        ax.plot(xs[fixed], y[fixed], "o", mfc="none", color="tab:gray", label="fixed")
        ax.set(xlabel=xlabel, ylabel=name, title=name)
        if ticks is not None:
            ax.set_xticks(range(len(ticks)), ticks, rotation=45, ha="right", fontsize="small")
    for ax in axes.flat[len(params) :]:
        ax.axis("off")
    fig.suptitle("value and 95% interval per specimen (hollow grey: fixed by the chosen model)")
    fixed_layout(fig, nrow, ncol, bottom=bottom, top=0.7, wspace=0.9, hspace=1.2)
    return fig


def _num(v: object) -> float:
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else math.nan


def study_html(rows: Sequence[Record], figures: Sequence[tuple[str, str]]) -> str:
    """One page: the counts, the figures and the table with links to every folder's report."""
    e = html.escape
    params = parameters_of([r for r in rows if r["status"] in (FITTED, SKIPPED)])
    meta = [c for c in columns(rows) if c.startswith("meta.")]
    head = ["folder", "status", "model", *params, *meta]
    body = "".join(_html_row(r, params, meta) for r in rows)
    n = {s: sum(r["status"] == s for r in rows) for s in (FITTED, SKIPPED, FAILED, INTERRUPTED)}
    counts = ", ".join(f"{v} {k}" for k, v in n.items() if v)
    imgs = "".join(
        f"<h3>{e(title)}</h3><img src='{e(src)}' style='max-width:100%'>" for title, src in figures
    )
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>stairfit study</title>
<style>body{{font-family:sans-serif;max-width:1400px;margin:auto}}td,th{{padding:2px 8px}}
table{{border-collapse:collapse}}tr:nth-child(even){{background:#f3f3f3}}
.failed,.interrupted{{color:#a00}}</style></head><body>
<h1>stairfit study: {len(rows)} specimens</h1><p>{e(counts)}. Values: posterior median (or
least squares) with the 95% interval; every column in study.csv; rules in docs/study.md.</p>
{imgs}<h2>Specimens</h2><table><tr>{"".join(f"<th>{e(h)}</th>" for h in head)}</tr>{body}
</table></body></html>
"""


def _html_row(row: Record, params: Sequence[str], meta: Sequence[str]) -> str:
    e = html.escape
    folder = e(row["folder"])
    link = f"<a href='{e(row['output'])}/report.html'>{folder}</a>" if row["output"] else folder
    status = e(row["status"]) + (f": {e(row['error'])}" if row["error"] else "")
    status += f" ({e(row['note'])})" if row["note"] else ""
    cells = [link, f"<span class='{e(row['status'])}'>{status}</span>", e(row["chosen_model"])]
    for name in params:
        v, lo, hi = (row.get(f"{name}{s}") for s in ("", "_lo95", "_hi95"))
        if v is None:
            cells.append("")
        elif lo is None or hi is None:
            fixed = " (fixed)" if row.get(f"{name}_from") == "fixed" else ""
            cells.append(f"{v:.4g}{fixed}")
        else:
            cells.append(f"{v:.4g} [{lo:.4g}, {hi:.4g}]")
    cells += [e(str(row.get(m, ""))) for m in meta]
    return "<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>"


def print_summary(out: Path, reports: Sequence[FolderReport]) -> None:
    """The lines printed at the end of a study."""
    n = {s: sum(r["status"] == s for r in reports) for s in (FITTED, SKIPPED, FAILED)}
    print(
        f"stairfit study: {len(reports)} folders: {n[FITTED]} fitted, {n[SKIPPED]} up to date "
        f"(skipped), {n[FAILED]} failed"
    )
    for r in sorted(reports, key=lambda r: r["folder"]):
        if r["status"] == FAILED:
            print(f"  failed: {r['folder']}: {r['error']}")
    print(f"  table: {out / 'study.csv'}; page: {out / 'study.html'}")
