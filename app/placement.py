"""From the scene to what `stairfit.imaging` needs to place faces from the markers.

The scene file's `face_mm` outlines lie on the specimen base; each wedge rises along +x at its
`angle_deg` (the shared base-frame convention, docs/imaging.md §3-D placement), so a photo's
faces are placed in 3-D with the photo's view direction and the `[camera]` intrinsics, and
every wedge with a `face_mm` may hide another from the camera.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .errors import UserError
from .scene import Photo, Polygon, Scene

if TYPE_CHECKING:
    from stairfit import imaging


def marker_layout(scene: Scene) -> imaging.MarkerLayout | None:
    """The scene's `[markers]` as an `imaging.MarkerLayout` (None without markers)."""
    from stairfit import imaging

    if scene.markers is None:
        return None
    return imaging.MarkerLayout(
        {m.id: m.corners_mm for m in scene.markers.markers},
        scene.markers.dictionary,
        scene.markers.min_markers,
    )


def pinhole_camera(scene: Scene) -> imaging.PinholeCamera | None:
    """The `[camera]` intrinsics as an `imaging.PinholeCamera`, or None (an affine camera)."""
    from stairfit import imaging

    if scene.camera.focal_length_px is None:
        return None
    return imaging.PinholeCamera(scene.camera.focal_length_px, scene.camera.principal_point_px)


def base_view_deg(scene: Scene, photo: Photo, wedges: list[str]) -> float | None:
    """The camera's direction from the base normal (deg, about y) in `photo`.

    With `angles_relative_to = "base"` it is the photo's `view_deg`; with "face" it is
    `view_deg - angle_deg` of the placed wedges, which must then agree (one camera). None when
    the photo gives no view_deg (a measure-only photo of patches).
    """
    if photo.view_deg is None:
        return None
    if scene.angles_relative_to == "base" or not wedges:
        return photo.view_deg
    angles = {w.name: w.angle_deg for w in scene.specimen.wedges}
    views = {round(photo.view_deg - angles[n], 9) for n in wedges if n in angles}
    if len(views) > 1:
        k = scene.photos.index(photo)
        raise UserError(
            f'{scene.path}: photos[{k}]: with angles_relative_to = "face" the wedges '
            f"{sorted(wedges)} of different angles cannot all be seen at view_deg = "
            f"{photo.view_deg:g} by one camera, so their faces cannot be placed from the "
            'markers; use angles_relative_to = "base" or give roi_px polygons'
        )
    return views.pop() if views else photo.view_deg


def placement_fields(scene: Scene, photo: Photo, faces: dict[str, Polygon]) -> dict[str, object]:
    """The `imaging.PhotoSpec` fields that place `faces` (name -> face_mm) of `photo` in 3-D:
    face_angles_deg, view_deg, camera and occluders_mm (every wedge with a face_mm)."""
    angles = {w.name: w.angle_deg for w in scene.specimen.wedges}
    wedges = [n for n in faces if n in angles]
    occluders = tuple(
        (w.name, w.face_mm, w.angle_deg) for w in scene.specimen.wedges if w.face_mm is not None
    )
    return {
        "face_angles_deg": tuple((n, angles[n]) for n in wedges),
        "view_deg": base_view_deg(scene, photo, wedges) if faces else None,
        "camera": pinhole_camera(scene),
        "occluders_mm": occluders if faces else (),
    }
