"""`stairfit predict`: evaluate the forward model on a grid and write CSV.

Degrees and nanometres at this edge; radians inside the model [conventions §1, §7].
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from .. import _ranges
from .._index_checks import extrapolation_warning
from ..errors import UserError
from ..outputs import staged_file
from ._predict_checks import (
    Given,
    RowWriter,
    check_combination,
    check_scalars,
    check_size,
    parse_index,
)
from ._predict_gloss import add_gloss_options, check_gloss, check_not_gloss, run_gloss

CSV_START = b"wedge_deg,wavelength_nm,n,"
"""How every CSV `predict` writes begins (its header); `--force` replaces only such a file."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the `predict` command."""
    p = sub.add_parser(
        "predict",
        help="evaluate the staircase BRDF on a grid (CSV)",
        description=(
            "Evaluate the staircase model for given wedges, material, broadening and angles and "
            "write CSV with a header. Angles in degrees (docs/conventions.md §1: theta_o = "
            "theta_i is mirror reflection, theta_o = -theta_i retroreflection). By default the "
            "table holds the broadened in-plane reflectance density rho (1/rad, §4); --lobes "
            "gives the sharp lobes and --diffuse the diffuse-lighting integral. "
            "--edge-radius-um > 0 rounds the layer edges and --fillet-radius-um > 0 the concave "
            "corners between layers (docs/rounded.md)."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--wedge-deg", default="10,20,30,40,45,60", help="wedge angles beta2 (deg)")
    p.add_argument(
        "--layer-um", type=float, default=150.0, help="layer thickness l1 (um)", action=Given
    )
    p.add_argument(
        "--material", default="pla", help="named dispersion model (see README)", action=Given
    )
    p.add_argument(
        "--n", default=None, help="constant complex index instead, e.g. 1.5 or 1.5+0.01j"
    )
    p.add_argument("--delta-n", type=float, default=0.0, help="offset added to n", action=Given)
    p.add_argument(
        "--sigma-deg", type=float, default=5.0, help="Gaussian broadening (deg)", action=Given
    )
    p.add_argument(
        "--edge-radius-um",
        type=float,
        default=0.0,
        action=Given,
        help=(
            "radius r (um) of the rounded layer edges, 0 = sharp; 0 <= r <= min(l1, l2) for "
            "every wedge (docs/rounded.md). With r > 0 the density uses the rounded model and "
            "--lobes lists its ten paths"
        ),
    )
    p.add_argument(
        "--fillet-radius-um",
        type=float,
        default=0.0,
        action=Given,
        help=(
            "radius r_f (um) of the fillets in the concave corners, 0 = sharp; "
            "0 <= r_f <= min(l1, l2) - r for every wedge (docs/rounded.md §11); density only"
        ),
    )
    p.add_argument("--wavelength-nm", default="550", help="wavelengths (nm)", action=Given)
    p.add_argument("--theta-i-deg", default="0", help="angles of incidence (deg)", action=Given)
    p.add_argument(
        "--theta-o-deg", default="-90:90:1", help="angles of observation (deg)", action=Given
    )
    p.add_argument(
        "--lobes",
        action="store_true",
        help="write the sharp lobes instead (with --edge-radius-um > 0: the ten paths)",
    )
    p.add_argument("--diffuse", action="store_true", help="write the diffuse-lighting integral")
    p.add_argument(
        "--cosine-weighted", action="store_true", help="diffuse integral with cos(theta_i) weight"
    )
    p.add_argument("-o", "--output", type=Path, default=None, help="CSV file (default: stdout)")
    p.add_argument("--force", action="store_true", help="overwrite an existing --output file")
    add_gloss_options(p)
    p.set_defaults(func=run, given=frozenset())


def run(args: argparse.Namespace) -> int:
    """Evaluate and write; user mistakes raise UserError.

    Each model evaluation is one compiled call (`_jit`): eager JAX would compile every
    operation separately (about 40 small programs for one `--lobes` case, most of its
    start-up; issue 14).
    """
    if args.output is None and getattr(args, "stdout_closed", False):
        raise UserError(
            "standard output is closed (>&-), so the table has nowhere to go; give -o FILE"
        )
    if args.gloss:
        check_gloss(args)
        check_combination(args)
        check_scalars(args)
        with _open_output(args.output, args.force) as out:
            run_gloss(args, csv.writer(out, lineterminator="\n"), lambda nm: _index(args, nm))
        return 0
    check_not_gloss(args)
    check_combination(args)
    check_scalars(args)
    wedges, lam, theta_i, theta_o = _grids(args)
    _check_table_size(args, wedges, lam, theta_i, theta_o)
    radius = _edge_radius(args.edge_radius_um, wedges, args.layer_um)
    fillet = _fillet_radius(args.fillet_radius_um, wedges, args.layer_um, radius)
    if fillet > 0.0 and (args.lobes or args.diffuse):
        flag = "--lobes" if args.lobes else "--diffuse"
        raise UserError(
            f"--fillet-radius-um with {flag}: fillets are only available for the density (their "
            f"rays have no path list or diffuse integral); drop {flag} or use "
            "--fillet-radius-um 0"
        )
    if radius > 0.0 and args.diffuse:
        raise UserError(
            "--edge-radius-um with --diffuse: the diffuse integral is only available for the "
            "sharp model; drop --diffuse (density or --lobes) or use --edge-radius-um 0"
        )
    n_lam = _index(args, lam)
    if args.sigma_deg == 0.0 and not (args.lobes or args.diffuse):
        raise UserError(
            "--sigma-deg 0: the model without broadening has no finite density; add --lobes "
            "(delta lobes, or the rounded model's paths) or --diffuse (exact diffuse integral), "
            "or give a broadening > 0"
        )
    b2, ti, to = np.deg2rad(wedges), np.deg2rad(theta_i), np.deg2rad(theta_o)
    with _open_output(args.output, args.force) as out:
        w = csv.writer(out, lineterminator="\n")
        if args.lobes and radius > 0.0:
            _write_rounded_paths(w, b2, lam, n_lam, ti, args.layer_um, radius)
        elif args.lobes:
            _write_lobes(w, b2, lam, n_lam, ti)
        elif args.diffuse:
            _write_diffuse(w, b2, lam, n_lam, to, args)
        else:
            _write_density(w, b2, lam, n_lam, ti, to, (radius, fillet), args)
    return 0


def _grids(args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Wedge angles (deg), wavelengths (nm), theta_i and theta_o (deg), each range-checked."""
    wedges = _ranges.check_range(
        _ranges.parse_values(args.wedge_deg, "--wedge-deg"), 0.01, 89.99, "--wedge-deg", "deg"
    )
    lam = _ranges.check_range(
        _ranges.parse_values(args.wavelength_nm, "--wavelength-nm"),
        200,
        2000,
        "--wavelength-nm",
        "nm",
    )
    theta_i = _ranges.check_range(
        _ranges.parse_values(args.theta_i_deg, "--theta-i-deg"), -90, 90, "--theta-i-deg", "deg"
    )
    theta_o = _ranges.check_range(
        _ranges.parse_values(args.theta_o_deg, "--theta-o-deg"), -90, 90, "--theta-o-deg", "deg"
    )
    return wedges, lam, theta_i, theta_o


def _check_table_size(
    args: argparse.Namespace,
    wedges: np.ndarray,
    lam: np.ndarray,
    theta_i: np.ndarray,
    theta_o: np.ndarray,
) -> None:
    """The number of rows the chosen table will have, refused beyond `MAX_ROWS` (up front)."""
    axes = [("wedges", wedges.size), ("wavelengths", lam.size)]
    if args.lobes:
        paths = 10 if args.edge_radius_um > 0 else 3  # model.PATH_NAMES / model.LOBE_NAMES
        check_size([*axes, ("theta_i", theta_i.size)], paths)
    elif args.diffuse:
        check_size([*axes, ("theta_o", theta_o.size)], 1)
    else:
        check_size([*axes, ("theta_i", theta_i.size), ("theta_o", theta_o.size)], 1)


def _write_lobes(
    w: RowWriter, b2: np.ndarray, lam: np.ndarray, n_lam: np.ndarray, theta_i: np.ndarray
) -> None:
    """The three sharp lobes of every (wedge, wavelength, theta_i) [conventions §3]."""
    from stairfit import model

    w.writerow(
        [
            "wedge_deg",
            "wavelength_nm",
            "n",
            "theta_i_deg",
            "lobe",
            "theta_o_deg",
            "weight",
            "fresnel",
            "ratio",
        ]
    )
    B, N, T = np.meshgrid(b2, n_lam, theta_i, indexing="ij")
    lobes = _jit(model.sharp_lobes)(T, B, N)
    L = np.broadcast_to(lam[None, :, None], B.shape)
    for idx in np.ndindex(B.shape):
        for k, name in enumerate(model.LOBE_NAMES):
            w.writerow(
                [
                    _f(np.rad2deg(B[idx])),
                    _f(L[idx]),
                    _fn(N[idx]),
                    _f(np.rad2deg(T[idx])),
                    name,
                    _f(np.rad2deg(lobes.theta_o[idx][k])),
                    _f(lobes.weight[idx][k]),
                    _f(lobes.fresnel[idx][k]),
                    _f(lobes.ratio[idx][k]),
                ]
            )


def _write_diffuse(
    w: RowWriter,
    b2: np.ndarray,
    lam: np.ndarray,
    n_lam: np.ndarray,
    theta_o: np.ndarray,
    args: argparse.Namespace,
) -> None:
    """The diffuse-lighting integral of every (wedge, wavelength, theta_o) [conventions §4]."""
    from stairfit import model

    w.writerow(
        [
            "wedge_deg",
            "wavelength_nm",
            "n",
            "theta_o_deg",
            "sigma_deg",
            "cosine_weighted",
            "diffuse",
        ]
    )
    B, N, Th_o = np.meshgrid(b2, n_lam, theta_o, indexing="ij")
    cosine = args.cosine_weighted
    if args.sigma_deg == 0.0:
        D = _jit(model.diffuse_sharp, "cosine_weighted")(Th_o, B, N, cosine_weighted=cosine)
    else:
        D = _jit(model.diffuse_broadened, "cosine_weighted")(
            Th_o, B, N, np.deg2rad(args.sigma_deg), cosine_weighted=cosine
        )
    L = np.broadcast_to(lam[None, :, None], B.shape)
    for idx in np.ndindex(B.shape):
        w.writerow(
            [
                _f(np.rad2deg(B[idx])),
                _f(L[idx]),
                _fn(N[idx]),
                _f(np.rad2deg(Th_o[idx])),
                _f(args.sigma_deg),
                int(args.cosine_weighted),
                _f(D[idx]),
            ]
        )


def _write_density(
    w: RowWriter,
    b2: np.ndarray,
    lam: np.ndarray,
    n_lam: np.ndarray,
    theta_i: np.ndarray,
    theta_o: np.ndarray,
    radii: tuple[float, float],
    args: argparse.Namespace,
) -> None:
    """The broadened density rho (1/rad) on the full grid: sharp, rounded (tip radius > 0) or
    filleted (fillet radius > 0) [conventions §4]."""
    from stairfit import model

    w.writerow(
        [
            "wedge_deg",
            "wavelength_nm",
            "n",
            "theta_i_deg",
            "theta_o_deg",
            "sigma_deg",
            "edge_radius_um",
            "fillet_radius_um",
            "rho_per_rad",
        ]
    )
    radius, fillet = radii
    B, N, T, Th_o = np.meshgrid(b2, n_lam, theta_i, theta_o, indexing="ij")
    if radius > 0.0 or fillet > 0.0:
        R = _rounded_density(b2, n_lam, theta_i, theta_o, args)
    else:
        R = _jit(model.brdf)(T, Th_o, B, N, np.deg2rad(args.sigma_deg))
    L = np.broadcast_to(lam[None, :, None, None], B.shape)
    for idx in np.ndindex(B.shape):
        w.writerow(
            [
                _f(np.rad2deg(B[idx])),
                _f(L[idx]),
                _fn(N[idx]),
                _f(np.rad2deg(T[idx])),
                _f(np.rad2deg(Th_o[idx])),
                _f(args.sigma_deg),
                _f(radius),
                _f(fillet),
                _f(R[idx]),
            ]
        )


def _edge_radius(radius_um: float, wedges_deg: np.ndarray, layer_um: float) -> float:
    """The edge radius (um) if it fits every requested wedge, else a one-line UserError.

    The arc is tangent to both facets, so it fits when `0 <= r <= min(l1, l2)`,
    `l2 = l1 cot beta2` [conventions §2] (`model.max_edge_radius`, docs/rounded.md).
    """
    from stairfit import model

    if radius_um == 0.0:  # sharp edges fit every wedge; nothing to evaluate
        return 0.0
    r_max = _jit(model.max_edge_radius)(np.deg2rad(wedges_deg), layer_um)
    limit = int(np.argmin(r_max))
    valid = f"[0, {r_max[limit]:.6g}] um"
    # the same relative slack as model.check_edge_radius, so r = r_max itself is accepted
    if not (np.isfinite(radius_um) and radius_um >= 0.0):
        raise UserError(
            f"--edge-radius-um: {radius_um:g} um is outside the valid range {valid}: the radius "
            "must be >= 0 (0 = sharp edges)"
        )
    if radius_um > r_max[limit] * (1 + 1e-12):
        raise UserError(
            f"--edge-radius-um: {radius_um:g} um is outside the valid range {valid}: the arc "
            f"must fit the layer edge, r <= min(l1, l2) = {r_max[limit]:.6g} um for --wedge-deg "
            f"{wedges_deg[limit]:g} with --layer-um {layer_um:g}; choose r in {valid}"
        )
    return float(radius_um)


def _fillet_radius(
    fillet_um: float, wedges_deg: np.ndarray, layer_um: float, radius_um: float
) -> float:
    """The fillet radius (um) if it fits every requested wedge beside the tip arcs, else a
    one-line UserError: `0 <= r_f <= min(l1, l2) - r` (`model.max_fillet_radius`)."""
    from stairfit import model

    if fillet_um == 0.0:
        return 0.0
    rf_max = _jit(model.max_fillet_radius)(np.deg2rad(wedges_deg), layer_um, radius_um)
    limit = int(np.argmin(rf_max))
    valid = f"[0, {max(float(rf_max[limit]), 0.0):.6g}] um"
    if not (np.isfinite(fillet_um) and fillet_um >= 0.0):
        raise UserError(
            f"--fillet-radius-um: {fillet_um:g} um is outside the valid range {valid}: the "
            "radius must be >= 0 (0 = sharp concave corners)"
        )
    cap = float(rf_max[limit]) + radius_um
    if fillet_um > float(rf_max[limit]) + cap * 1e-12:
        raise UserError(
            f"--fillet-radius-um: {fillet_um:g} um is outside the valid range {valid}: tip arc "
            f"and fillet must fit the facets, r + r_f <= min(l1, l2) = {cap:.6g} um for "
            f"--wedge-deg {wedges_deg[limit]:g} with --layer-um {layer_um:g} and "
            f"--edge-radius-um {radius_um:g}; choose r_f in {valid}"
        )
    return float(fillet_um)


def _rounded_density(
    b2: np.ndarray,
    n_lam: np.ndarray,
    theta_i: np.ndarray,
    theta_o: np.ndarray,
    args: argparse.Namespace,
) -> np.ndarray:
    """`model.brdf_rounded` (or `brdf_filleted` with a fillet) on the (wedge, wavelength,
    theta_i, theta_o) grid (radians).

    Each quantity on its own axis: the geometry is computed once per (wedge, theta_i) and the
    Fresnel factors once per wavelength (see `brdf_rounded`) [conventions §1, §4].
    """
    import functools

    import jax

    from stairfit import model

    if args.fillet_radius_um > 0.0:
        fn = jax.jit(functools.partial(model.brdf_filleted, fillet_radius_um=args.fillet_radius_um))
    else:
        fn = jax.jit(model.brdf_rounded)
    rho = fn(
        theta_i[None, None, :, None],
        theta_o[None, None, None, :],
        b2[:, None, None, None],
        n_lam[None, :, None, None],
        np.deg2rad(args.sigma_deg),
        args.layer_um,
        args.edge_radius_um,
    )
    shape = (b2.size, n_lam.size, theta_i.size, theta_o.size)
    return np.broadcast_to(np.asarray(rho), shape)


def _write_rounded_paths(
    w: RowWriter,
    b2: np.ndarray,
    lam: np.ndarray,
    n_lam: np.ndarray,
    theta_i: np.ndarray,
    layer_um: float,
    radius_um: float,
) -> None:
    """The ten paths of the rounded model (`model.PATH_NAMES`), one row each.

    The three delta lobes keep their sharp directions; the seven continuous lobes spread over a
    range of directions and get an empty `theta_o_deg`. `fresnel = ratio / weight` (the mean
    unpolarised factor of the path; empty where the weight is 0) [conventions §3, §4].
    """
    import jax

    from stairfit import model

    w.writerow(
        [
            "wedge_deg",
            "wavelength_nm",
            "n",
            "theta_i_deg",
            "edge_radius_um",
            "lobe",
            "theta_o_deg",
            "weight",
            "fresnel",
            "ratio",
        ]
    )
    B, N, T = np.meshgrid(b2, n_lam, theta_i, indexing="ij")
    paths = jax.jit(model.rounded_paths)
    p = paths(T, B, N, layer_um, radius_um)
    weight, ratio = np.asarray(p.weight), np.asarray(p.ratio)
    direction = _jit(model.lobe_directions)(T, B)
    L = np.broadcast_to(lam[None, :, None], B.shape)
    for idx in np.ndindex(B.shape):
        for k, name in enumerate(model.PATH_NAMES):
            wk, rk = float(weight[idx][k]), float(ratio[idx][k])
            w.writerow(
                [
                    _f(np.rad2deg(B[idx])),
                    _f(L[idx]),
                    _fn(N[idx]),
                    _f(np.rad2deg(T[idx])),
                    _f(radius_um),
                    name,
                    _f(np.rad2deg(direction[idx][k])) if k < 3 else "",
                    _f(wk),
                    _f(rk / wk) if wk > 0 else "",
                    _f(rk),
                ]
            )


def _index(args: argparse.Namespace, lam: np.ndarray) -> np.ndarray:
    from stairfit import model

    if args.n is not None:
        n = parse_index(args.n)
        values = np.full(lam.shape, n if n.imag else n.real)
    else:
        try:
            disp = model.get_material(args.material)
        except ValueError as e:
            raise UserError(f"--material: {e}") from None
        values = _jit(model.refractive_index, "dispersion")(disp, lam)
        problem = model.materials.index_problem(disp, lam, args.delta_n, values=values)
        if problem is not None:
            raise UserError(f"--material {args.material}, --delta-n {args.delta_n:g}: {problem}")
        extrapolation_warning(disp, args.material, lam, user="this prediction")
    values = values + args.delta_n
    if np.any(np.real(values) <= 1.0):
        raise UserError("--delta-n: the resulting index must stay > 1")
    return values


def _jit(fn: Callable[..., Any], *static: str) -> Callable[..., Any]:
    """`fn` compiled as one program, returning NumPy arrays (the CSV loops index them)."""
    import jax

    compiled = jax.jit(fn, static_argnames=static)

    def call(*args: Any, **kwargs: Any) -> Any:
        return jax.tree.map(np.asarray, compiled(*args, **kwargs))

    return call


def _f(x: float) -> str:
    return f"{float(x) + 0.0:.10g}"  # + 0.0: no "-0"


def _fn(x: complex) -> str:
    x = complex(x)
    return _f(x.real) if x.imag == 0 else f"{x.real:.8g}{x.imag:+.8g}j"


@contextmanager
def _open_output(path: Path | None, force: bool) -> Iterator[TextIO]:
    if path is None:
        yield sys.stdout
        return
    with staged_file(path, force, signature=CSV_START, command="predict") as fh:
        yield fh
