"""`stairfit predict --gloss`: gloss units (ISO 2813) of printed surfaces, as CSV.

Parses and checks the gloss options of `predict`, calls `stairfit.gloss` (app/gloss.py) and
writes one row per surface angle x azimuth x geometry (docs/gloss.md). Degrees at this edge.
"""

from __future__ import annotations

import argparse
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .. import _ranges
from ..errors import StairfitWarning, UserError
from ._predict_checks import Given, RowWriter, check_number

if TYPE_CHECKING:
    from ..gloss import GlossModel

FACETS = ("gaussian", "ggx", "beckmann")
"""The facets `--facets` offers (`stairfit.model.LAB_KERNELS`)."""

GLOSS_COLUMNS = (
    "wedge_deg", "wavelength_nm", "n", "layer_um", "azimuth_deg", "layer_lines", "geometry_deg",
    "gloss_gu", "specular_gu", "body_gu", "median_gu", "p16_gu", "p84_gu", "sd_gu",
    "uncertainty", "facets", "parameters",
)  # fmt: skip
"""The columns of the gloss table; it begins like every table `predict` writes (`CSV_START`)."""

MAX_GLOSS_ROWS = 5000
"""The most rows (surfaces x azimuths x geometries) one `--gloss` run computes: each row is a
quadrature over the source and the receptor (up to tens of milliseconds, times the posterior
draws); split a larger request."""

_FIT_EXCLUSIVE = ("material", "n", "sigma_deg", "delta_n", "edge_radius_um", "facets", "alpha",
                  "body_albedo")  # fmt: skip
_GLOSS_ONLY = ("fit", "azimuth_deg", "geometry_deg", "facets", "alpha", "body_albedo")
_NOT_WITH_GLOSS = ("theta_i_deg", "theta_o_deg", "wavelength_nm", "fillet_radius_um")


def add_gloss_options(p: argparse.ArgumentParser) -> None:
    """The options of `predict --gloss` (an argument group of their own)."""
    g = p.add_argument_group("gloss units, ISO 2813 (--gloss; docs/gloss.md)")
    g.add_argument(
        "--gloss", action="store_true",
        help="write the gloss units at the 20, 60 and 85 deg geometries of every --wedge-deg "
        "(the surface's angle to the build plate, 0-90) instead of the density",
    )  # fmt: skip
    g.add_argument(
        "--fit", type=Path, default=None, action=Given, metavar="FITDIR",
        help="take the parameters from a `stairfit fit` folder (its posterior gives the "
        "uncertainties) instead of --material/--n/--sigma-deg/...",
    )  # fmt: skip
    g.add_argument(
        "--azimuth-deg", default="0", action=Given,
        help="turn of the plane of incidence from across the layer lines: 0 across with the "
        "source downhill, 90 along the layer lines, 180 across from uphill",
    )  # fmt: skip
    g.add_argument(
        "--geometry-deg", default="20,60,85", action=Given,
        help="the ISO 2813 geometries (angles of incidence) to report",
    )  # fmt: skip
    g.add_argument(
        "--facets", default="gaussian", choices=FACETS, action=Given,
        help="the facets of given parameters: Gaussian (width --sigma-deg) or microfacet "
        "(roughness --alpha)",
    )  # fmt: skip
    g.add_argument(
        "--alpha",
        type=float,
        default=None,
        action=Given,
        help="microfacet roughness of given parameters (with --facets ggx/beckmann)",
    )
    g.add_argument(
        "--body-albedo", type=float, default=0.0, action=Given,
        help="albedo of the diffuse body of given parameters (0-1)",
    )  # fmt: skip


def check_not_gloss(args: argparse.Namespace) -> None:
    """Refuse the gloss options without `--gloss` (they would be ignored)."""
    given = getattr(args, "given", frozenset())
    for name in _GLOSS_ONLY:
        if name in given:
            flag = "--" + name.replace("_", "-")
            raise UserError(f"{flag} is an option of the gloss table; add --gloss or drop {flag}")


def check_gloss(args: argparse.Namespace) -> None:
    """Refuse options that contradict `--gloss` or each other there, before any work."""
    given = getattr(args, "given", frozenset())
    for flag, on in (("--lobes", args.lobes), ("--diffuse", args.diffuse),
                     ("--cosine-weighted", args.cosine_weighted)):  # fmt: skip
        if on:
            raise UserError(f"--gloss with {flag}: choose one table; drop {flag} or --gloss")
    for name in _NOT_WITH_GLOSS:
        if name in given:
            flag = "--" + name.replace("_", "-")
            why = ("the glossmeter's geometry fixes the directions" if "theta" in name else
                   "the gloss is taken at the standard's 587.6 nm" if "wavelength" in name else
                   "fillets are not modelled out of the plane of incidence")  # fmt: skip
            raise UserError(f"--gloss with {flag}: {why}; drop {flag}")
    if args.fit is not None:
        for name in _FIT_EXCLUSIVE:
            if name in given:
                flag = "--" + name.replace("_", "-")
                raise UserError(
                    f"--fit with {flag}: the fit folder gives the parameters; drop {flag}, or "
                    "drop --fit to give them yourself"
                )
    elif args.facets == "gaussian" and "alpha" in given:
        raise UserError("--alpha is the microfacet roughness; add --facets ggx or beckmann")
    elif args.facets != "gaussian":
        if args.alpha is None:
            raise UserError(f"--facets {args.facets}: give the roughness --alpha (e.g. 0.06)")
        if "sigma_deg" in given:
            raise UserError(f"--sigma-deg with --facets {args.facets}: give --alpha instead")


