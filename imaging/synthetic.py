"""Synthetic RAW photographs of wedges on a marked base, for tests, the demo and benchmarks.

`render_photo` draws a Bayer mosaic from per-face relative radiance (the units `measure_photos`
recovers), uniform or varying along the face's in-plane direction (a viewing-angle profile):
faces and background, ArUco markers on the base, a mild multiplicative texture,
vignetting, then the sensor: DN = radiance * t * (ISO/100) / N^2 above black, Poisson shot noise
in electrons, Gaussian read noise, black level, quantisation and clipping at the white level.
It also returns the exact noise-free expectation of every ROI mean the decoder computes, so tests
can compute pulls. `write_dng` writes a real DNG (tifffile) that rawpy and exifread read back.

It knows nothing about BRDFs: the caller turns model predictions into per-face radiance.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import tifffile

from stairfit.fileio import atomic_path

from ._decode import CHANNELS
from ._errors import ImagingError
from ._exposure import Exposure
from ._markers import MarkerLayout
from ._roi import Polygon, RoiMask, as_polygon, roi_mask

# XYZ (D65) -> linear sRGB: the synthetic camera's colour matrix (its channels are sRGB's).
_XYZ_TO_CAMERA = (
    (3.2406, -1.5372, -0.4986),
    (-0.9689, 1.8758, 0.0415),
    (0.0557, -0.2040, 1.0570),
)
_SHIFT = 8

EXPOSURE_TAG_PLACES: tuple[str, ...] = ("exif", "ifd0", "both", "none")
"""Where `SyntheticPhoto.write_dng` can put the exposure tags."""


@dataclass(frozen=True)
class SensorModel:
    """The synthetic camera's sensor.

    Attributes:
        bits: bit depth of the raw values (12 or 14; stored unpacked as uint16).
        black_level: black level (DN), the same for every channel.
        white_level: saturation level (DN); default 2**bits - 1.
        gain_e_per_dn: electrons per DN at ISO 100; at ISO s it is gain * 100 / s.
        read_noise_dn: Gaussian read noise (DN, standard deviation).
        cfa: the 2 x 2 CFA tile, row by row ("RGGB", "BGGR", "GRBG" or "GBRG").
        bias_dn: an offset (DN) of every pixel above the black level the file declares (a
            black-level tag that is off; dark frames measure it, the tag does not).
        fixed_pattern_dn: standard deviation (DN) of a per-pixel offset that is the same in
            every photo of this sensor (dark-signal non-uniformity), drawn from `pattern_seed`.
        pattern_seed: seeds the fixed pattern (the same sensor gives the same pattern).
    """

    bits: int = 14
    black_level: int = 1024
    white_level: int | None = None
    gain_e_per_dn: float = 1.0
    read_noise_dn: float = 2.0
    cfa: str = "RGGB"
    bias_dn: float = 0.0
    fixed_pattern_dn: float = 0.0
    pattern_seed: int = 12345

    def __post_init__(self) -> None:
        if self.bits not in (12, 14, 16):
            raise ImagingError("sensor: bits must be 12, 14 or 16")
        if sorted(self.cfa) != ["B", "G", "G", "R"]:
            raise ImagingError(f"sensor: cfa {self.cfa!r} must be a Bayer tile such as 'RGGB'")
        if not 0 <= self.black_level < self.white:
            raise ImagingError("sensor: need 0 <= black_level < white_level")
        if self.white > 2**self.bits - 1:
            raise ImagingError(f"sensor: white_level exceeds {2**self.bits - 1} ({self.bits} bits)")

    @property
    def white(self) -> int:
        """The white level in DN."""
        return self.white_level if self.white_level is not None else 2**self.bits - 1

    def pattern(self) -> np.ndarray:
        """The CFA tile as colour indices (0 = R, 1 = G, 2 = B), shape (2, 2)."""
        return np.array([CHANNELS.index(ch) for ch in self.cfa], dtype=np.uint8).reshape(2, 2)

    def offset_dn(self, height: int, width: int) -> np.ndarray | float:
        """The true dark level above the declared black level: bias plus fixed pattern (DN)."""
        if self.fixed_pattern_dn <= 0:
            return float(self.bias_dn)
        rng = np.random.default_rng(self.pattern_seed)
        pattern = rng.standard_normal((height, width), dtype=np.float32)
        return pattern * np.float32(self.fixed_pattern_dn) + np.float32(self.bias_dn)


@dataclass(frozen=True, eq=False)
class SyntheticPhoto:
    """A rendered photo and the truth behind it.

    Attributes:
        mosaic: the raw mosaic, uint16 DN, shape (H, W).
        exposure: the exposure it was rendered with.
        sensor: the sensor model.
        faces_px: the face polygons (pixel coordinates).
        erode_px: the erosion the expectations below were computed for.
        expected: face -> (3,) the exact noise-free mean relative radiance (R, G, B) over the
            eroded ROI, as the decoder averages it: texture and vignetting included.
        expected_untextured: the same with the texture replaced by its mean (1).
        marker_corners_px: marker id -> (4, 2) true corner positions (px).
        field: the noise-free relative radiance of every pixel (H, W), if kept.
    """

    mosaic: np.ndarray
    exposure: Exposure
    sensor: SensorModel
    faces_px: dict[str, Polygon]
    erode_px: int
    expected: dict[str, np.ndarray]
    expected_untextured: dict[str, np.ndarray]
    marker_corners_px: dict[int, np.ndarray]
    field: np.ndarray | None = None

    def write_dng(
        self,
        path: str | Path,
        *,
        exif: bool = True,
        exposure_tags: str = "exif",
        make: str = "stairfit",
        model: str = "synthetic",
    ) -> Path:
        """Write the photo as a DNG (see `write_dng`); `exif=False` leaves the exposure out.

        `exposure_tags` says where the exposure goes: one of `EXPOSURE_TAG_PLACES`, "exif" (the
        EXIF sub-IFD), "ifd0" (IFD0, as TIFF/EP puts it), "both", or "none".
        """
        if exposure_tags not in EXPOSURE_TAG_PLACES:
            raise ImagingError(
                f"write_dng: exposure_tags {exposure_tags!r}; use one of {EXPOSURE_TAG_PLACES}"
            )
        where = exposure_tags if exif else "none"
        return write_dng(
            path,
            self.mosaic,
            cfa=self.sensor.cfa,
            black_level=self.sensor.black_level,
            white_level=self.sensor.white,
            exposure=self.exposure if where in ("exif", "both") else None,
            ifd0_exposure=self.exposure if where in ("ifd0", "both") else None,
            make=make,
            model=model,
        )


def _cfa_field(pattern: np.ndarray, lut: np.ndarray, label: np.ndarray) -> np.ndarray:
    """Per-pixel value lut[label, colour of the pixel], float32, for a 2 x 2 CFA tile."""
    out = np.empty(label.shape, dtype=np.float32)
    for dy in range(2):
        for dx in range(2):
            out[dy::2, dx::2] = lut[label[dy::2, dx::2], int(pattern[dy, dx])]
    return out


def _draw_markers(
    field: np.ndarray,
    label: np.ndarray,
    pattern: np.ndarray,
    layout: MarkerLayout,
    plane_to_image: np.ndarray,
    background: np.ndarray,
    white: np.ndarray,
    black: np.ndarray,
    quiet_cells: float = 1.0,
) -> dict[int, np.ndarray]:
    """Draw the markers, each in a white quiet zone `quiet_cells` cells wide (0: none, the black
    border lies directly on the background), on the background pixels, in place."""
    if not (math.isfinite(quiet_cells) and quiet_cells >= 0):
        raise ImagingError("render_photo: marker_quiet_zone_cells must be >= 0")
    h_img, w_img = field.shape
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, layout.dictionary))
    cells = dictionary.markerSize + 2  # data bits plus the black border, per side
    corners_px = {}
    for mid, corners_mm in layout.corners_mm().items():
        if mid >= dictionary.bytesList.shape[0]:
            raise ImagingError(f"marker {mid} is not in {layout.dictionary}")
        local = np.array([[0, 0], [cells, 0], [cells, cells], [0, cells]], dtype=np.float32)
        loc_to_mm = cv2.getPerspectiveTransform(local, corners_mm.astype(np.float32))
        loc_to_px = plane_to_image @ loc_to_mm
        pts = cv2.perspectiveTransform(corners_mm.reshape(-1, 1, 2), plane_to_image).reshape(4, 2)
        corners_px[mid] = pts
        q0, q1 = -quiet_cells, cells + quiet_cells
        quiet = np.array([[q0, q0], [q1, q0], [q1, q1], [q0, q1]], float)
        q = cv2.perspectiveTransform(quiet.reshape(-1, 1, 2), loc_to_px).reshape(4, 2)
        x0, y0 = max(0, math.floor(q[:, 0].min())), max(0, math.floor(q[:, 1].min()))
        x1, y1 = min(w_img, math.ceil(q[:, 0].max()) + 1), min(h_img, math.ceil(q[:, 1].max()) + 1)
        if x0 >= x1 or y0 >= y1:
            continue
        sides = [float(np.linalg.norm(pts[1] - pts[0])), float(np.linalg.norm(pts[3] - pts[0]))]
        p = max(4, math.ceil(2 * max(sides) / cells))  # marker-image px per cell: 2x oversampled
        img = cv2.aruco.generateImageMarker(dictionary, mid, cells * p, borderBits=1)
        pad = round(quiet_cells * p)
        img = np.pad(img, pad, constant_values=255).astype(np.float32) / 255.0
        off = 0.5 / p - pad / p
        to_local = np.array([[1 / p, 0, off], [0, 1 / p, off], [0, 0, 1]])
        shift = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]], dtype=np.float64)
        m = shift @ loc_to_px @ to_local
        supersample = min(8, math.ceil(max(sides) / max(min(sides), 1e-9)))
        whiteness, cover = _warped(img, m, (x1 - x0, y1 - y0), supersample)
        ys, xs = np.arange(y0, y1), np.arange(x0, x1)
        chan = pattern[(ys % 2)[:, None], (xs % 2)[None, :]]
        value = background[chan] * (1 - cover) + black[chan] * cover
        value += (white[chan] - black[chan]) * whiteness
        box = field[y0:y1, x0:x1]
        bg = label[y0:y1, x0:x1] == 0
        box[bg] = value[bg]
    return corners_px


def _warped(
    img: np.ndarray, m: np.ndarray, size: tuple[int, int], k: int
) -> tuple[np.ndarray, np.ndarray]:
    """The marker image and its coverage warped by `m` into a box of `size` (width, height),
    rendered k x k times finer and area-averaged: a foreshortened marker (k = the ratio of its
    sides) is anti-aliased across its short side too, so its edges do not snap to pixels."""
    fine = np.array([[k, 0, (k - 1) / 2], [0, k, (k - 1) / 2], [0, 0, 1]]) @ m
    fsize = (size[0] * k, size[1] * k)
    flags = cv2.INTER_LINEAR
    whiteness = cv2.warpPerspective(img, fine, fsize, flags=flags, borderValue=0)
    cover = cv2.warpPerspective(np.ones_like(img), fine, fsize, flags=flags, borderValue=0)
    if k > 1:
        whiteness = cv2.resize(whiteness, size, interpolation=cv2.INTER_AREA)
        cover = cv2.resize(cover, size, interpolation=cv2.INTER_AREA)
    return whiteness, cover


def _vignetting(h: int, w: int, falloff: float) -> np.ndarray | None:
    """cos^4-law vignetting 1 / (1 + r^2/f^2)^2, with 1 - falloff in the image corners."""
    if falloff <= 0:
        return None
    cy, cx = (h - 1) / 2, (w - 1) / 2
    f2 = (cx**2 + cy**2) / ((1 - falloff) ** -0.5 - 1)
    ry = ((np.arange(h, dtype=np.float32) - cy) ** 2 / f2)[:, None]
    rx = ((np.arange(w, dtype=np.float32) - cx) ** 2 / f2)[None, :]
    v = 1.0 / (1.0 + ry + rx)
    return (v * v).astype(np.float32)


def _channel_means(field: np.ndarray, pattern: np.ndarray, roi: RoiMask) -> np.ndarray:
    """(3,) mean of `field` over each colour's pixels in an ROI."""
    rows, cols = roi.box()
    sub = field[rows, cols]
    ys = np.arange(roi.y0, roi.y0 + roi.mask.shape[0])
    xs = np.arange(roi.x0, roi.x0 + roi.mask.shape[1])
    chan = pattern[(ys % 2)[:, None], (xs % 2)[None, :]]
    return np.array(
        [float(sub[roi.mask & (chan == c)].astype(np.float64).mean()) for c in range(3)]
    )


