"""Calibration frames: a master dark frame and a smooth flat field, per CFA position.

Dark frames (the lens capped, at the photos' ISO and exposure time) are averaged into a master
dark that is subtracted pixel by pixel instead of the black level. Flat-field photos (a uniform
diffuse target filling the frame, at the photos' aperture and focus) are averaged, the dark (or
the black level) subtracted, binned into cells and fitted, separately for every position of the
CFA tile, by a smooth 2-D Legendre polynomial; the gain map is that polynomial normalised to 1
at the image centre. A photo is corrected as `(raw - dark) / gain`. See docs/imaging.md
§Flat fields and dark frames.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._decode import RawFrame, decode_raw, file_sha256
from ._errors import ImagingError

FLAT_DEGREE = 8
"""Default total degree of the flat field's Legendre polynomial (45 coefficients)."""
FLAT_CELLS = 64
"""The flat is binned into about this many cells along the longer side of a CFA sub-plane."""
FLAT_MIN_SIGNAL = 0.05
"""A flat whose median is below this fraction of the raw range above black is too dark."""
FLAT_MAX_SATURATED = 0.001
"""A flat with a larger fraction of saturated pixels is refused."""
DARK_MAX_SIGNAL = 0.01
"""A dark frame whose median is above black by more than this fraction of the range is refused."""


@dataclass(frozen=True)
class CalibrationFile:
    """One calibration file: its path, the scene field that names it, and its SHA-256."""

    path: Path
    label: str
    sha256: str


@dataclass(frozen=True)
class CalibrationSpec:
    """The calibration frames a set of photos uses (the scene file's [calibration] table).

    Attributes:
        flat_field: flat-field photos (averaged), or none.
        dark_frames: dark frames (averaged), or none.
        flat_degree: total degree of the flat's smoothing polynomial (2 .. 16).
    """

    flat_field: tuple[CalibrationFile, ...] = ()
    dark_frames: tuple[CalibrationFile, ...] = ()
    flat_degree: int = FLAT_DEGREE

    def __post_init__(self) -> None:
        if not (isinstance(self.flat_degree, int) and 2 <= self.flat_degree <= 16):
            raise ImagingError("calibration: flat_degree must be an integer in [2, 16]")

    def key(self) -> dict[str, object]:
        """What the calibration's values depend on, for cache keys (hashes, not paths)."""
        return {
            "flat": [f.sha256 for f in self.flat_field],
            "dark": [f.sha256 for f in self.dark_frames],
            "flat_degree": self.flat_degree,
        }

    def describe(self) -> str:
        """A short tag for the measurement table, e.g. "dark(8)+flat(2)"."""
        parts = []
        if self.dark_frames:
            parts.append(f"dark({len(self.dark_frames)})")
        if self.flat_field:
            parts.append(f"flat({len(self.flat_field)})")
        return "+".join(parts)


def calibration_spec(
    flat_field: Sequence[tuple[str, str | Path]] = (),
    dark_frames: Sequence[tuple[str, str | Path]] = (),
    flat_degree: int = FLAT_DEGREE,
) -> CalibrationSpec:
    """A `CalibrationSpec` from (label, path) pairs; reads each file's SHA-256.

    The label names the file in messages (e.g. the scene field "calibration.flat_field[0]").

    Raises:
        ImagingError: a file is missing or cannot be read.
    """

    def one(label: str, path: str | Path) -> CalibrationFile:
        path = Path(path)
        try:
            return CalibrationFile(path, label, file_sha256(path))
        except OSError as e:
            raise ImagingError(
                f"{label} {path.name!r}: cannot read {path} ({e.strerror or e}); check the file "
                "name (it is relative to the scene file's folder)"
            ) from None

    return CalibrationSpec(
        tuple(one(lb, p) for lb, p in flat_field),
        tuple(one(lb, p) for lb, p in dark_frames),
        flat_degree,
    )


@dataclass(frozen=True, eq=False)
class DarkFrame:
    """The master dark: the mean of the dark frames, and the noise of that mean.

    Attributes:
        mean: (H, W) float32, the averaged raw values (DN), subtracted instead of the black.
        pixel_sd: (ph, pw) per CFA position, the standard deviation of one frame's pixel
            about its mean over the frames (read noise, dark-current shot noise). With a single
            frame it is the spatial standard deviation, which includes the fixed pattern and
            is therefore an upper bound.
        n_frames: frames averaged.
    """

    mean: np.ndarray
    pixel_sd: np.ndarray
    n_frames: int

    def mean_variance(self, cfa_shape: tuple[int, int]) -> np.ndarray:
        """(ph, pw) variance (DN^2) of one pixel of the master: pixel_sd^2 / n_frames."""
        return (self.pixel_sd.reshape(cfa_shape) ** 2) / self.n_frames


