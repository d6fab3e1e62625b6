"""The report's gloss section: the ISO 2813 gloss units each printed wedge's surface would
read, from the fitted parameters, with their uncertainty (docs/gloss.md).

`gloss_record` computes it for results.json (`gloss`), `gloss_html` shows it in report.html.
Both are self-contained: a failure is recorded and shown as one sentence, never a lost report.
"""

from __future__ import annotations

import html
import time
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import UserError

if TYPE_CHECKING:
    from ._jsontypes import Record
    from .gloss import GlossRow

REPORT_DRAWS = 16
"""Posterior draws whose gloss the report computes (`stairfit predict --gloss --fit` takes
`stairfit.gloss.GLOSS_DRAWS`, 64): 16 x 18 evaluations cost about 40 s of a lab fit with GGX
facets on the 2-core machine (docs/gloss.md §2), 64 would cost minutes; the 16-84% interval
of 16 draws is good to about a fifth of a standard deviation."""

REPORT_AZIMUTH_DEG = 0.0
"""The report's orientation: the plane of incidence across the layer lines, the source on the
downhill side, as the photographs' light (`stairfit predict --gloss --azimuth-deg` gives the
others)."""


def gloss_record(results: Record, out: Path) -> Record:
    """results.json's `gloss`: one row per fitted wedge and ISO 2813 geometry (the specimen's
    own angles and layer, across the layer lines), or `{"error": ...}` when it could not be
    computed. `out`: the fit folder (for chain.npz)."""
    from . import gloss

    t0 = time.perf_counter()
    try:
        model = gloss.gloss_model_from_results(results, out, REPORT_DRAWS)
        specimen = results.get("specimen") or {}
        wedges = [float(w["angle_deg"]) for w in specimen.get("wedges", [])]
        if not wedges or model.layer_um is None:
            return {"error": "results.json has no specimen record (wedge angles, layer)"}
        rows = gloss.gloss_table(model, wedges, model.layer_um, (REPORT_AZIMUTH_DEG,))
        per_wedge = len(rows) // len(wedges)  # gloss_table's order: wedge by wedge
    except (UserError, ValueError) as e:
        return {"error": str(e)}
    return {
        "azimuth_deg": REPORT_AZIMUTH_DEG,
        "orientation": "the glossmeter's plane of incidence across the layer lines, its "
        "source on the downhill side",
        "layer_lines": gloss.layer_lines(REPORT_AZIMUTH_DEG),
        "layer_um": model.layer_um,
        "facets": model.kind,
        "uncertainty": model.uncertainty,
        "notes": list(model.notes),
        "elapsed_s": time.perf_counter() - t0,
        "rows": [_row(specimen["wedges"][i // per_wedge]["name"], r) for i, r in enumerate(rows)],
    }


def _row(wedge: str, row: GlossRow) -> Record:
    """A `gloss.GlossRow` as a results.json record with its wedge's name."""
    return {"wedge": wedge, **{k: v for k, v in row._asdict().items() if k != "uncertainty"}}


def _cell(row: Record) -> str:
    """`12.31 [12.10, 12.62]` (posterior) or `12.31 ± 0.21` (delta method) or `12.31`: two
    decimals, a glossmeter's 0.1 GU and one more."""
    value = f"{row['gloss']:.2f}"
    if row["p16"] is not None:
        return f"{value} [{row['p16']:.2f}, {row['p84']:.2f}]"
    if row["sd"] is not None:
        return f"{value} &plusmn; {row['sd']:.2f}"
    return value


def gloss_html(record: Record) -> str:
    """The report's section: a table of wedges x geometries and what it assumes."""
    e = html.escape
    head = "<h2>Gloss units (ISO 2813)</h2>"
    if "error" in record:
        return f"{head}<p>Not computed: {e(record['error'])}.</p>"
    angles = sorted({r["angle_deg"] for r in record["rows"]})
    by_wedge: dict[str, dict[float, Record]] = {}
    for r in record["rows"]:
        by_wedge.setdefault(r["wedge"], {})[r["angle_deg"]] = r
    rows = "".join(
        f"<tr><td>{e(name)}</td><td>{next(iter(cells.values()))['wedge_deg']:g}</td>"
        + "".join(f"<td>{_cell(cells[a])}</td>" for a in angles)
        + "</tr>"
        for name, cells in by_wedge.items()
    )
    spread = ("posterior median's 16-84% interval in brackets" if "posterior" in
              record["uncertainty"] else "&plusmn; one standard deviation by the delta method"
              if "delta" in record["uncertainty"] else "no uncertainty")  # fmt: skip
    notes = "".join(f"<li>{e(n)}</li>" for n in record["notes"])
    return (
        f"{head}<p>What a glossmeter would read on each wedge's printed surface (gloss units: "
        "100 = the polished black glass standard of index 1.567), from the fitted parameters "
        f"({e(record['facets'])} facets, layers of {record['layer_um']:g} um), with "
        f"{e(record['orientation'])}; value at the optimum, {spread} "
        f"({e(record['uncertainty'])}). Other orientations and surfaces: <code>stairfit predict "
        "--gloss --fit FITDIR</code> (docs/gloss.md).</p><table><tr><th>wedge</th><th>angle "
        "(deg)</th>"
        + "".join(f"<th>{a:g} deg</th>" for a in angles)
        + f"</tr>{rows}</table>"
        + (f"<ul>{notes}</ul>" if notes else "")
    )