def render_photo(
    size: tuple[int, int],
    faces_px: Mapping[str, Polygon],
    radiance: Mapping[str, Sequence[float]],
    exposure: Exposure,
    *,
    background: Sequence[float],
    sensor: SensorModel | None = None,
    markers: MarkerLayout | None = None,
    plane_to_image: np.ndarray | None = None,
    marker_white: Sequence[float] | None = None,
    marker_black: Sequence[float] | None = None,
    marker_quiet_zone_cells: float = 1.0,
    texture_amplitude: float = 0.02,
    texture_sigma_px: float = 1.5,
    vignetting: float = 0.04,
    erode_px: int = 8,
    seed: int = 0,
    keep_field: bool = False,
    texture_seed: int | None = None,
    profile_ends: Mapping[str, tuple[Sequence[float], Sequence[float]]] | None = None,
) -> SyntheticPhoto:
    """Render a RAW photo of wedge faces on a base.

    Args:
        size: (width, height) in pixels.
        faces_px: face name -> polygon in pixel coordinates (docs/imaging.md §Pixels).
        radiance: face name -> (R, G, B) relative radiance, the units the decoder recovers:
            DN above black = radiance * t * (ISO/100) / N^2 (see `Exposure.scale`); or a
            profile `(Q, 3)` along the face (needs `profile_ends`).
        profile_ends: face name -> ((x, y), (x, y)) pixel positions where a profile face's
            coordinate s is -1 and +1: a pixel at p has s = 2 (p - a).(b - a) / |b - a|^2 - 1
            (clipped to [-1, 1]), and its radiance is the profile interpolated linearly at s
            between Q nodes evenly spaced over [-1, 1].
        exposure: the exposure (time, f-number, ISO).
        background: (R, G, B) relative radiance of the base.
        sensor: the sensor model (default `SensorModel()`: 14 bits, RGGB).
        markers: ArUco markers to draw on the base (needs `plane_to_image`).
        plane_to_image: 3 x 3 homography from base-plane mm to pixels.
        marker_white, marker_black: (R, G, B) radiance of the markers' white and black cells
            (default: the background, and a tenth of it).
        marker_quiet_zone_cells: the white margin around each marker's black border, in
            cells (0: none, the border lies on the background as on a dark plate).
        texture_amplitude: relative standard deviation of the multiplicative texture.
        texture_sigma_px: correlation scale of the texture: Gaussian smoothing (px) of white
            noise; the texture's autocorrelation is a Gaussian of width sigma * sqrt(2).
        vignetting: relative falloff in the image corners (cos^4 law).
        erode_px: erosion of the ROIs for which `expected` is computed (as in extraction).
        seed: seeds the texture and the noise (deterministic).
        texture_seed: if given, seeds the texture alone (`seed` then seeds only the noise), so
            that several exposures of one view (a bracket) share their texture.
        keep_field: keep the noise-free radiance image in the result (memory: 4 bytes/pixel).

    Returns:
        A `SyntheticPhoto` with the mosaic and the exact expected ROI means.
    """
    sensor = sensor or SensorModel()
    w_img, h_img = int(size[0]), int(size[1])
    if w_img < 2 or h_img < 2:
        raise ImagingError("render_photo: size must be at least 2 x 2")
    names = list(faces_px)
    if len(names) > 254:
        raise ImagingError("render_photo: at most 254 faces")
    missing = [n for n in names if n not in radiance]
    if missing:
        raise ImagingError(f"render_photo: no radiance for faces {missing}")
    pattern = sensor.pattern()
    bg = np.asarray(background, dtype=np.float32).reshape(3)
    polys = {n: as_polygon(faces_px[n], f"face {n!r}") for n in names}
    label = _face_labels((h_img, w_img), [polys[n] for n in names])
    profiles = {n: np.asarray(radiance[n], dtype=np.float32) for n in names}
    ends = dict(profile_ends or {})
    for n, prof in profiles.items():
        if prof.ndim == 2 and (prof.shape[0] < 2 or prof.shape[1] != 3 or n not in ends):
            raise ImagingError(f"render_photo: the profile of face {n!r} needs (Q >= 2, 3) "
                               "values and its profile_ends")  # fmt: skip
    lut = np.vstack([bg] + [p.reshape(-1, 3).mean(axis=0) for p in profiles.values()])
    field = _cfa_field(pattern, lut, label)
    for k, n in enumerate(names, start=1):
        if profiles[n].ndim == 2:
            _paint_profile(field, label == k, pattern, profiles[n], ends[n])
    corners_px: dict[int, np.ndarray] = {}
    if markers is not None:
        if plane_to_image is None:
            raise ImagingError("render_photo: markers need plane_to_image (a 3 x 3 homography)")
        white = np.asarray(marker_white if marker_white is not None else bg, np.float32)
        black = np.asarray(marker_black if marker_black is not None else 0.1 * bg, np.float32)
        corners_px = _draw_markers(field, label, pattern, markers, np.asarray(plane_to_image,
                                   float), bg, white, black, marker_quiet_zone_cells)  # fmt: skip
    del label
    vig = _vignetting(h_img, w_img, vignetting)
    if vig is not None:
        field *= vig
        del vig
    rng = np.random.default_rng(seed)
    tex_rng = rng if texture_seed is None else np.random.default_rng(texture_seed)
    untextured = field
    field = _textured(untextured, texture_amplitude, texture_sigma_px, tex_rng)
    expected, expected_untextured = {}, {}
    for n in names:
        roi = roi_mask(polys[n], (h_img, w_img), erode_px, photo="synthetic", wedge=n)
        expected[n] = _channel_means(field, pattern, roi)
        expected_untextured[n] = _channel_means(untextured, pattern, roi)
    del untextured
    return SyntheticPhoto(
        mosaic=_expose(field, exposure, sensor, rng),
        exposure=exposure,
        sensor=sensor,
        faces_px=polys,
        erode_px=erode_px,
        expected=expected,
        expected_untextured=expected_untextured,
        marker_corners_px=corners_px,
        field=field if keep_field else None,
    )