@dataclass(frozen=True, eq=False)
class FlatField:
    """The smoothed flat field: one Legendre polynomial per CFA position.

    Attributes:
        coef: (ph, pw, d + 1, d + 1) Legendre coefficients in the normalised image coordinates
            (x, y in [-1, 1] across the visible image), scaled so that the gain is 1 at the
            image centre, ((W - 1) / 2, (H - 1) / 2);
            only terms of total degree <= d are non-zero.
        shape: (H, W) of the images it applies to.
        rel_stderr: (ph, pw) RMS over the image of the fitted gain's standard error, relative.
        fit_rms: (ph, pw) RMS of the cell means about the fit, relative to the gain; larger
            than the cells' noise when the flat has structure the polynomial cannot follow.
        cell_noise: (ph, pw) the RMS relative noise of one cell mean.
        n_frames: flat-field photos averaged.
        centre_stderr: (ph, pw) relative standard error of the fitted level at the centre,
            which the gain is divided by: a common factor of every corrected value of that
            CFA position in every photo (docs/imaging.md §Flat fields and dark frames).
    """

    coef: np.ndarray
    shape: tuple[int, int]
    rel_stderr: np.ndarray
    fit_rms: np.ndarray
    cell_noise: np.ndarray
    n_frames: int
    centre_stderr: np.ndarray

    def gain(self) -> np.ndarray:
        """(H, W) float32 gain map: the flat's smooth relative response, 1 at the centre."""
        h, w = self.shape
        ph, pw = self.coef.shape[:2]
        out = np.empty((h, w), dtype=np.float32)
        for dy in range(ph):
            for dx in range(pw):
                vy = _legendre_rows(np.arange(dy, h, ph), h, self.coef.shape[2] - 1)
                vx = _legendre_rows(np.arange(dx, w, pw), w, self.coef.shape[3] - 1)
                out[dy::ph, dx::pw] = vy @ self.coef[dy, dx] @ vx.T
        return out


@dataclass(frozen=True, eq=False)
class Calibration:
    """Master calibration frames built from a `CalibrationSpec` (see `build_calibration`).

    Attributes:
        spec: what it was built from.
        shape, cfa: image size (H, W) and CFA tile the frames had; photos must match.
        dark: the master dark, or None (the black level is subtracted).
        flat: the flat field, or None (no vignetting correction).
    """

    spec: CalibrationSpec
    shape: tuple[int, int]
    cfa: np.ndarray
    dark: DarkFrame | None
    flat: FlatField | None

    def check_frame(self, frame: RawFrame) -> None:
        """ImagingError unless `frame` has the calibration frames' size and CFA tile."""
        first = (self.spec.dark_frames or self.spec.flat_field)[0]
        if (
            frame.cfa is None
            or (frame.height, frame.width) != self.shape
            or not np.array_equal(frame.cfa, self.cfa)
        ):
            got = "a linear (demosaiced) image" if frame.cfa is None else frame.cfa_string
            raise ImagingError(
                f"photo {frame.name!r}: {frame.width} x {frame.height} px, CFA {got}, but the "
                f"calibration frames ({first.label} {first.path.name!r} ...) are "
                f"{self.shape[1]} x {self.shape[0]} px, CFA {_cfa_text(self.cfa)}; take flat "
                "fields and dark frames with the same camera, image size and orientation"
            )

    def signal(self, frame: RawFrame) -> np.ndarray:
        """(H, W) float32 raw value minus the master dark (or the black level), in DN."""
        self.check_frame(frame)
        out = frame.data.astype(np.float32)
        if self.dark is not None:
            out -= self.dark.mean
        else:
            out -= np.tile(frame.black, _tiles(frame))[: frame.height, : frame.width]
        return out

    def dark_variance(self) -> np.ndarray | None:
        """(ph, pw) variance (DN^2) of one master-dark pixel, or None without dark frames."""
        if self.dark is None:
            return None
        return self.dark.mean_variance(self.cfa.shape)

    def describe(self) -> str:
        """The spec's tag, e.g. "dark(8)+flat(2)"."""
        return self.spec.describe()


