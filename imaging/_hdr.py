"""Radiometric corrections of one view: dark frame, flat field and HDR bracket merge.

`prepare_radiometry` turns the decoded exposures of one view (one photo, or an HDR bracket of
several) into the image the ROI statistics are computed on: float32 DN above black at the
exposure of the first file (the reference), the master dark subtracted (or the black level),
the exposures merged in the linear raw domain, divided by the flat field's gain, NaN where no
exposure gives a usable value (all clipped). The block standard-error estimator then runs on
it unchanged (imaging/_extract.py). See docs/imaging.md §Flat fields and dark frames and
§HDR brackets.

The merge: for each pixel, exposure k is used unless it is clipped at that pixel, or the mean
of the 8 nearest pixels of the same CFA colour is above `HDR_HIGH` of its saturation threshold
(close to clipping), or that mean is below `HDR_LOW` of the raw range (near black) while a
longer exposure is usable. The value is `sum_k s_k / sum_k h_k` over the exposures used, with
`s_k` the signal (DN) and `h_k` the exposure relative to the reference (`t ISO / N^2`): the
exposure-time-weighted mean of the per-exposure radiance estimates `s_k / h_k`, which is the
maximum-likelihood combination for shot noise and needs no noisy per-pixel variances. The
selection looks at the neighbours, not at the pixel itself, so a pixel's own noise does not
decide which exposures it is averaged from (that would bias the mean near the thresholds).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from ._calibration import Calibration, combined_sha256
from ._decode import RawFrame
from ._errors import ImagingError
from ._exposure import Exposure
from ._extract import ChannelStats, ExtractionSettings
from ._roi import RoiMask

HDR_HIGH = 0.9
"""An exposure is not used where its neighbours are above this fraction of its clip level."""
HDR_LOW = 0.01
"""...nor where they are below this fraction of the raw range while a longer one is usable."""


@dataclass(frozen=True)
class BracketMember:
    """A further exposure of the same view in an HDR bracket (`PhotoSpec.bracket`).

    Attributes:
        path: the RAW file.
        exposure_time_s, f_number, iso: overrides of its own exposure tags (None = the tags).
    """

    path: Path
    exposure_time_s: float | None = None
    f_number: float | None = None
    iso: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))


@dataclass(frozen=True, eq=False)
class Radiometry:
    """One view after dark, flat and bracket merge (see the module docstring).

    Attributes:
        frame: the image the statistics are computed on: the reference exposure's metadata,
            `data` float32 DN above black at the reference exposure (corrected), NaN where no
            exposure is usable, `black` zero and `white_level` infinite (clipping is already
            decided).
        members: the decoded exposures, the reference first (the pipeline finds the markers
            in the one that shows them best).
        black_per_channel: the mean R, G, B level subtracted (the master dark's, or the black).
        dark_variance: (H, W) float32, or None: the variance (DN^2, reference units) the master
            dark's own noise adds to each pixel of `frame.data`.
        flat_rel_stderr: (3,) the flat's relative standard error per channel, or None.
        description: what was applied, e.g. "dark(8)+flat(2)+bracket(3)".
    """

    frame: RawFrame
    members: tuple[RawFrame, ...]
    black_per_channel: tuple[float, float, float]
    dark_variance: np.ndarray | None
    flat_rel_stderr: np.ndarray | None
    description: str

    def common_stderr_dn(
        self, roi: RoiMask, stats: Sequence[ChannelStats]
    ) -> tuple[float, float, float]:
        """(R, G, B) standard error (DN) of an ROI mean from the calibration frames' noise.

        The master dark's noise averaged over the ROI's used pixels (independent pixels) and
        the flat field's relative error times the mean. Both are the same in every photo that
        uses these calibration frames (docs/imaging.md §Flat fields and dark frames).
        """
        out = []
        rows, cols = roi.box()
        data = self.frame.data[rows, cols]
        cfa = self.frame.cfa
        assert cfa is not None
        ys = np.arange(roi.y0, roi.y0 + roi.mask.shape[0]) % cfa.shape[0]
        xs = np.arange(roi.x0, roi.x0 + roi.mask.shape[1]) % cfa.shape[1]
        colour = cfa[ys[:, None], xs[None, :]]
        used = roi.mask & np.isfinite(data)
        for c, s in enumerate(stats):
            var = 0.0
            if self.dark_variance is not None and s.n_pixels > 0:
                sel = used & (colour == c)
                var += float(self.dark_variance[rows, cols][sel].sum(dtype=np.float64))
                var /= s.n_pixels**2
            if self.flat_rel_stderr is not None and math.isfinite(s.mean_dn):
                var += (s.mean_dn * float(self.flat_rel_stderr[c])) ** 2
            out.append(math.sqrt(var))
        return tuple(out)  # type: ignore[return-value]


def _check_members(frames: Sequence[RawFrame], photo: str) -> None:
    ref = frames[0]
    for f in frames[1:]:
        same_cfa = (f.cfa is None) == (ref.cfa is None) and (
            f.cfa is None or np.array_equal(f.cfa, ref.cfa)
        )
        if f.data.shape != ref.data.shape or not same_cfa:
            raise ImagingError(
                f"photo {photo!r}: bracket member {f.name!r} is {f.width} x {f.height} px, CFA "
                f"{f.cfa_string or 'linear'}, unlike {ref.name!r} ({ref.width} x {ref.height} "
                f"px, CFA {ref.cfa_string or 'linear'}); a bracket's files must come from one "
                "camera at one image size"
            )


def _cfa_map(frame: RawFrame, values: np.ndarray) -> np.ndarray:
    """(H, W) map of a per-CFA-position (or per-plane, for a linear file) quantity."""
    if frame.cfa is None:
        return np.broadcast_to(np.asarray(values, np.float32), frame.data.shape)
    ph, pw = frame.cfa.shape
    reps = (-(-frame.height // ph), -(-frame.width // pw))
    return np.tile(np.asarray(values, np.float32), reps)[: frame.height, : frame.width]


def _signal(frame: RawFrame, calibration: Calibration | None) -> np.ndarray:
    """float32 DN above the master dark (or the black level)."""
    if calibration is not None:
        return calibration.signal(frame)
    return frame.data.astype(np.float32) - _cfa_map(frame, frame.black)


def _clip_levels(frame: RawFrame, settings: ExtractionSettings) -> tuple[np.ndarray, np.ndarray]:
    """(raw clip threshold map, signal range map): a raw value at or above the first is clipped."""
    black = _cfa_map(frame, frame.black)
    span = frame.white_level - black
    return black + settings.saturation_level * span, span


def _neighbour_mean(signal: np.ndarray, frame: RawFrame) -> np.ndarray:
    """Mean of the 8 nearest pixels of the same CFA position (or plane), the pixel excluded."""
    out = np.empty_like(signal)
    if frame.cfa is None:
        for c in range(signal.shape[2]):
            box = cv2.boxFilter(signal[..., c], -1, (3, 3), normalize=False)
            out[..., c] = (box - signal[..., c]) / 8.0
        return out
    ph, pw = frame.cfa.shape
    for dy in range(ph):
        for dx in range(pw):
            sub = np.ascontiguousarray(signal[dy::ph, dx::pw])
            box = cv2.boxFilter(sub, -1, (3, 3), normalize=False, borderType=cv2.BORDER_REFLECT)
            out[dy::ph, dx::pw] = (box - sub) / 8.0
    return out


def _merge(
    frames: Sequence[RawFrame],
    exposures: Sequence[Exposure],
    calibration: Calibration | None,
    settings: ExtractionSettings,
) -> tuple[np.ndarray, np.ndarray]:
    """Merged signal (reference DN; NaN where nothing is usable) and the dark's coefficient
    `n_used / sum h` per pixel (how a dark-frame error enters the merged value)."""
    h = [exposures[0].scale / e.scale for e in exposures]
    order = sorted(range(len(frames)), key=lambda k: -h[k])  # longest exposure first
    num = np.zeros(frames[0].data.shape, np.float32)
    den = np.zeros_like(num)
    count = np.zeros_like(num)
    fallback = np.zeros(num.shape, bool)  # a longer usable exposure was seen
    longest = np.full(num.shape, -1, np.int16)
    signals = {}
    for k in order:
        sig = _signal(frames[k], calibration)
        clip, span = _clip_levels(frames[k], settings)
        nb = _neighbour_mean(sig, frames[k])
        usable = (frames[k].data < clip) & (nb < HDR_HIGH * settings.saturation_level * span)
        take = usable & (nb >= HDR_LOW * span)
        longest[usable & ~fallback] = k
        fallback |= usable
        num += np.where(take, sig, 0.0)
        den += np.where(take, np.float32(h[k]), 0.0)
        count += take
        signals[k] = (sig, take)
    # pixels where every usable exposure is near black: the longest usable one alone
    alone = (count == 0) & (longest >= 0)
    for k in order:
        sel = alone & (longest == k)
        if sel.any():
            num[sel] = signals[k][0][sel]
            den[sel] = h[k]
            count[sel] = 1
    with np.errstate(invalid="ignore", divide="ignore"):
        merged = np.where(den > 0, num / den, np.nan).astype(np.float32)
        coef = np.where(den > 0, count / den, 0.0).astype(np.float32)
    return merged, coef


def prepare_radiometry(
    frames: Sequence[RawFrame],
    exposures: Sequence[Exposure],
    calibration: Calibration | None,
    settings: ExtractionSettings,
    photo: str,
) -> Radiometry:
    """One view's exposures (reference first) after dark, bracket merge and flat field.

    Raises:
        ImagingError: the exposures differ in size or CFA, or do not match the calibration
            frames; the message names the photo and the file.
    """
    _check_members(frames, photo)
    ref = frames[0]
    if calibration is not None:
        for f in frames:
            calibration.check_frame(f)
    if len(frames) > 1:
        data, coef = _merge(frames, exposures, calibration, settings)
    else:
        clip, _ = _clip_levels(ref, settings)
        data = np.where(ref.data < clip, _signal(ref, calibration), np.nan).astype(np.float32)
        coef = None
    dark_var = flat_rel = None
    if calibration is not None and calibration.dark is not None:
        var = _cfa_map(ref, calibration.dark_variance())
        dark_var = var if coef is None else var * coef**2
    if calibration is not None and calibration.flat is not None:
        gain = calibration.flat.gain()
        data /= gain
        if dark_var is not None:
            dark_var = dark_var / gain**2
        flat_rel = _per_channel(ref, calibration.flat.rel_stderr)
    black = _black_per_channel(ref, calibration)
    shas = [f.sha256 for f in frames]
    zeros = np.zeros_like(ref.black)
    frame = replace(ref, data=data, black=zeros, white_level=math.inf, sha256=combined_sha256(shas))
    tags = [calibration.describe()] if calibration is not None else []
    if len(frames) > 1:
        tags.append(f"bracket({len(frames)})")
    return Radiometry(frame, tuple(frames), black, dark_var, flat_rel, "+".join(tags))


def _per_channel(frame: RawFrame, per_position: np.ndarray) -> np.ndarray:
    """(3,) RMS over the CFA positions of each colour of a per-position quantity."""
    assert frame.cfa is not None
    vals = np.asarray(per_position, float)
    return np.array([math.sqrt(float(np.mean(vals[frame.cfa == c] ** 2))) for c in range(3)])


def _black_per_channel(
    frame: RawFrame, calibration: Calibration | None
) -> tuple[float, float, float]:
    """The mean level subtracted per channel: the master dark's, or the black level."""
    if calibration is None or calibration.dark is None or frame.cfa is None:
        return frame.black_level_per_channel()
    ph, pw = frame.cfa.shape
    means = np.array(
        [[float(calibration.dark.mean[dy::ph, dx::pw].mean()) for dx in range(pw)]
         for dy in range(ph)]
    )  # fmt: skip
    return tuple(float(means[frame.cfa == c].mean()) for c in range(3))  # type: ignore[return-value]
