"""From the scene file to what `stairfit.imaging` measures: one `imaging.PhotoSpec` per photo
(the ROIs of the wedges it can see, placed by pixels or by markers), the calibration frames, the
extraction settings, and where the measurement cache lives. Shared by `stairfit fit`,
`stairfit measure`, the fit's reports and `stairfit.explore`.
"""

from __future__ import annotations

import os
import secrets
import warnings
from collections.abc import Mapping
from contextlib import suppress
from pathlib import Path
from typing import TYPE_CHECKING

from . import fileio
from .errors import StairfitWarning, UserError
from .fileio import read_bytes
from .scene import Photo, Polygon, Scene, visible

if TYPE_CHECKING:
    from stairfit import imaging

CACHE_DIR = ".stairfit-cache"
MEASUREMENT_CACHE = "measurements.csv"
KEY_FILE = "measurement-cache.key"
"""The key (32 random bytes, readable by the user only) that signs the measurement caches this
user writes, in the user's cache folder (`_jaxcache.user_cache_dir`): a cache edited by anyone
without it, its checksum recomputed or not, is measured again (imaging/_cache.py)."""


def measurement_cache(scene: Scene, use: bool) -> tuple[Path | None, bytes | None]:
    """The measurement cache of a scene's photo folder and this user's key for it, or (None,
    None) with a one-line warning why when it cannot be kept (no user cache folder for the key,
    a read-only photo folder, a file in the way). Temporary files that killed runs left beside
    the cache are removed."""
    if not use:
        return None, None
    cache = scene.folder / CACHE_DIR / MEASUREMENT_CACHE
    secret = cache_secret()
    if secret is None:
        warnings.warn(
            "no user cache folder for the measurement-cache key (HOME is empty, or its .cache "
            "cannot be written); measuring every photo without the cache",
            StairfitWarning,
            stacklevel=2,
        )
        return None, None
    try:
        cache.parent.mkdir(exist_ok=True)
    except OSError as e:  # a read-only photo folder, or a file in the way: measure without
        warnings.warn(
            f"{cache.parent}: cannot keep the measurement cache there ({e.strerror or e}); "
            "measuring without it",
            StairfitWarning,
            stacklevel=2,
        )
        return None, None
    for name in (cache.name, f"{cache.stem}.checksum.json"):
        for leftover in fileio.leftovers(cache.with_name(name)):
            with suppress(OSError):
                fileio.remove_tree(leftover)
    return cache, secret


def cache_secret(environ: Mapping[str, str] | None = None) -> bytes | None:
    """This user's measurement-cache key, made on first use; None where there is no user cache
    folder or it cannot be written (then no measurement cache is used)."""
    from ._jaxcache import user_cache_dir

    folder = user_cache_dir(environ)
    if folder is None:
        return None
    path = folder / KEY_FILE
    for _ in range(2):
        try:
            key = read_bytes(path, max_bytes=4096)
            return key if len(key) == 32 else None
        except FileNotFoundError:
            pass
        except OSError:
            return None
        try:
            folder.mkdir(parents=True, exist_ok=True, mode=0o700)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            continue  # another run made it first: read that one
        except OSError:
            return None
        with os.fdopen(fd, "wb") as fh:
            fh.write(secrets.token_bytes(32))
    return None


def photo_specs(scene: Scene) -> list[imaging.PhotoSpec]:
    """One `imaging.PhotoSpec` per photo: the ROIs of the wedges it can see."""
    from stairfit import imaging

    from .placement import marker_layout, placement_fields

    layout = marker_layout(scene)
    calibration = calibration_spec(scene)
    specs = []
    for photo in scene.photos:
        per_photo = dict(photo.roi_px)
        rois: dict[str, Polygon] = {}
        faces: dict[str, Polygon] = {}
        for wedge in scene.specimen.wedges:
            if not visible(scene, photo, wedge):
                continue
            if wedge.name in per_photo:
                rois[wedge.name] = per_photo[wedge.name]
            elif wedge.roi_px is not None:
                rois[wedge.name] = wedge.roi_px
            elif wedge.face_mm is not None:
                faces[wedge.name] = wedge.face_mm
        reference = None
        if scene.reference is not None:
            reference = scene.reference.name
            if scene.reference.roi_px is not None:
                rois[reference] = scene.reference.roi_px
            else:
                faces[reference] = scene.reference.face_mm
        specs.append(
            imaging.PhotoSpec(
                path=scene.folder / photo.file,
                name=photo.file,
                exposure_time_s=photo.exposure_time_s,
                f_number=photo.f_number,
                iso=photo.iso,
                rois=tuple(rois.items()),
                faces_mm=tuple(faces.items()),
                markers=layout if faces else None,
                reference=reference,
                plane_of_incidence=scene.camera.plane_of_incidence,
                **placement_fields(scene, photo, faces),
                **radiometry_fields(scene, photo, calibration),
            )
        )
    return specs


def radiometry_fields(
    scene: Scene, photo: Photo, calibration: imaging.CalibrationSpec | None
) -> dict[str, object]:
    """A photo's `imaging.PhotoSpec` fields for its HDR bracket members and the calibration
    frames (`calibration_spec(scene)`, shared by every photo)."""
    from stairfit import imaging

    bracket = tuple(
        imaging.BracketMember(scene.folder / b.file, b.exposure_time_s, b.f_number, b.iso)
        for b in photo.bracket
    )
    return {"bracket": bracket, "calibration": calibration}


def calibration_spec(scene: Scene) -> imaging.CalibrationSpec | None:
    """The scene's `[calibration]` frames as an `imaging.CalibrationSpec` (None without any).

    Reads each file's SHA-256 (the cache key depends on the frames' contents).

    Raises:
        UserError: a frame cannot be read (one line naming the scene field).
    """
    from stairfit import imaging

    c = scene.calibration
    if c is None:
        return None
    folder = scene.folder
    try:
        return imaging.calibration_spec(
            flat_field=[
                (f"calibration.flat_field[{j}]", folder / f) for j, f in enumerate(c.flat_field)
            ],
            dark_frames=[
                (f"calibration.dark_frames[{j}]", folder / f) for j, f in enumerate(c.dark_frames)
            ],
            flat_degree=c.flat_degree,
        )
    except imaging.ImagingError as err:  # an unreadable frame: one line, no traceback
        raise UserError(f"{scene.path}: {err}") from None


def extraction_settings(scene: Scene) -> imaging.ExtractionSettings:
    """The scene's [extraction] as `imaging.ExtractionSettings`."""
    from stairfit import imaging

    e = scene.extraction
    return imaging.ExtractionSettings(
        erode_px=e.erode_px,
        block_px=e.block_px,
        saturation_level=e.saturation_level,
        max_saturated_fraction=e.max_saturated_fraction,
    )
