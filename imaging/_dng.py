"""The header of a DNG file checked against its data before LibRaw decodes it.

LibRaw trusts a DNG's tags: a file whose ImageWidth is one less than its strips hold decodes
into a sheared image, one whose Compression says lossless JPEG over uncompressed data decodes
into noise, a WhiteLevel of 0 becomes 65535. None of that raises. So the raw image's IFDs (the
full-resolution CFA or LinearRaw images: NewSubFileType 0) are read with tifffile and their
fields checked against each other and against the bytes they point to; a field that does not
fit is a `DngHeaderError` naming it. Only DNG files (DNGVersion present) are checked: the
proprietary formats LibRaw reads (CR2, NEF, ...) use their own compression values.
"""

from __future__ import annotations

import io
import math
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import tifffile

from ._errors import ImagingError

DNG_COMPRESSION = {1: "uncompressed", 7: "lossless JPEG", 8: "deflate", 34892: "lossy JPEG",
                   52546: "JPEG XL"}  # fmt: skip
"""The Compression values the DNG specification (1.7) allows for image data."""
RAW_PHOTOMETRIC = {32803: "CFA", 34892: "LinearRaw"}
"""PhotometricInterpretation of raw image data in a DNG."""
_JPEG = (7, 34892)
_SOF = {0xC0, 0xC1, 0xC2, 0xC3}  # start-of-frame markers: baseline, extended, progressive, lossless


class DngHeaderError(ImagingError):
    """A DNG header field that contradicts the image data (`field` names it)."""

    def __init__(self, field: str, problem: str) -> None:
        super().__init__(f"DNG field {field} {problem}")
        self.field = field


@dataclass(frozen=True)
class _Ifd:
    """The fields of one raw image IFD that the checks use."""

    width: int
    length: int
    bits: tuple[int, ...]
    samples: int
    compression: int
    planar: int
    tile: tuple[int, int] | None  # (width, length) of a tile; None for strips
    rows_per_strip: int
    offsets: tuple[int, ...]
    counts: tuple[int, ...]
    white: tuple[float, ...] | None
    black: tuple[float, ...] | None


def _values(page: tifffile.TiffPage, code: int) -> tuple[float, ...] | None:
    """A tag's values as numbers (RATIONALs as num / den); None when absent."""
    tag = page.tags.get(code)
    if tag is None:
        return None
    value = tag.value
    value = value if isinstance(value, tuple | list) else (value,)
    if tag.dtype in (5, 10):  # RATIONAL, SRATIONAL: (num, den) pairs flattened by tifffile
        pairs = zip(value[::2], value[1::2], strict=True)
        return tuple(n / d if d else math.nan for n, d in pairs)
    return tuple(float(v) for v in value)


def _ifd(page: tifffile.TiffPage) -> _Ifd:
    bits = page.tags.get(258)
    bits_values = bits.value if bits is not None else 1
    tiled = page.tags.get(322) is not None
    return _Ifd(
        width=int(page.imagewidth),
        length=int(page.imagelength),
        bits=tuple(bits_values) if isinstance(bits_values, tuple) else (int(bits_values),),
        samples=int(page.samplesperpixel),
        compression=int(page.compression),
        planar=int(page.planarconfig),
        tile=(int(page.tilewidth), int(page.tilelength)) if tiled else None,
        rows_per_strip=int(page.rowsperstrip) or int(page.imagelength),
        offsets=tuple(int(v) for v in page.dataoffsets),
        counts=tuple(int(v) for v in page.databytecounts),
        white=_values(page, 50717),
        black=_values(page, 50714),
    )


def _raw_pages(tif: tifffile.TiffFile) -> Iterator[tifffile.TiffPage]:
    """IFD0 and its SubIFDs that hold the full-resolution raw image."""
    first = tif.pages.first
    for page in (first, *(first.pages or ())):
        subfile = page.tags.get(254)
        main = subfile is None or int(subfile.value) == 0
        if main and int(page.photometric) in RAW_PHOTOMETRIC:
            yield page


def _blocks(d: _Ifd) -> list[tuple[int, int]]:
    """(width, rows) of every strip or tile, in order (per plane when planar)."""
    planes = d.samples if d.planar == 2 else 1
    if d.tile is not None:
        tw, tl = d.tile
        n = math.ceil(d.width / tw) * math.ceil(d.length / tl)
        return [(tw, tl)] * n * planes
    rps = min(d.rows_per_strip, d.length)
    rows = [min(rps, d.length - k) for k in range(0, d.length, rps)]
    return [(d.width, r) for r in rows] * planes


def _check_sizes(d: _Ifd, size: int) -> None:
    """Dimensions, bit depths, the number of strips or tiles and where they lie."""
    if d.width < 1 or d.length < 1:
        raise DngHeaderError("ImageWidth/ImageLength", f"is {d.width} x {d.length}")
    if any(not 1 <= b <= 32 for b in d.bits):
        raise DngHeaderError("BitsPerSample", f"is {list(d.bits)}; raw data have 1 to 32 bits")
    if d.tile is not None and (d.tile[0] < 1 or d.tile[1] < 1):
        raise DngHeaderError("TileWidth/TileLength", f"is {d.tile[0]} x {d.tile[1]}")
    where = "TileByteCounts" if d.tile is not None else "StripByteCounts"
    expected = len(_blocks(d))
    if len(d.counts) != expected or len(d.offsets) != expected:
        raise DngHeaderError(
            where,
            f"lists {len(d.counts)} blocks, but ImageWidth {d.width} x ImageLength {d.length} "
            f"need {expected}",
        )
    for offset, count in zip(d.offsets, d.counts, strict=True):
        if offset + count > size:
            raise DngHeaderError(where, f"points past the end of the file ({size} bytes)")


