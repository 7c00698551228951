"""A PNG's chunks as the PNG specification (ISO/IEC 15948, section 5) lays them out:
read here byte by byte, with each chunk's CRC checked, so that a test asks what a
reader of the file sees rather than whether some bytes occur in it."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_chunks(path: Path) -> list[tuple[str, bytes]]:
    """(type, data) of every chunk in file order; AssertionError on a malformed file."""
    data = Path(path).read_bytes()
    assert data[:8] == SIGNATURE, f"{path}: not a PNG"
    chunks, at = [], 8
    while at < len(data):
        (length,) = struct.unpack(">I", data[at:at + 4])
        kind = data[at + 4:at + 8]
        body = data[at + 8:at + 8 + length]
        (crc,) = struct.unpack(">I", data[at + 8 + length:at + 12 + length])
        assert zlib.crc32(kind + body) == crc, f"{path}: bad CRC in {kind!r}"
        chunks.append((kind.decode("latin-1"), body))
        at += 12 + length
    assert chunks and chunks[0][0] == "IHDR" and chunks[-1][0] == "IEND", f"{path}: order"
    return chunks