def _paint_profile(
    field: np.ndarray,
    inside: np.ndarray,
    pattern: np.ndarray,
    profile: np.ndarray,
    ends: tuple[Sequence[float], Sequence[float]],
) -> None:
    """Overwrite `field` where `inside` with the (Q, 3) profile interpolated at each pixel's
    face coordinate s (see `render_photo`), each pixel in its own CFA colour."""
    ys, xs = np.nonzero(inside)
    a, b = np.asarray(ends[0], float), np.asarray(ends[1], float)
    d = b - a
    s = 2.0 * ((xs - a[0]) * d[0] + (ys - a[1]) * d[1]) / float(d @ d) - 1.0
    nodes = np.linspace(-1.0, 1.0, profile.shape[0])
    colour = pattern[ys % 2, xs % 2]
    out = np.empty(xs.size, dtype=np.float32)
    for c in range(3):
        sel = colour == c
        out[sel] = np.interp(np.clip(s[sel], -1.0, 1.0), nodes, profile[:, c])
    field[ys, xs] = out


def _face_labels(shape: tuple[int, int], polygons: Sequence[Polygon]) -> np.ndarray:
    """Label image (uint8): 0 for the base, k for the k-th polygon (1-based, later ones on
    top), filled at sub-pixel precision."""
    label = np.zeros(shape, dtype=np.uint8)
    for k, poly in enumerate(polygons, start=1):
        pts = np.round(np.asarray(poly) * (1 << _SHIFT)).astype(np.int32)
        cv2.fillPoly(label, [pts], k, lineType=cv2.LINE_8, shift=_SHIFT)
    return label


