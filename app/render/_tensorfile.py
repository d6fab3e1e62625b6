"""Mitsuba's tensor file (`src/core/tensor.cpp`): named n-dimensional arrays in one binary file,
the container of the RGL measured-material format (`.bsdf`).

Layout (little-endian): the 12 bytes `tensor_file\\0`, the version (1, 0) as two bytes, the
number of fields (uint32); per field its name's length (uint16), the name, the number of
dimensions (uint16), the type code (uint8, Mitsuba's `Struct::Type`), the data's offset in the
file (uint64) and the shape (uint64 each); then each field's data, C order, at an offset aligned
to 8 bytes.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

MAGIC = b"tensor_file\0"
TYPE_CODES: dict[np.dtype, int] = {
    np.dtype(np.uint8): 1, np.dtype(np.int8): 2, np.dtype(np.uint16): 3,
    np.dtype(np.int16): 4, np.dtype(np.uint32): 5, np.dtype(np.int32): 6,
    np.dtype(np.uint64): 7, np.dtype(np.int64): 8, np.dtype(np.float16): 9,
    np.dtype(np.float32): 10, np.dtype(np.float64): 11,
}  # fmt: skip
"""numpy dtype -> Mitsuba's type code (`Struct::Type`, as `tensor.cpp` reads it)."""
ALIGN = 8


def tensor_bytes(fields: dict[str, NDArray | str]) -> bytes:
    """The tensor file holding `fields` (a string becomes a uint8 array of its UTF-8 bytes)."""
    arrays = {
        k: np.frombuffer(v.encode("utf8"), np.uint8) if isinstance(v, str)
        else np.ascontiguousarray(v)
        for k, v in fields.items()
    }  # fmt: skip
    header = bytearray(MAGIC + struct.pack("<BBI", 1, 0, len(arrays)))
    slots = {}
    for name, a in arrays.items():
        if a.dtype not in TYPE_CODES:
            raise ValueError(f"tensor field {name!r}: dtype {a.dtype} has no tensor-file type")
        label = name.encode("utf8")
        header += struct.pack("<H", len(label)) + label
        header += struct.pack("<HB", a.ndim, TYPE_CODES[a.dtype])
        slots[name] = len(header)
        header += struct.pack("<Q", 0) + struct.pack(f"<{a.ndim}Q", *a.shape)
    body = bytearray()
    offsets = {}
    pos = len(header)
    for name, a in arrays.items():
        pad = -(pos + len(body)) % ALIGN
        body += b"\0" * pad
        offsets[name] = pos + len(body)
        body += a.astype(a.dtype.newbyteorder("<"), copy=False).tobytes()
    for name, at in slots.items():
        header[at : at + 8] = struct.pack("<Q", offsets[name])
    return bytes(header + body)


def read_tensor_file(path: str | Path) -> dict[str, NDArray]:
    """The fields of a tensor file (the inverse of `tensor_bytes`); ValueError if it is not
    one."""
    data = Path(path).read_bytes()
    if data[:12] != MAGIC:
        raise ValueError(f"{path}: not a tensor file (no 'tensor_file' header)")
    (n_fields,) = struct.unpack_from("<I", data, 14)
    codes = {v: k for k, v in TYPE_CODES.items()}
    pos, out = 18, {}
    for _ in range(n_fields):
        (length,) = struct.unpack_from("<H", data, pos)
        name = data[pos + 2 : pos + 2 + length].decode("utf8")
        pos += 2 + length
        ndim, code, offset = struct.unpack_from("<HBQ", data, pos)
        pos += 11
        shape = struct.unpack_from(f"<{ndim}Q", data, pos)
        pos += 8 * ndim
        dtype = codes[code].newbyteorder("<")
        count = int(np.prod(shape)) if shape else 1
        out[name] = np.frombuffer(data, dtype, count, offset).reshape(shape).copy()
    return out
