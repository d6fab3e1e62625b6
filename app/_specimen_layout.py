"""Where things appear in a synthetic photo: an orthographic camera over the specimen base.

Base frame (millimetres): `x` uphill along the wedges' slope, `y` along the layer lines, `z` up
from the base. Every wedge rises along `+x` with its face tilted by `beta2` (so its face normal
leans downhill) [conventions §1, §2]. The camera looks at the base from the direction
`(sin V, 0, cos V)`, `V` = `view_deg` (positive: uphill side), and rotates only about `y`, so all
light and view directions stay in the plane of the profile. Image: `u` (columns) runs along `+y`,
`v` (rows) along the projection of `+x`, which points down the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class SpecimenLayout:
    """Wedges in one row across the base (no wedge hides another), markers around them."""

    wedges_deg: tuple[float, ...]
    footprint_mm: float = 20.0  # each wedge is footprint x footprint on the base (paper Sec. 3)
    gap_mm: float = 6.0
    marker_mm: float = 14.0
    marker_margin_mm: float = 8.0

    @property
    def width_mm(self) -> float:
        """Extent of the wedge row along y."""
        n = len(self.wedges_deg)
        return n * self.footprint_mm + (n - 1) * self.gap_mm

    def face_corners_mm(self, k: int) -> NDArray:
        """(4, 3) corners of wedge k's face: low edge, high edge (x = footprint), in 3-D."""
        y0 = k * (self.footprint_mm + self.gap_mm)
        f = self.footprint_mm
        h = f * np.tan(np.deg2rad(self.wedges_deg[k]))
        return np.array([[0, y0, 0], [f, y0, h], [f, y0 + f, h], [0, y0 + f, 0]], float)

    def face_base_mm(self, k: int) -> NDArray:
        """(4, 2) the face's outline projected straight down onto the base plane (x, y)."""
        return self.face_corners_mm(k)[:, :2]

    def markers_mm(self) -> list[tuple[int, NDArray]]:
        """Four ArUco markers (id, (4, 2) corners on the base) beside the two ends of the wedge
        row, where no wedge can hide them from any view (the camera turns about y)."""
        m, g = self.marker_mm, self.marker_margin_mm
        xs = (-g - m, self.footprint_mm + g)
        ys = (-g - m, self.width_mm + g)
        out = []
        for i, (x0, y0) in enumerate((x, y) for x in xs for y in ys):
            corners = np.array([[x0, y0], [x0, y0 + m], [x0 + m, y0 + m], [x0 + m, y0]])
            out.append((i, corners))
        return out


@dataclass(frozen=True)
class OrthoCamera:
    """An orthographic camera at `view_deg` (rotation about y), `px_per_mm` on the sensor."""

    view_deg: float
    width_px: int
    height_px: int
    px_per_mm: float
    centre_mm: tuple[float, float, float]

    def project(self, points_mm: NDArray) -> NDArray:
        """(..., 3) base-frame points to (..., 2) pixel coordinates (u, v)."""
        v = np.deg2rad(self.view_deg)
        e_x = np.array([np.cos(v), 0.0, -np.sin(v)])  # image "down" direction in 3-D
        e_y = np.array([0.0, 1.0, 0.0])
        p = np.asarray(points_mm, float) - np.asarray(self.centre_mm)
        u = self.width_px / 2 + self.px_per_mm * (p @ e_y)
        w = self.height_px / 2 + self.px_per_mm * (p @ e_x)
        return np.stack([u, w], axis=-1)

    def project_base(self, points_xy_mm: NDArray) -> NDArray:
        """(..., 2) points on the base plane (z = 0) to pixels."""
        p = np.asarray(points_xy_mm, float)
        return self.project(np.concatenate([p, np.zeros((*p.shape[:-1], 1))], axis=-1))


def camera_for(
    layout: SpecimenLayout, view_deg: float, width_px: int, height_px: int
) -> OrthoCamera:
    """A camera that frames the wedge row and the markers with a margin at every view."""
    tallest = max(layout.face_corners_mm(k)[:, 2].max() for k in range(len(layout.wedges_deg)))
    span_y = layout.width_mm + 2 * (layout.marker_mm + layout.marker_margin_mm)
    span_x = layout.footprint_mm + 2 * (layout.marker_mm + layout.marker_margin_mm) + tallest
    px_per_mm = 0.85 * min(width_px / span_y, height_px / span_x)
    centre = (layout.footprint_mm / 2, layout.width_mm / 2, 0.0)
    return OrthoCamera(view_deg, width_px, height_px, px_per_mm, centre)