def _textured(
    field: np.ndarray, amplitude: float, sigma_px: float, rng: np.random.Generator
) -> np.ndarray:
    """`field` times a multiplicative texture of mean 1 and relative sd `amplitude`: white
    noise smoothed by a Gaussian of `sigma_px` (none at 0); `field` itself when amplitude is 0."""
    if amplitude <= 0:
        return field
    noise = rng.standard_normal(field.shape, dtype=np.float32)
    if sigma_px > 0:
        noise = cv2.GaussianBlur(noise, (0, 0), sigma_px)
    noise -= noise.mean()
    noise *= amplitude / noise.std()
    noise += 1.0
    return field * noise


def _expose(
    field: np.ndarray, exposure: Exposure, sensor: SensorModel, rng: np.random.Generator
) -> np.ndarray:
    """The sensor: electrons -> Poisson -> DN, read noise, black, quantisation, clipping."""
    h_img, w_img = field.shape
    gain = sensor.gain_e_per_dn * 100.0 / exposure.iso  # electrons per DN at this ISO
    electrons = np.maximum(field / np.float32(exposure.scale), 0.0) * np.float32(gain)
    dn = rng.poisson(electrons).astype(np.float32)
    del electrons
    dn /= np.float32(gain)
    dn += rng.standard_normal((h_img, w_img), dtype=np.float32) * np.float32(sensor.read_noise_dn)
    dn += np.float32(sensor.black_level)
    dn += sensor.offset_dn(h_img, w_img)
    np.rint(dn, out=dn)
    np.clip(dn, 0, sensor.white, out=dn)
    return dn.astype(np.uint16)


