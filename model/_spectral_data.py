"""The spectral datasets stairfit ships: CIE colour-matching functions, CIE illuminants, camera
sensitivities and the sRGB matrix [conventions §8].

They are copies of colour-science's datasets (BSD-3-Clause), written to
`model/data/spectral_tables.json` by `tools/make_spectral_data.py` and checked against
colour-science by `tests/model/test_spectral_data.py`. Shipping them keeps `import colour` (which
also imports matplotlib and SciPy, seconds of start-up) out of every stairfit process (issue 14).
Sources, as colour-science cites them:

* `CMFS_NAME`: the CIE 1931 2-degree standard observer, 360-830 nm every 1 nm (colour-science's
  `MSDS_CMFS`, from CVRL's "Older CIE Standards").
* illuminants: colour-science's `SDS_ILLUMINANTS`: CIE 15:2004 tables (A, B, C, D50-D75, E,
  FL1-FL12, FL3.1-FL3.15, HP1-HP5), CIE 015:2018 (LED-*, ID50, ID65; D60 computed from the
  D series) and ISO 7589:2002 (the photographic illuminants).
* cameras: colour-science's `MSDS_CAMERA_SENSITIVITIES`, the NPL measurements of a Nikon 5100
  and a Sigma SD Merrill (Darrodi, Finlayson, Goodman & Mackiewicz, "Reference data set for
  camera spectral sensitivity estimation", JOSA A 32, 381 (2015)).
* `srgb_matrix_xyz_to_rgb`: XYZ -> linear sRGB, IEC 61966-2-1:1999.

The file is read once per process, on first use (nothing happens on import).
"""

from __future__ import annotations

import functools
import json
import re
from importlib import resources
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

DATA_FILE = "spectral_tables.json"
CMFS_NAME = "CIE 1931 2 Degree Standard Observer"


class Tabulated(NamedTuple):
    """A tabulated spectrum: `values` (n,) or several as columns (n, m) at `wavelength_nm`."""

    wavelength_nm: NDArray
    values: NDArray


class SpectralTables(NamedTuple):
    """Every shipped table, keyed by colour-science's names."""

    cmfs: dict[str, Tabulated]
    illuminants: dict[str, Tabulated]
    cameras: dict[str, Tabulated]
    srgb_matrix_xyz_to_rgb: NDArray
    source: str


def _tabulated(d: dict[str, Any]) -> Tabulated:
    return Tabulated(np.asarray(d["wavelength_nm"], float), np.asarray(d["values"], float))


@functools.cache
def tables() -> SpectralTables:
    """The shipped tables, read from the package data on first use (then kept)."""
    text = resources.files(__package__).joinpath("data", DATA_FILE).read_text()
    raw = json.loads(text)
    return SpectralTables(
        cmfs={k: _tabulated(v) for k, v in raw["cmfs"].items()},
        illuminants={k: _tabulated(v) for k, v in raw["illuminants"].items()},
        cameras={k: _tabulated(v) for k, v in raw["cameras"].items()},
        srgb_matrix_xyz_to_rgb=np.asarray(raw["srgb_matrix_xyz_to_rgb"], float),
        source=str(raw["source"]),
    )


def canonical(name: str) -> str:
    """A name compared without case, spaces, '-' or '_' ("led b1" finds "LED-B1"), as
    colour-science's canonical mappings compare their keys."""
    return re.sub(r"[\s_-]", "", name.lower())


def lookup(mapping: dict[str, Tabulated], name: str) -> Tabulated:
    """`mapping[name]`, else the entry whose canonical name matches; KeyError if none does."""
    if name in mapping:
        return mapping[name]
    key = canonical(name)
    for k, v in mapping.items():
        if canonical(k) == key:
            return v
    raise KeyError(name)
