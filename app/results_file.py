"""Reading a fit's results.json back: the parameters' identities and their least-squares
covariance (for `stairfit.explore`, `stairfit.gloss` and `stairfit predict --fit`), refusing
the files of an older stairfit in one line.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ._jsontypes import JSONObject

OLDER_RESULTS = "was written by an older stairfit (no parameter records): re-run `stairfit fit`"
"""Why a results.json without the `parameter` and `wedge` fields is refused: a parameter's
identity is never parsed back from its display name."""


class OlderResultsError(ValueError):
    """A results.json written before its parameter records had `parameter` and `wedge`."""


def parameter_key(rec: JSONObject) -> tuple[str, int | None]:
    """`(param, wedge)` of a results.json parameter record: the fitting layer's identity of the
    parameter (`("sigma_rad", 2)` for wedge 2's own width, shown as `sigma_deg[2: ...]`).

    Raises:
        OlderResultsError: the record has no `parameter` or `wedge` field.
    """
    if "parameter" not in rec or "wedge" not in rec:
        raise OlderResultsError(f"results.json {OLDER_RESULTS} (record {rec.get('name')!r})")
    return str(rec["parameter"]), None if rec["wedge"] is None else int(rec["wedge"])


def check_parameter_records(results: JSONObject, fit_dir: str | Path) -> None:
    """Every parameter record of results.json names its `parameter` and `wedge`.

    Raises:
        OlderResultsError: one line naming the folder and the fix (re-run `stairfit fit`).
    """
    if any("parameter" not in r or "wedge" not in r for r in results.get("parameters", [])):
        raise OlderResultsError(f"results.json in {fit_dir} {OLDER_RESULTS}")


def covariance_from_results(results: JSONObject) -> np.ndarray | None:
    """The least-squares covariance (display units) from stderr and correlation, or None."""
    corr = results["correlation"]["matrix"]
    se = [p["least_squares"]["stderr"] for p in results["parameters"]]
    if corr is None or any(s is None for s in se):
        return None
    s = np.asarray(se, float)
    return np.asarray(corr, float) * np.outer(s, s)