_UINT32_MAX = 2**32 - 1


def _rational(x: float, max_den: int) -> tuple[int, int]:
    """`x` as a TIFF RATIONAL (two unsigned 32-bit integers), the denominator at most `max_den`
    and small enough that the numerator fits; an ImagingError when `x` cannot be written."""
    if not (math.isfinite(x) and 0 < x <= _UINT32_MAX):
        raise ImagingError(f"write_dng: {x!r} does not fit an EXIF RATIONAL tag (0, 2^32 - 1]")
    den = max(1, min(max_den, (_UINT32_MAX - 1) // math.ceil(x)))
    fr = Fraction(x).limit_denominator(den)
    if fr.numerator == 0:
        raise ImagingError(f"write_dng: {x!r} is below the smallest RATIONAL 1/{den} written")
    return fr.numerator, fr.denominator


def write_dng(
    path: str | Path,
    mosaic: np.ndarray,
    *,
    cfa: str = "RGGB",
    black_level: int = 1024,
    white_level: int = 16383,
    exposure: Exposure | None = None,
    ifd0_exposure: Exposure | None = None,
    make: str = "stairfit",
    model: str = "synthetic",
) -> Path:
    """Write a Bayer mosaic as a DNG 1.4 file (tifffile), atomically.

    The file has PhotometricInterpretation 32803 (CFA), CFARepeatPatternDim 2 x 2, CFAPattern,
    BlackLevel, WhiteLevel, a colour matrix (linear sRGB camera, D65) and, when `exposure` is
    given, an EXIF sub-IFD with ExposureTime, FNumber and ISOSpeedRatings (rawpy reports ISO only
    from there); `ifd0_exposure` puts the same three tags in IFD0 instead (or as well), where
    TIFF/EP puts them. Data are stored unpacked as uint16, so rawpy reads them back bit-exactly.

    Args:
        path: the .dng file to write.
        mosaic: (H, W) uint16 raw values.
        cfa: the 2 x 2 CFA tile, e.g. "RGGB".
        black_level, white_level: in DN.
        exposure: exposure tags to write to the EXIF IFD; None writes no EXIF exposure.
        ifd0_exposure: exposure tags to write to IFD0; None writes none there.
        make, model: camera make and model tags.
    """
    mosaic = np.asarray(mosaic)
    if mosaic.ndim != 2 or mosaic.dtype != np.uint16:
        raise ImagingError("write_dng: the mosaic must be a 2-D uint16 array")
    if sorted(cfa) != ["B", "G", "G", "R"]:
        raise ImagingError(f"write_dng: cfa {cfa!r} must be a Bayer tile such as 'RGGB'")
    cm: list[int] = []
    for row in _XYZ_TO_CAMERA:
        for v in row:
            cm += [round(v * 10000), 10000]
    tags = [
        (271, "s", 0, make, True),
        (272, "s", 0, model, True),
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, tuple(CHANNELS.index(c) for c in cfa), True),  # CFAPattern
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, f"{make} {model}", True),  # UniqueCameraModel
        (50710, "B", 3, (0, 1, 2), True),  # CFAPlaneColor
        (50711, "H", 1, 1, True),  # CFALayout: rectangular
        (50713, "H", 2, (1, 1), True),  # BlackLevelRepeatDim
        (50714, "I", 1, int(black_level), True),  # BlackLevel
        (50717, "I", 1, int(white_level), True),  # WhiteLevel
        (50721, "2i", 9, tuple(cm), True),  # ColorMatrix1
        (50728, "2I", 3, (1, 1, 1, 1, 1, 1), True),  # AsShotNeutral
        (50778, "H", 1, 21, True),  # CalibrationIlluminant1: D65
        *_ifd0_exposure_tags(ifd0_exposure),
    ]
    path = Path(path)
    with atomic_path(path) as tmp:
        tifffile.imwrite(
            tmp,
            mosaic,
            photometric=32803,
            extratags=tags,
            software="stairfit",
            metadata=None,
            byteorder="<",
            bigtiff=False,
        )
        if exposure is not None:
            _append_exif_ifd(tmp, exposure)
    return path