def _cfa_text(cfa: np.ndarray) -> str:
    return "".join("RGB"[int(c)] for c in np.asarray(cfa).ravel())


def _tiles(frame: RawFrame) -> tuple[int, int]:
    ph, pw = frame.black.shape
    return (-(-frame.height // ph), -(-frame.width // pw))


def _frames(
    files: Sequence[CalibrationFile], kind: str
) -> Iterator[tuple[CalibrationFile, RawFrame]]:
    """Decode calibration files one at a time; ImagingError naming the field unless all match."""
    first: RawFrame | None = None
    for f in files:
        try:
            frame = decode_raw(f.path, f.path.name)
        except ImagingError as e:
            raise ImagingError(f"{f.label} {f.path.name!r}: {_strip_photo(str(e))}") from None
        if frame.cfa is None:
            raise ImagingError(
                f"{f.label} {f.path.name!r}: a linear (demosaiced) file; {kind} must be RAW "
                "mosaic files from the camera that took the photos"
            )
        if first is None:
            first = frame
        elif frame.data.shape != first.data.shape or not np.array_equal(frame.cfa, first.cfa):
            raise ImagingError(
                f"{f.label} {f.path.name!r}: {frame.width} x {frame.height} px, CFA "
                f"{frame.cfa_string}, unlike {files[0].label} {files[0].path.name!r} "
                f"({first.width} x {first.height} px, CFA {first.cfa_string}); all calibration "
                "frames must come from the camera and image size of the photos"
            )
        yield f, frame


def _strip_photo(message: str) -> str:
    """An ImagingError about a file, without its leading "photo 'name': "."""
    if message.startswith("photo ") and ": " in message:
        return message.split(": ", 1)[1]
    return message


def _black_map(frame: RawFrame) -> np.ndarray:
    return np.tile(frame.black, _tiles(frame))[: frame.height, : frame.width]


def build_dark(files: Sequence[CalibrationFile]) -> tuple[DarkFrame, RawFrame]:
    """The master dark frame of `files` (see `DarkFrame`), and the first frame (for its size).

    The frames are read one at a time; the mean and the between-frame variance are accumulated
    as offsets from the first frame (small numbers, exact in float32).

    Raises:
        ImagingError: a file cannot be decoded, differs in size or CFA from the first, or is not
            dark (its median is more than `DARK_MAX_SIGNAL` of the raw range above black).
    """
    first: RawFrame | None = None
    s1 = s2 = base = None
    for f, frame in _frames(files, "dark frames"):
        _check_dark_exposure(f, frame)
        if first is None:
            first, base = frame, frame.data.astype(np.float32)
            s1, s2 = np.zeros_like(base), np.zeros_like(base)
            continue
        d = frame.data.astype(np.float32) - base
        s1 += d
        s2 += d * d
    assert first is not None and s1 is not None and s2 is not None and base is not None
    n = len(files)
    mean = base + s1 / n
    ph, pw = first.cfa.shape
    sd = np.empty((ph, pw))
    for dy in range(ph):
        for dx in range(pw):
            if n > 1:
                sub1, sub2 = s1[dy::ph, dx::pw], s2[dy::ph, dx::pw]
                var = (sub2 - sub1 * sub1 / n) / (n - 1)
                sd[dy, dx] = math.sqrt(max(float(np.mean(var, dtype=np.float64)), 0.0))
            else:
                sd[dy, dx] = float(base[dy::ph, dx::pw].std(dtype=np.float64))
    return DarkFrame(mean=mean, pixel_sd=sd, n_frames=n), first


def _check_dark_exposure(f: CalibrationFile, frame: RawFrame) -> None:
    black = float(frame.black.mean())
    median = float(np.median(frame.data[::4, ::4])) - black
    if median > DARK_MAX_SIGNAL * (frame.white_level - black):
        raise ImagingError(
            f"{f.label} {f.path.name!r}: its median is {median:.0f} DN above the black "
            f"level ({100 * median / (frame.white_level - black):.1f}% of the raw range); "
            "not a dark frame. Take dark frames with the lens capped, at the ISO and "
            "exposure time of the photos"
        )


def _legendre_rows(idx: np.ndarray, n: int, degree: int) -> np.ndarray:
    """(len(idx), degree + 1) Legendre polynomials of pixel index idx mapped to [-1, 1]."""
    t = (np.asarray(idx, float) - (n - 1) / 2.0) / max((n - 1) / 2.0, 1.0)
    return np.polynomial.legendre.legvander(t, degree)


def _bin_cells(
    plane: np.ndarray, good: np.ndarray, cell: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-cell (sum, sum of squares, count) of the good pixels of a sub-plane."""
    h, w = plane.shape
    gh, gw = -(-h // cell), -(-w // cell)
    pad = ((0, gh * cell - h), (0, gw * cell - w))
    v = np.pad(np.where(good, plane, 0.0), pad).reshape(gh, cell, gw, cell)
    g = np.pad(good, pad).reshape(gh, cell, gw, cell)
    return (
        v.sum(axis=(1, 3), dtype=np.float64),
        (v.astype(np.float64) ** 2).sum(axis=(1, 3)),
        g.sum(axis=(1, 3)).astype(np.float64),
    )


def _cell_centres(n: int, cell: int) -> np.ndarray:
    """Centre (sub-plane index) of each cell of `cell` pixels along a side of `n` pixels."""
    starts = np.arange(-(-n // cell)) * cell
    return starts + (np.minimum(cell, n - starts) - 1) / 2.0


def _total_degree_mask(degree: int) -> np.ndarray:
    i, j = np.meshgrid(np.arange(degree + 1), np.arange(degree + 1), indexing="ij")
    return (i + j) <= degree


@dataclass(frozen=True)
class _PlaneFit:
    coef: np.ndarray  # (d + 1, d + 1), total-degree terms only
    cov: np.ndarray  # covariance of the total-degree terms (in `_total_degree_mask` order)
    rel_stderr: float
    fit_rms: float
    cell_noise: float


def _fit_plane(
    plane: np.ndarray, good: np.ndarray, pos: tuple[int, int], tile: tuple[int, int],
    shape: tuple[int, int], degree: int,
) -> _PlaneFit:  # fmt: skip
    """Fit one CFA position's sub-plane by a weighted least-squares Legendre polynomial."""
    h, w = plane.shape
    cell = max(1, -(-max(h, w) // FLAT_CELLS))
    s, s2, n = _bin_cells(plane, good, cell)
    ok = n > 0
    m = np.where(ok, s / np.maximum(n, 1), 0.0)
    var_pix = np.where(n > 1, (s2 - n * m**2) / np.maximum(n - 1, 1), 0.0)
    ys, xs = _cell_centres(h, cell), _cell_centres(w, cell)  # sub-plane pixel indices
    vy = _legendre_rows(ys * tile[0] + pos[0], shape[0], degree)
    vx = _legendre_rows(xs * tile[1] + pos[1], shape[1], degree)
    keep = _total_degree_mask(degree)
    design = np.einsum("ai,bj->abij", vy, vx)[..., keep][ok]  # (cells, terms)
    # Normal equations with einsum: the Legendre basis keeps them well conditioned, and a
    # BLAS least-squares call on this small matrix is slow when OpenBLAS's threads compete
    # with other work for the cores.
    wn = n[ok]
    normal = np.einsum("ci,c,cj->ij", design, wn, design)
    a = np.linalg.solve(normal, np.einsum("ci,c->i", design, wn * m[ok]))
    fitted = np.einsum("ci,i->c", design, a)
    resid = m[ok] - fitted
    dof = max(int(ok.sum()) - a.size, 1)
    sigma2 = float(np.sum(wn * resid**2) / dof)  # per-pixel variance, misfit included
    cov = sigma2 * np.linalg.inv(normal)
    se = np.sqrt(np.maximum(np.einsum("ci,ij,cj->c", design, cov, design), 0.0))
    coef = np.zeros((degree + 1, degree + 1))
    coef[keep] = a
    return _PlaneFit(
        coef=coef,
        cov=cov,
        rel_stderr=float(np.sqrt(np.mean((se / fitted) ** 2))),
        fit_rms=float(np.sqrt(np.mean((resid / fitted) ** 2))),
        cell_noise=float(np.sqrt(np.mean(var_pix[ok] / n[ok] / fitted**2))),
    )


def _normalise(fit: _PlaneFit) -> tuple[np.ndarray, float]:
    """The coefficients scaled to 1 at the image centre ((W - 1) / 2, (H - 1) / 2, where the
    normalised coordinates are 0), and that value's relative standard error (common to the
    whole gain map of this position)."""
    degree = fit.coef.shape[0] - 1
    at_zero = np.polynomial.legendre.legvander(np.zeros(1), degree)[0]  # P_n(0)
    basis = np.outer(at_zero, at_zero)
    b = basis[_total_degree_mask(degree)]
    centre = float(np.sum(basis * fit.coef))
    return fit.coef / centre, math.sqrt(max(float(b @ fit.cov @ b), 0.0)) / centre


def build_flat(
    files: Sequence[CalibrationFile],
    dark: DarkFrame | None,
    degree: int = FLAT_DEGREE,
    saturation_level: float = 0.98,
) -> tuple[FlatField, RawFrame]:
    """The smoothed flat field of `files` (see `FlatField`) after subtracting `dark` (or the
    black level), and the first frame (for its size).

    Raises:
        ImagingError: a file cannot be decoded, differs in size or CFA from the first (or from
            the dark frames), is too dark (median below `FLAT_MIN_SIGNAL` of the range) or
            saturated (more than `FLAT_MAX_SATURATED` of its pixels).
    """
    first: RawFrame | None = None
    total = good = None
    for f, frame in _frames(files, "flat fields"):
        if dark is not None and dark.mean.shape != frame.data.shape:
            raise ImagingError(
                f"{f.label} {f.path.name!r}: {frame.width} x {frame.height} px, unlike the dark "
                f"frames ({dark.mean.shape[1]} x {dark.mean.shape[0]} px); flat fields and dark "
                "frames must come from the camera and image size of the photos"
            )
        black = _black_map(frame)
        sat = frame.data >= black + saturation_level * (frame.white_level - black)
        _check_flat_exposure(f, frame, sat)
        signal = frame.data.astype(np.float32) - (dark.mean if dark is not None else black)
        if first is None:
            first, total, good = frame, signal, ~sat
        else:
            total += signal
            good &= ~sat
    assert first is not None and total is not None and good is not None
    mean = total / len(files)
    ph, pw = first.cfa.shape
    shape = (first.height, first.width)
    fits = [
        [_fit_plane(mean[dy::ph, dx::pw], good[dy::ph, dx::pw], (dy, dx), (ph, pw), shape, degree)
         for dx in range(pw)]
        for dy in range(ph)
    ]  # fmt: skip
    normed = [[_normalise(f) for f in row] for row in fits]
    coef = np.stack([np.stack([c for c, _ in row]) for row in normed])
    centre_se = np.array([[se for _, se in row] for row in normed])
    grid = np.array([[[f.rel_stderr, f.fit_rms, f.cell_noise] for f in row] for row in fits])
    flat = FlatField(coef, shape, grid[..., 0], grid[..., 1], grid[..., 2], len(files), centre_se)
    return flat, first


def _check_flat_exposure(f: CalibrationFile, frame: RawFrame, saturated: np.ndarray) -> None:
    frac = float(saturated.mean())
    if frac > FLAT_MAX_SATURATED:
        raise ImagingError(
            f"{f.label} {f.path.name!r}: {100 * frac:.2g}% of its pixels are saturated; take "
            "the flat field with a shorter exposure (its brightest part at about half of the "
            "raw range)"
        )
    black = float(frame.black.mean())
    median = float(np.median(frame.data[::4, ::4])) - black
    if median < FLAT_MIN_SIGNAL * (frame.white_level - black):
        raise ImagingError(
            f"{f.label} {f.path.name!r}: too dark, its median is {median:.0f} DN above black "
            f"({100 * median / (frame.white_level - black):.2g}% of the raw range, at least "
            f"{100 * FLAT_MIN_SIGNAL:g}% needed); expose the flat field to about half of the range"
        )


def build_calibration(spec: CalibrationSpec, saturation_level: float = 0.98) -> Calibration:
    """Decode, check and combine the calibration frames of `spec` (dark first, then flat).

    Raises:
        ImagingError: see `build_dark`, `build_flat`; the message names the scene field.
    """
    if not spec.flat_field and not spec.dark_frames:
        raise ImagingError("calibration: neither flat fields nor dark frames are given")
    dark = flat = None
    if spec.dark_frames:
        dark, probe = build_dark(spec.dark_frames)
    if spec.flat_field:
        flat, probe = build_flat(spec.flat_field, dark, spec.flat_degree, saturation_level)
    return Calibration(spec, (probe.height, probe.width), probe.cfa, dark, flat)


def combined_sha256(digests: Sequence[str]) -> str:
    """One digest for several files (a bracket): SHA-256 of their hex digests joined by ','."""
    if len(digests) == 1:
        return digests[0]
    return hashlib.sha256(",".join(digests).encode()).hexdigest()
