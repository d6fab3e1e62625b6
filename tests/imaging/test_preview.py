"""Preview PNGs (issue 6): cached with the measurements, cheap to make, still showing the ROIs.

A second `measure_photos` run whose measurement cache hits must not decode any photo, yet write
every preview into a new folder; a missing, damaged or stale cached preview means decoding again.
The previews themselves: the size limit, ROI outlines where the ROIs are, the colours of the CFA
positions, saturated pixels, and the tone mapping against a plain float reference.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from stairfit import imaging
from stairfit.imaging import _pipeline, _preview, synthetic

EXPOSURE = imaging.Exposure(exposure_time_s=1 / 100, f_number=8.0, iso=200)
SIZE = (600, 400)  # (width, height)
BACKGROUND = np.full(3, 1000.0) * EXPOSURE.scale
FACES = {
    "f0": [(40, 40), (240, 40), (240, 200), (40, 200)],
    "f1": [(320, 60), (540, 60), (540, 340), (320, 340)],
}
GREEN = (0, 220, 0)
YELLOW = (0, 220, 255)
MAGENTA = (255, 0, 255)


def _photo(path: Path, seed: int = 0, size: tuple[int, int] = SIZE, **kw) -> Path:
    radiance = {
        "f0": np.array([3000.0, 2000.0, 1000.0]) * EXPOSURE.scale,
        "f1": np.array([800.0, 1600.0, 2400.0]) * EXPOSURE.scale,
    }
    radiance |= kw.pop("radiance", {})
    photo = synthetic.render_photo(
        size, FACES, radiance, EXPOSURE, background=BACKGROUND, seed=seed, **kw
    )
    return photo.write_dng(path)


def _specs(tmp_path: Path, n: int = 2) -> list[imaging.PhotoSpec]:
    return [imaging.PhotoSpec(_photo(tmp_path / f"p{k}.dng", seed=k), rois=FACES) for k in range(n)]


@pytest.fixture
def count_decodes(monkeypatch) -> list[str]:
    """The names of the photos `measure_photos` decodes (in this process)."""
    decoded: list[str] = []
    real = _pipeline.decode_raw

    def counting(path, name=None):
        decoded.append(Path(path).name)
        return real(path, name)

    monkeypatch.setattr(_pipeline, "decode_raw", counting)
    return decoded


def _cached_pngs(cache: Path) -> list[str]:
    return sorted(p.name for p in _pipeline.preview_cache_dir(cache).glob("*.png"))


# --- the cache -------------------------------------------------------------------------------


def test_cache_hit_decodes_nothing_and_still_writes_every_preview(tmp_path, monkeypatch) -> None:
    specs = _specs(tmp_path)
    cache = tmp_path / "cache" / "measurements.csv"
    first = imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "a", max_workers=1)
    assert len(_cached_pngs(cache)) == 2

    def no_decoding(path, name=None):
        raise AssertionError(f"{path} was decoded although its rows and preview are cached")

    monkeypatch.setattr(_pipeline, "decode_raw", no_decoding)
    again = imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "b", max_workers=1)
    assert again.to_csv() == first.to_csv()
    for spec in specs:
        made = imaging.preview_path(tmp_path / "a", spec).read_bytes()
        copied = imaging.preview_path(tmp_path / "b", spec).read_bytes()
        assert copied == made
    # no temporary files are left behind by the atomic writes
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["p0.dng.png", "p1.dng.png"]


def test_previews_made_by_worker_processes_are_cached_too(tmp_path, monkeypatch) -> None:
    specs = _specs(tmp_path)
    cache = tmp_path / "m.csv"
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "a", max_workers=2)
    assert len(_cached_pngs(cache)) == 2

    def no_decoding(path, name=None):
        raise AssertionError("decoded")

    monkeypatch.setattr(_pipeline, "decode_raw", no_decoding)
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "b", max_workers=1)
    assert all(imaging.preview_path(tmp_path / "b", s).exists() for s in specs)


def test_missing_or_damaged_cached_preview_means_decoding_again(tmp_path, count_decodes) -> None:
    specs = _specs(tmp_path)
    cache = tmp_path / "m.csv"
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "a", max_workers=1)
    folder = _pipeline.preview_cache_dir(cache)
    sha = imaging.file_sha256(specs[0].path)
    key = imaging.cache_key(specs[0], imaging.ExtractionSettings())
    first = folder / _pipeline.cached_preview_name(sha, key)
    assert first.exists()

    first.unlink()
    count_decodes.clear()
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "b", max_workers=1)
    assert count_decodes == ["p0.dng"]
    assert first.exists()  # made again

    first.write_bytes(first.read_bytes()[:-20])  # a truncated PNG
    count_decodes.clear()
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "c", max_workers=1)
    assert count_decodes == ["p0.dng"]
    assert cv2.imread(str(imaging.preview_path(tmp_path / "c", specs[0]))) is not None


def test_stale_previews_are_not_reused_and_are_pruned(tmp_path, count_decodes) -> None:
    specs = _specs(tmp_path)
    cache = tmp_path / "m.csv"
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "a", max_workers=1)
    before = _cached_pngs(cache)

    # an ROI moves: the rows and the preview of that photo are made again, the old preview goes
    moved = dict(FACES, f0=[(50, 50), (230, 50), (230, 190), (50, 190)])
    specs2 = [imaging.PhotoSpec(specs[0].path, rois=moved), specs[1]]
    count_decodes.clear()
    imaging.measure_photos(specs2, cache=cache, preview_dir=tmp_path / "b", max_workers=1)
    assert count_decodes == ["p0.dng"]
    after = _cached_pngs(cache)
    assert len(after) == 2 and len(set(after) & set(before)) == 1

    # the saturation level (which pixels are magenta) is part of the key
    count_decodes.clear()
    imaging.measure_photos(
        specs2,
        imaging.ExtractionSettings(saturation_level=0.9),
        cache=cache,
        preview_dir=tmp_path / "c",
        max_workers=1,
    )
    assert sorted(count_decodes) == ["p0.dng", "p1.dng"]
    assert len(_cached_pngs(cache)) == 2


def test_other_preview_code_or_size_means_decoding_again(tmp_path, count_decodes, monkeypatch):
    specs = _specs(tmp_path, 1)
    cache = tmp_path / "m.csv"
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "a", max_workers=1)
    monkeypatch.setattr(_pipeline, "PREVIEW_VERSION", _pipeline.PREVIEW_VERSION + 1)
    count_decodes.clear()
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "b", max_workers=1)
    assert count_decodes == ["p0.dng"]
    monkeypatch.setattr(_pipeline, "PREVIEW_MAX_SIZE", 800)
    count_decodes.clear()
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "c", max_workers=1)
    assert count_decodes == ["p0.dng"]


def test_cache_without_previews_then_with(tmp_path, count_decodes) -> None:
    specs = _specs(tmp_path, 1)
    cache = tmp_path / "m.csv"
    imaging.measure_photos(specs, cache=cache, max_workers=1)
    assert not _pipeline.preview_cache_dir(cache).exists()  # nothing rendered for nobody
    count_decodes.clear()
    imaging.measure_photos(specs, cache=cache, max_workers=1)
    assert count_decodes == []
    # previews wanted now: decoded once to make them, then cached
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "a", max_workers=1)
    assert count_decodes == ["p0.dng"]
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "b", max_workers=1)
    assert count_decodes == ["p0.dng"]


def test_failed_photo_gets_a_preview_but_no_cached_one(tmp_path) -> None:
    good, bad = _specs(tmp_path)
    outside = dict(FACES, f1=[(320, 60), (700, 60), (700, 340), (320, 340)])  # past x = 599.5
    bad = imaging.PhotoSpec(bad.path, rois=outside)
    cache = tmp_path / "m.csv"
    with pytest.raises(imaging.ImagingError, match="1 of 2 photos"):
        imaging.measure_photos([good, bad], cache=cache, preview_dir=tmp_path / "a", max_workers=1)
    img = cv2.imread(str(imaging.preview_path(tmp_path / "a", bad)))
    assert img is not None
    assert not np.any(np.all(img == GREEN, axis=-1))  # drawn without ROIs
    assert len(_cached_pngs(cache)) == 1  # only the photo that was measured


# --- the preview image -----------------------------------------------------------------------


def _frame(tmp_path: Path, **kw) -> imaging.RawFrame:
    return imaging.decode_raw(_photo(tmp_path / "f.dng", **kw))


def _extent(img_mask: np.ndarray, box: tuple[float, float, float, float], pad: int = 4) -> tuple:
    """(x0, x1, y0, y1) of the True pixels of `img_mask` near `box` (preview px)."""
    x0, x1, y0, y1 = (round(v) for v in box)
    sub = img_mask[y0 - pad : y1 + pad + 1, x0 - pad : x1 + pad + 1]
    cols, rows = np.nonzero(sub.any(axis=0))[0], np.nonzero(sub.any(axis=1))[0]
    return cols[0] + x0 - pad, cols[-1] + x0 - pad, rows[0] + y0 - pad, rows[-1] + y0 - pad


def test_default_size_limit_and_roi_outlines_where_the_rois_are(tmp_path) -> None:
    # 3600 x 400 raw: binned 1800 x 200, shrunk to the 1600 px default (a fractional factor)
    frame = _frame(tmp_path, size=(3600, 400))
    shape = (frame.height, frame.width)
    rois = {n: imaging.roi_mask(p, shape, 8, photo="f", wedge=n) for n, p in FACES.items()}
    img = imaging.render_preview(frame, rois)
    assert img.shape == (178, 1600, 3)
    assert _preview.PREVIEW_MAX_SIZE == 1600
    s = img.shape[1] / frame.width

    def to_preview(v: float) -> float:  # docs/imaging.md §Pixels
        return (v + 0.5) * s - 0.5

    green = np.all(img == GREEN, axis=-1)
    b, g, r = (img[..., c].astype(int) for c in range(3))
    yellowish = (b < 80) & (g > 190) & (r > 220)  # the anti-aliased 1 px polygon lines
    for name, roi in rois.items():
        poly = np.array(FACES[name], dtype=float)
        box = [to_preview(v) for v in (*poly[:, 0][[0, 1]], poly[0, 1], poly[2, 1])]
        for got, want in zip(_extent(yellowish, box), box, strict=True):
            assert abs(got - want) <= 1.0
        ys, xs = np.nonzero(roi.mask)
        inner = [
            to_preview(v)
            for v in (roi.x0 + xs.min(), roi.x0 + xs.max(), roi.y0 + ys.min(), roi.y0 + ys.max())
        ]
        # the green 2 px outline runs along the eroded mask's edge, inside the polygon
        for got, want in zip(_extent(green, inner), inner, strict=True):
            assert abs(got - want) <= 1.5
        assert inner[0] - box[0] > 3  # 8 raw px of erosion are 3.6 preview px: visible


def test_size_limit_with_whole_and_fractional_factors(tmp_path) -> None:
    frame = _frame(tmp_path)  # 600 x 400 raw, 300 x 200 binned
    for max_size, shape in ((300, (200, 300)), (150, (100, 150)), (100, (67, 100)), (70, (47, 70))):
        img = imaging.render_preview(frame, max_size=max_size)
        assert img.shape == (*shape, 3)


@pytest.mark.parametrize("cfa", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_colours_follow_the_cfa_pattern(tmp_path, cfa: str) -> None:
    """A red face looks red and a blue face blue in the preview, whatever the Bayer tile."""
    red = np.array([4000.0, 400.0, 400.0]) * EXPOSURE.scale
    blue = np.array([400.0, 400.0, 4000.0]) * EXPOSURE.scale
    frame = _frame(
        tmp_path,
        radiance={"f0": red, "f1": blue},
        sensor=synthetic.SensorModel(cfa=cfa),
        texture_amplitude=0.0,
    )
    img = imaging.render_preview(frame, max_size=150)  # half of the binned size
    b, g, r = (img[20:50, 20:50, c].astype(float).mean() for c in range(3))  # inside f0
    assert r > g + 40 and r > b + 40
    b, g, r = (img[40:75, 90:125, c].astype(float).mean() for c in range(3))  # inside f1
    assert b > g + 40 and b > r + 40


def test_saturated_pixels_are_magenta_after_shrinking(tmp_path) -> None:
    frame = _frame(tmp_path, radiance={"f0": np.full(3, 1e5) * EXPOSURE.scale})
    img = imaging.render_preview(frame, max_size=150)  # 4 raw px per preview px
    magenta = np.all(img == MAGENTA, axis=-1)
    assert magenta[12:48, 12:58].all()  # f0: raw (40..240) x (40..200)
    assert not magenta[:, 80:].any()  # f1 and the background are not saturated
    unsaturated = imaging.render_preview(_frame(tmp_path), max_size=150)
    assert not np.all(unsaturated == MAGENTA, axis=-1).any()


def test_tone_mapping_matches_a_float_reference(tmp_path) -> None:
    """Without shrinking, the lookup tables give what plain float arithmetic gives (+-1 level).

    The reference is the rendering documented in docs/imaging.md §Previews, written out here
    with NumPy floats: 2 x 2 binning (greens averaged), black subtracted, grey-world gains and
    the 99.5th percentile from every 4th pixel, a 1/2.2 gamma.
    """
    frame = _frame(tmp_path)
    img = imaging.render_preview(frame).astype(int)
    d = frame.data.astype(np.float64)
    black = frame.black.astype(np.float64)
    planes = {0: [], 1: [], 2: []}
    for dy in range(2):
        for dx in range(2):
            planes[int(frame.cfa[dy, dx])].append(d[dy::2, dx::2] - black[dy, dx])
    rgb = np.stack([np.mean(planes[c], axis=0) for c in range(3)], axis=-1)
    means = rgb[::4, ::4].mean(axis=(0, 1))
    rgb = rgb * (means.max() / means)
    hi = np.percentile(rgb[::4, ::4].max(axis=2), 99.5)
    ref = np.clip(rgb / hi, 0, 1) ** (1 / 2.2) * 255
    ref = ref[..., ::-1]  # BGR
    assert img.shape == ref.shape == (200, 300, 3)
    # truncation to 8 bits, the uint16 mean of the greens and float32 tables: within 1.5 levels
    assert np.abs(img - ref).max() <= 1.5


def test_linear_frames_are_previewed(tmp_path) -> None:
    """A linear (demosaiced) frame: planes at full resolution, saturation per plane."""
    rng = np.random.default_rng(1)
    data = rng.integers(100, 4000, size=(300, 500, 3)).astype(np.uint16)
    data[10:60, 10:60, 1] = 16383  # saturated green
    frame = imaging.RawFrame(
        path=tmp_path / "lin.dng",
        name="lin.dng",
        sha256="0" * 64,
        data=data,
        cfa=None,
        black=np.full(3, 64.0, dtype=np.float32),
        white_level=16383.0,
        camera_whitebalance=(1.0, 1.0, 1.0),
        exif_exposure_time_s=None,
        exif_f_number=None,
        exif_iso=None,
        make="",
        model="",
    )
    img = imaging.render_preview(frame, max_size=250)
    assert img.shape == (150, 250, 3)
    magenta = np.all(img == MAGENTA, axis=-1)
    assert magenta[6:29, 6:29].all() and magenta.sum() < 40 * 40


def test_png_settings_are_lossless(tmp_path) -> None:
    """Huffman-only deflate and the "sub" filter still give back the image exactly."""
    img = imaging.render_preview(_frame(tmp_path))
    png = _preview.encode_png(img, "x")
    back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert np.array_equal(back, img)


# --- issue 42: a cache is verified against what it claims to be --------------------------------

SECRET = b"k" * 32


def test_swapped_cached_previews_are_made_again(tmp_path, count_decodes) -> None:
    # issue 42 case 4: two swapped PNGs showed the wrong photos
    specs = _specs(tmp_path)
    cache = tmp_path / "cache" / "measurements.csv"
    kw = {"cache": cache, "max_workers": 1, "cache_secret": SECRET}
    imaging.measure_photos(specs, preview_dir=tmp_path / "a", **kw)
    one, two = (_pipeline.preview_cache_dir(cache) / n for n in _cached_pngs(cache))
    a, b = one.read_bytes(), two.read_bytes()
    one.write_bytes(b), two.write_bytes(a)
    count_decodes.clear()
    table = imaging.measure_photos(specs, preview_dir=tmp_path / "b", **kw)
    assert sorted(count_decodes) == ["p0.dng", "p1.dng"]  # neither swapped preview was used
    assert table.from_cache == ()
    for spec in specs:
        assert (tmp_path / "a" / f"{spec.name}.png").read_bytes() == (
            tmp_path / "b" / f"{spec.name}.png"
        ).read_bytes()


def _forge(cache: Path, secret: bytes | None) -> None:
    """Scale every value of the cache by 2 and recompute its checksum as stairfit would
    (with `secret`, or a plain SHA-256 when None)."""
    from stairfit.imaging._cache import checksum_path, table_digest

    table = imaging.MeasurementTable.read_csv(cache)
    forged = imaging.MeasurementTable(
        tuple(dataclasses.replace(r, value=2 * r.value) for r in table.rows)
    )
    blob = forged.to_csv().encode()
    check = json.loads(checksum_path(cache).read_text())
    check["digest"] = table_digest(blob, check["table_version"], secret, check["previews"])
    if secret is None:
        check["scheme"] = "sha256"
    cache.write_bytes(blob)
    checksum_path(cache).write_text(json.dumps(check))


@pytest.mark.parametrize("forger_key", [None, b"x" * 32], ids=["plain-sha256", "another-key"])
def test_an_edited_cache_with_a_recomputed_checksum_is_not_trusted(
    tmp_path, count_decodes, forger_key
) -> None:
    # issue 42 case 5: the editor does not hold this user's key
    specs = _specs(tmp_path)
    cache = tmp_path / "cache" / "measurements.csv"
    first = imaging.measure_photos(specs, cache=cache, max_workers=1, cache_secret=SECRET)
    assert first.from_cache == ()
    _forge(cache, forger_key)
    count_decodes.clear()
    with pytest.warns(imaging.ImagingWarning, match="measuring every photo again"):
        again = imaging.measure_photos(specs, cache=cache, max_workers=1, cache_secret=SECRET)
    assert again.to_csv() == first.to_csv() and again.from_cache == ()
    assert sorted(count_decodes) == ["p0.dng", "p1.dng"]
    hit = imaging.measure_photos(specs, cache=cache, max_workers=1, cache_secret=SECRET)
    assert hit.from_cache == ("p0.dng", "p1.dng") and hit.to_csv() == first.to_csv()


@pytest.mark.skipif(not hasattr(__import__("os"), "mkfifo"), reason="POSIX named pipes")
def test_a_named_pipe_in_the_cache_is_skipped_not_waited_for(tmp_path) -> None:
    # issue 42 case 7: reading a FIFO in place of the cache blocked forever
    import os

    specs = _specs(tmp_path, 1)
    cache = tmp_path / "cache" / "measurements.csv"
    cache.parent.mkdir()
    os.mkfifo(cache)
    with pytest.warns(imaging.ImagingWarning, match="named pipe"):
        table = imaging.measure_photos(specs, cache=cache, max_workers=1, cache_secret=SECRET)
    assert len(table) == 6


def test_leftover_temporary_files_in_the_preview_cache_are_removed(tmp_path) -> None:
    # issue 42 case 11: a kill while writing the preview cache left a .tmp no run removed
    specs = _specs(tmp_path, 1)
    cache = tmp_path / "cache" / "measurements.csv"
    folder = _pipeline.preview_cache_dir(cache)
    folder.mkdir(parents=True)
    (folder / ".x.png.0123abcd.tmp").write_bytes(b"half a png")
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "a", max_workers=1)
    assert [p.name for p in folder.iterdir() if p.name.startswith(".")] == []