def _ifd0_exposure_tags(exposure: Exposure | None) -> list[tuple]:
    """tifffile extratags for ExposureTime, FNumber and ISOSpeedRatings in IFD0 (TIFF/EP)."""
    if exposure is None:
        return []
    iso = _iso_short(exposure)
    return [
        (33434, "2I", 1, _rational(exposure.exposure_time_s, 1_000_000), True),  # ExposureTime
        (33437, "2I", 1, _rational(exposure.f_number, 1000), True),  # FNumber
        (34855, "H", 1, iso, True),  # ISOSpeedRatings
    ]


def _iso_short(exposure: Exposure) -> int:
    """The ISO as an EXIF SHORT (an ImagingError when it does not fit)."""
    iso = round(exposure.iso)
    if not 1 <= iso <= 65535:
        raise ImagingError(f"write_dng: ISO {exposure.iso} does not fit the EXIF SHORT tag")
    return iso


def _append_exif_ifd(path: Path, exposure: Exposure) -> None:
    """Add an EXIF sub-IFD to a little-endian classic TIFF written by tifffile.

    tifffile does not write the ExifIFD pointer (tag 34665) itself, so this appends the EXIF IFD
    and a copy of IFD0 with the pointer inserted at the end of the file, then points the header
    at the new IFD0. Out-of-line values of IFD0 keep their offsets, so the copy stays valid.
    """
    with open(path, "r+b") as f:
        data = f.read()
        if data[:4] != b"II*\x00":
            raise ImagingError("write_dng: expected a little-endian classic TIFF from tifffile")
        ifd0 = struct.unpack_from("<I", data, 4)[0]
        n = struct.unpack_from("<H", data, ifd0)[0]
        entries = [data[ifd0 + 2 + 12 * k : ifd0 + 14 + 12 * k] for k in range(n)]
        next_ifd = struct.unpack_from("<I", data, ifd0 + 2 + 12 * n)[0]
        exif_at = len(data) + len(data) % 2
        n_exif = 4
        values_at = exif_at + 2 + 12 * n_exif + 4
        t_num, t_den = _rational(exposure.exposure_time_s, 1_000_000)
        f_num, f_den = _rational(exposure.f_number, 1000)
        iso = _iso_short(exposure)
        payload = struct.pack("<IIII", t_num, t_den, f_num, f_den)
        exif_entries = [
            struct.pack("<HHII", 33434, 5, 1, values_at),  # ExposureTime, RATIONAL
            struct.pack("<HHII", 33437, 5, 1, values_at + 8),  # FNumber, RATIONAL
            struct.pack("<HHIHH", 34855, 3, 1, iso, 0),  # ISOSpeedRatings, SHORT
            struct.pack("<HHI4s", 36864, 7, 4, b"0230"),  # ExifVersion, UNDEFINED
        ]
        exif = struct.pack("<H", n_exif) + b"".join(exif_entries) + struct.pack("<I", 0) + payload
        new_ifd0 = exif_at + len(exif)
        new_ifd0 += new_ifd0 % 2
        entries.append(struct.pack("<HHII", 34665, 4, 1, exif_at))  # ExifIFD pointer, LONG
        entries.sort(key=lambda e: struct.unpack_from("<H", e)[0])
        ifd = struct.pack("<H", len(entries)) + b"".join(entries) + struct.pack("<I", next_ifd)
        f.seek(0, 2)
        f.write(b"\0" * (exif_at - len(data)) + exif + b"\0" * (new_ifd0 - exif_at - len(exif)))
        f.write(ifd)
        f.seek(4)
        f.write(struct.pack("<I", new_ifd0))


