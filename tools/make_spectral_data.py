"""Regenerate `model/data/spectral_tables.json` from colour-science (issue 14: cold start).

stairfit's spectral code needs four tables: the CIE 1931 2-degree colour-matching functions,
the CIE illuminants, the measured camera sensitivities and the XYZ -> linear sRGB matrix.
colour-science has them all, but `import colour` also imports `colour.plotting`, matplotlib and
SciPy (seconds of every process's start-up; docs/performance.md), so the tables are shipped as
package data, copied here from colour-science's own datasets. Run after upgrading
colour-science, then `pytest tests/model/test_spectral_data.py` (which checks the shipped tables
equal colour-science's):

    python tools/make_spectral_data.py
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

OUT = Path(__file__).resolve().parents[1] / "model" / "data" / "spectral_tables.json"
CMFS = "CIE 1931 2 Degree Standard Observer"


def _table(wavelengths: Any, values: Any) -> dict[str, Any]:
    """One tabulated spectrum (or a few, as columns) as plain lists of floats."""
    return {
        "wavelength_nm": [float(x) for x in np.asarray(wavelengths, float)],
        "values": np.asarray(values, float).tolist(),
    }


def build_tables() -> dict[str, Any]:
    """Every table stairfit reads, straight from colour-science's datasets."""
    import colour

    cmfs = colour.MSDS_CMFS[CMFS]
    srgb = colour.RGB_COLOURSPACES["sRGB"]
    return {
        "source": f"colour-science {colour.__version__} (BSD-3-Clause), model/_spectral_data.py",
        "cmfs": {CMFS: _table(cmfs.wavelengths, cmfs.values)},
        "illuminants": {
            name: _table(sd.wavelengths, sd.values) for name, sd in colour.SDS_ILLUMINANTS.items()
        },
        "cameras": {
            name: _table(m.wavelengths, m.values)
            for name, m in colour.MSDS_CAMERA_SENSITIVITIES.items()
        },
        "srgb_matrix_xyz_to_rgb": np.asarray(srgb.matrix_XYZ_to_RGB, float).tolist(),
    }


def main() -> None:
    """Write the tables (compact JSON: shortest round-trip float representations)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", type=Path, default=OUT, help="JSON file to write")
    args = parser.parse_args()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(build_tables(), separators=(",", ":"), allow_nan=False)
    args.output.write_text(text + "\n")
    print(f"wrote {args.output} ({len(text) / 1024:.0f} KiB)")


if __name__ == "__main__":
    main()