def _check_uncompressed(d: _Ifd) -> None:
    """Every strip or tile holds exactly its rows of samples at BitsPerSample."""
    samples = 1 if d.planar == 2 else d.samples
    bits = max(d.bits)
    for k, ((width, rows), count) in enumerate(zip(_blocks(d), d.counts, strict=True)):
        need = rows * math.ceil(width * samples * bits / 8)
        if count != need:
            kind = "tile" if d.tile is not None else "strip"
            raise DngHeaderError(
                "ImageWidth" if d.tile is None else "TileWidth",
                f"= {width} does not match the data: {kind} {k} holds {count} bytes, {rows} rows "
                f"of {width} x {samples} samples at {bits} bits need {need}",
            )


def _jpeg_frame(block: bytes) -> tuple[int, int, int, int] | None:
    """(precision, height, width, components) of a JPEG stream's frame header, or None."""
    if not block.startswith(b"\xff\xd8"):
        return None
    i = 2
    while i + 4 <= len(block):
        if block[i] != 0xFF:
            return None
        marker = block[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        (length,) = struct.unpack_from(">H", block, i + 2)
        if marker in _SOF and i + 10 <= len(block):
            return struct.unpack_from(">BHHB", block, i + 4)
        i += 2 + length
    return None


def _check_jpeg(d: _Ifd, blob: bytes) -> None:
    """Each strip or tile is a JPEG stream whose frame holds its samples at BitsPerSample."""
    samples = 1 if d.planar == 2 else d.samples
    for k, ((width, rows), offset, count) in enumerate(
        zip(_blocks(d), d.offsets, d.counts, strict=True)
    ):
        frame = _jpeg_frame(blob[offset : offset + min(count, 1 << 16)])
        if frame is None:
            raise DngHeaderError(
                "Compression",
                f"= {d.compression} ({DNG_COMPRESSION[d.compression]}), but block {k} is not a "
                "JPEG stream",
            )
        precision, height, jwidth, components = frame
        if height * jwidth * components != rows * width * samples or precision != max(d.bits):
            raise DngHeaderError(
                "ImageWidth" if d.tile is None else "TileWidth",
                f"= {width} does not match the data: block {k} is a {jwidth} x {height} JPEG of "
                f"{components} components at {precision} bits, not {width} x {rows} x {samples} "
                f"samples at {max(d.bits)} bits",
            )


def _check_deflate(d: _Ifd, blob: bytes) -> None:
    """Each strip or tile starts with a zlib header."""
    for k, offset in enumerate(d.offsets):
        head = blob[offset : offset + 2]
        if len(head) < 2 or head[0] & 0x0F != 8 or (head[0] << 8 | head[1]) % 31:
            raise DngHeaderError(
                "Compression", f"= 8 (deflate), but block {k} is not a zlib stream"
            )


def _check_levels(d: _Ifd) -> None:
    """WhiteLevel within (0, 2^bits - 1], BlackLevel below it."""
    top = 2 ** max(d.bits) - 1
    white = d.white if d.white is not None else (float(top),)
    if any(not (0 < w <= top) for w in white):
        raise DngHeaderError(
            "WhiteLevel", f"= {_show(white)} is outside 1 to {top} (the {max(d.bits)}-bit range)"
        )
    if d.black is not None and any(not (0 <= b < min(white)) for b in d.black):
        raise DngHeaderError(
            "BlackLevel", f"= {_show(d.black)} is not below WhiteLevel {_show(white)} (or < 0)"
        )


def _show(values: Sequence[float]) -> str:
    text = ", ".join(f"{v:g}" for v in values[:4]) + (", ..." if len(values) > 4 else "")
    return text if len(values) == 1 else f"[{text}]"


def check_dng(blob: bytes) -> None:
    """Refuse a DNG whose raw image's header contradicts its data (`DngHeaderError`).

    Files that are not TIFF-based DNGs, or that tifffile cannot parse, are left to LibRaw.
    """
    if blob[:4] not in (b"II*\x00", b"MM\x00*"):
        return
    try:
        with tifffile.TiffFile(io.BytesIO(blob)) as tif:
            if 50706 not in tif.pages.first.tags:  # DNGVersion
                return
            ifds = [_ifd(page) for page in _raw_pages(tif)]
    except Exception:  # tifffile cannot read the structure: LibRaw decides
        return
    for d in ifds:
        if d.compression not in DNG_COMPRESSION:
            raise DngHeaderError(
                "Compression",
                f"= {d.compression} is not a DNG compression (allowed: "
                + ", ".join(f"{k} {v}" for k, v in DNG_COMPRESSION.items())
                + ")",
            )
        _check_sizes(d, len(blob))
        if d.compression == 1:
            _check_uncompressed(d)
        elif d.compression in _JPEG:
            _check_jpeg(d, blob)
        elif d.compression == 8:
            _check_deflate(d, blob)
        _check_levels(d)
