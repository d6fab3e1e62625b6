"""From the scene file to what `stairfit.imaging` measures: one `imaging.PhotoSpec` per photo
(the ROIs of the wedges it can see, placed by pixels or by markers), the calibration frames, the
extraction settings, and where the measurement cache lives. Shared by `stairfit fit`,
`stairfit measure`, the fit's reports and `stairfit.explore`.
"""

from __future__ import annotations

from typing import Any

from .errors import UserError
from .scene import Photo, Scene, visible

CACHE_DIR = ".stairfit-cache"
MEASUREMENT_CACHE = "measurements.csv"


def photo_specs(scene: Scene) -> list[Any]:
    """One `imaging.PhotoSpec` per photo: the ROIs of the wedges it can see."""
    from stairfit import imaging

    from .placement import marker_layout, placement_fields

    layout = marker_layout(scene)
    calibration = calibration_spec(scene)
    specs = []
    for photo in scene.photos:
        per_photo = dict(photo.roi_px)
        rois: dict[str, Any] = {}
        faces: dict[str, Any] = {}
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


def radiometry_fields(scene: Scene, photo: Photo, calibration: Any) -> dict[str, Any]:
    """A photo's `imaging.PhotoSpec` fields for its HDR bracket members and the calibration
    frames (`calibration_spec(scene)`, shared by every photo)."""
    from stairfit import imaging

    bracket = tuple(
        imaging.BracketMember(scene.folder / b.file, b.exposure_time_s, b.f_number, b.iso)
        for b in photo.bracket
    )
    return {"bracket": bracket, "calibration": calibration}


def calibration_spec(scene: Scene) -> Any:
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


def extraction_settings(scene: Scene) -> Any:
    """The scene's [extraction] as `imaging.ExtractionSettings`."""
    from stairfit import imaging

    e = scene.extraction
    return imaging.ExtractionSettings(
        erode_px=e.erode_px,
        block_px=e.block_px,
        saturation_level=e.saturation_level,
        max_saturated_fraction=e.max_saturated_fraction,
    )
