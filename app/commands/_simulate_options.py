"""The options of `stairfit simulate`, shared by `demo`: the parser's arguments and the checked
`SimulationSettings` they give (user mistakes raise UserError naming the option)."""

from __future__ import annotations

import argparse
import math

import numpy as np

from .. import _ranges
from ..errors import UserError
from ..simulation import (
    MARKER_STYLES,
    MIN_MEGAPIXELS,
    SessionEffects,
    SimulationSettings,
    Truth,
    check_radii,
)


def add_truth_options(p: argparse.ArgumentParser, seed_and_workers: bool = True) -> None:
    """Options shared by `simulate` and `demo` (whose fit options bring --seed/--workers)."""
    t, s = Truth(), SimulationSettings()
    p.add_argument("--sigma-deg", type=float, default=t.sigma_deg, help="true broadening (deg)")
    p.add_argument("--delta-n", type=float, default=t.delta_n, help="true index offset")
    p.add_argument(
        "--edge-radius-um", type=float, default=t.edge_radius_um, help="true edge radius (um)"
    )
    p.add_argument(
        "--fillet-radius-um",
        type=float,
        default=t.fillet_radius_um,
        help="true radius of the concave fillets between the layers (um; edge + fillet radius "
        "must fit the finest cell, docs/rounded.md)",
    )
    p.add_argument("--floor", type=float, default=t.floor, help="true diffuse floor")
    p.add_argument("--megapixels", type=float, default=s.megapixels, help="photo size")
    p.add_argument(
        "--views",
        type=int,
        default=len(s.views_deg),
        help="number of photos (viewing angles from -80 to 20 deg, base frame)",
    )
    p.add_argument(
        "--exposure-tags",
        default=s.exposure_tags,
        choices=("exif", "ifd0", "both", "none"),
        help="where the DNGs carry ExposureTime/FNumber/ISO: the EXIF IFD, IFD0 (TIFF/EP), both,"
        " or none (the scene file then gives them as overrides)",
    )
    p.add_argument(
        "--markers",
        default=s.markers,
        choices=MARKER_STYLES,
        help="ArUco markers in a white quiet zone, or printed straight on the dark base plate",
    )
    if seed_and_workers:
        p.add_argument("--seed", type=int, default=s.seed, help="seed of texture and noise")
        p.add_argument("--workers", type=int, default=s.workers, help="processes for rendering")
    add_effect_options(p)


def add_effect_options(p: argparse.ArgumentParser) -> None:
    """Real-world effects of a session (`SessionEffects`), shared by `simulate` and `demo`."""
    e = SessionEffects()
    g = p.add_argument_group("real-world effects (docs/imaging.md)")
    g.add_argument(
        "--vignetting", type=float, default=e.vignetting,
        help="lens fall-off in the image corners (0.15 = 15%% darker)",
    )  # fmt: skip
    g.add_argument(
        "--flat-field", type=int, default=e.flat_frames, metavar="N",
        help="write N flat-field photos and declare them in [calibration]",
    )  # fmt: skip
    g.add_argument(
        "--dark-frames", type=int, default=e.dark_frames, metavar="N",
        help="write N dark frames and declare them in [calibration]",
    )  # fmt: skip
    g.add_argument(
        "--black-error-dn", type=float, default=e.black_error_dn,
        help="true dark level above the black level the files declare (DN)",
    )  # fmt: skip
    g.add_argument(
        "--bracket", type=int, default=e.bracket, metavar="N",
        help="exposures per view (an HDR bracket, 2 stops apart)",
    )  # fmt: skip
    g.add_argument(
        "--fixed-exposure", action="store_true",
        help="one exposure for every view (set by the brightest face of the session)",
    )  # fmt: skip


def effects_from_args(args: argparse.Namespace) -> SessionEffects:
    """Validated `SessionEffects` from the command line (user mistakes raise UserError)."""
    if not (math.isfinite(args.vignetting) and 0.0 <= args.vignetting <= 0.6):
        raise UserError(f"--vignetting: {args.vignetting} is outside [0, 0.6]")
    for option in ("flat_field", "dark_frames"):
        if not 0 <= getattr(args, option) <= 64:
            raise UserError(f"--{option.replace('_', '-')}: give 0 to 64 frames")
    if not (math.isfinite(args.black_error_dn) and abs(args.black_error_dn) <= 100):
        raise UserError(f"--black-error-dn: {args.black_error_dn} is outside [-100, 100] DN")
    if not 1 <= args.bracket <= 5:
        raise UserError(f"--bracket: {args.bracket} is outside [1, 5] exposures per view")
    return SessionEffects(
        vignetting=args.vignetting,
        flat_frames=args.flat_field,
        dark_frames=args.dark_frames,
        black_error_dn=args.black_error_dn,
        bracket=args.bracket,
        fixed_exposure=args.fixed_exposure,
    )


def settings_from_args(args: argparse.Namespace) -> SimulationSettings:
    """Validated settings from command-line options (user mistakes raise UserError)."""
    for option in (
        "sigma_deg", "delta_n", "edge_radius_um", "fillet_radius_um", "floor", "megapixels",
    ):  # fmt: skip
        value = getattr(args, option)
        if not math.isfinite(value):
            raise UserError(f"--{option.replace('_', '-')}: must be a finite number, not {value}")
    if not 0.0 < args.sigma_deg <= 45.0:
        raise UserError(f"--sigma-deg: {args.sigma_deg} is outside (0, 45] deg")
    if not -0.3 <= args.delta_n <= 0.5:
        raise UserError(f"--delta-n: {args.delta_n} is outside [-0.3, 0.5]")
    if args.floor < 0:
        raise UserError("--floor: must be >= 0")
    if not MIN_MEGAPIXELS <= args.megapixels <= 60:
        raise UserError(
            f"--megapixels: {args.megapixels} is outside [{MIN_MEGAPIXELS}, 60] (below "
            f"{MIN_MEGAPIXELS} the steepest face is smaller than the ROI erosion)"
        )
    if not 3 <= args.views <= 200:
        raise UserError(f"--views: {args.views} is outside [3, 200]")
    _ranges.check_workers(args.workers)
    if args.seed < 0:
        raise UserError(f"--seed: {args.seed} is negative; give an integer >= 0")
    base = SimulationSettings()
    truth = Truth(
        sigma_deg=args.sigma_deg,
        delta_n=args.delta_n,
        edge_radius_um=args.edge_radius_um,
        fillet_radius_um=args.fillet_radius_um,
        scale=base.truth.scale,
        floor=args.floor,
    )
    views = tuple(float(v) for v in np.linspace(-80.0, 20.0, args.views))
    settings = SimulationSettings(
        megapixels=args.megapixels,
        views_deg=views,
        seed=args.seed,
        workers=args.workers,
        truth=truth,
        exposure_tags=getattr(args, "exposure_tags", base.exposure_tags),
        markers=getattr(args, "markers", base.markers),
        effects=effects_from_args(args),
    )
    check_radii(settings)
    return settings