def _grids(args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface angles, azimuths and geometries (deg), each checked."""
    from .. import gloss

    wedges = _ranges.check_range(
        _ranges.parse_values(args.wedge_deg, "--wedge-deg"), 0.0, 90.0, "--wedge-deg", "deg"
    )
    azimuths = _ranges.check_range(
        _ranges.parse_values(args.azimuth_deg, "--azimuth-deg"), -360.0, 360.0, "--azimuth-deg",
        "deg",
    )  # fmt: skip
    angles = _ranges.parse_values(args.geometry_deg, "--geometry-deg")
    known = gloss.GLOSS_ANGLES_DEG
    for a in angles:
        if float(a) not in known:
            raise UserError(
                f"--geometry-deg: ISO 2813 has no {a:g} deg geometry; use "
                f"{', '.join(f'{k:g}' for k in known)}"
            )
    rows = wedges.size * azimuths.size * angles.size
    if rows > MAX_GLOSS_ROWS:
        raise UserError(
            f"--gloss: {rows:,} rows ({wedges.size} wedges x {azimuths.size} azimuths x "
            f"{angles.size} geometries) is more than the {MAX_GLOSS_ROWS:,} one run computes; "
            "split the request"
        )
    return wedges, azimuths, angles


def _given_model(
    args: argparse.Namespace, index_of: Callable[[np.ndarray], np.ndarray]
) -> GlossModel:
    """The gloss model of the parameters given on the command line; `index_of(nm)`: the given
    material's index with `--delta-n` added (predict's own lookup and checks)."""
    from stairfit import model

    from .. import gloss

    lam = np.sort(np.r_[model.luminous_rule()[0], model.GLOSS_STANDARD_WAVELENGTH_NM])

    check_number(args.body_albedo, "--body-albedo", 0.0, 1.0)
    check_number(args.edge_radius_um, "--edge-radius-um", 0.0, 10_000.0, "um")
    if args.facets == "gaussian":
        width = args.sigma_deg
    else:
        width = check_number(args.alpha, "--alpha", 1e-6, 10.0)
    return gloss.given_gloss_model(args.facets, lam, index_of(lam), width, args.edge_radius_um,
                                   args.body_albedo)  # fmt: skip


def _layer(args: argparse.Namespace, model: GlossModel) -> float:
    """The layer thickness: as given, else the fit's specimen's, else `--layer-um`'s default
    (refused for a rounded fit, whose gloss depends on it)."""
    given = getattr(args, "given", frozenset())
    if "layer_um" in given or model.layer_um is None:
        if model.rounded and "layer_um" not in given and args.fit is not None:
            raise UserError(
                f"--fit {args.fit}: the folder does not record the specimen's layer thickness, "
                "which the rounded edges' gloss depends on; give --layer-um"
            )
        return float(args.layer_um)
    return float(model.layer_um)


def run_gloss(
    args: argparse.Namespace, writer: RowWriter, index_of: Callable[[np.ndarray], np.ndarray]
) -> None:
    """Compute the gloss table and write it with `writer` (a csv writer). `index_of(nm)`: the
    given material's index with `--delta-n` (predict's own lookup and checks)."""
    from stairfit import model as m

    from .. import gloss

    wedges, azimuths, angles = _grids(args)
    if args.fit is not None:
        model = gloss.fitted_gloss_model(args.fit)
        if "layer_um" in getattr(args, "given", frozenset()):
            check_number(args.layer_um, "--layer-um", 1e-6, 10_000.0, "um")
    else:
        model = _given_model(args, index_of)
    note = gloss.out_of_plane_note(model, azimuths, angles)
    for text in (*model.notes, *([note] if note else [])):
        warnings.warn(text, StairfitWarning, stacklevel=2)
    layer = _layer(args, model)
    rows = gloss.gloss_table(model, wedges, layer, azimuths, angles)
    n = gloss.index_at(model, m.GLOSS_STANDARD_WAVELENGTH_NM) + model.fixed.get("delta_n", 0.0)
    if ("delta_n", None) in model.keys:
        n += model.best[model.keys.index(("delta_n", None))]
    writer.writerow(GLOSS_COLUMNS)
    for r in rows:
        writer.writerow([
            _f(r.wedge_deg), _f(587.6), _fn(n), _f(r.layer_um), _f(r.azimuth_deg), r.layer_lines,
            _f(r.angle_deg), _f(r.gloss), _f(r.specular), _f(r.body), _fo(r.median), _fo(r.p16),
            _fo(r.p84), _fo(r.sd), r.uncertainty, model.kind, model.source,
        ])  # fmt: skip


def _f(x: float) -> str:
    return f"{float(x) + 0.0:.6g}"


def _fo(x: float | None) -> str:
    return "" if x is None else _f(x)


def _fn(x: complex) -> str:
    x = complex(x)
    return _f(x.real) if x.imag == 0 else f"{x.real:.8g}{x.imag:+.8g}j"