def marker_test_photo(
    cell_px: float,
    *,
    view_deg: float = 0.0,
    paper_to_peak: float = 0.5,
    quiet_zone_cells: float = 1.0,
    dictionary: str = "DICT_4X4_50",
    seed: int = 0,
) -> tuple[SyntheticPhoto, MarkerLayout]:
    """A small photo of four ArUco markers around a bright face, for detection sweeps.

    An orthographic camera at `view_deg` (a rotation about the base's y axis) sees 12 mm
    markers at the corners of a 64 x 64 mm square and a 20 x 20 mm face in its middle, all on
    the base. The markers' cells are `cell_px` pixels along x (foreshortened by cos(view)) and
    cell_px / cos(view) along y. The exposure puts the face at half the raw range, as a session
    exposed for the wedges would; the markers' white paper has `paper_to_peak` of the face's
    radiance, the ink 4% and the base plate 10% of the paper.

    Returns:
        The photo (true marker corners in `marker_corners_px`) and the marker layout.
    """
    cells = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).markerSize + 2
    side_mm, cos_v = 12.0, math.cos(math.radians(view_deg))
    px_per_mm = cell_px * cells / side_mm / cos_v
    corners = {
        i: [(x, y), (x, y + side_mm), (x + side_mm, y + side_mm), (x + side_mm, y)]
        for i, (x, y) in enumerate([(0, 0), (0, 52), (52, 0), (52, 52)])
    }  # ArUco order as seen by the camera below (image x along +y, image y along +x)
    layout = MarkerLayout(corners, dictionary=dictionary)
    margin = 6 * side_mm / 12 + 4 * cell_px / px_per_mm
    w = math.ceil((64 + 2 * margin) * px_per_mm / 2) * 2
    h = math.ceil((64 + 2 * margin) * px_per_mm * cos_v / 2) * 2
    hom = np.array(
        [[0, px_per_mm, margin * px_per_mm], [px_per_mm * cos_v, 0, margin * px_per_mm * cos_v],
         [0, 0, 1]]
    )  # fmt: skip
    face_mm = np.array([[22, 22], [22, 42], [42, 42], [42, 22]], float)
    face = cv2.perspectiveTransform(face_mm.reshape(-1, 1, 2), hom).reshape(-1, 2)
    exposure = Exposure(1 / 100, 5.6, 100)
    sensor = SensorModel()
    peak = 0.5 * (sensor.white - sensor.black_level) * exposure.scale
    paper = paper_to_peak * peak
    photo = render_photo(
        (w, h), {"face": face.tolist()}, {"face": np.full(3, peak)}, exposure,
        background=np.full(3, 0.1 * paper), sensor=sensor, markers=layout, plane_to_image=hom,
        marker_white=np.full(3, paper), marker_black=np.full(3, 0.04 * paper),
        marker_quiet_zone_cells=quiet_zone_cells, vignetting=0.0, erode_px=2, seed=seed,
    )  # fmt: skip
    return photo, layout
