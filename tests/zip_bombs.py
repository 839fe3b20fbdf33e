"""Zip bombs for tests, built fast: one member's data deflated once and written `n` times by hand (zip format:
local headers, data, central directory), so a 4,000 x 1 MiB bomb takes milliseconds and a few MB."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path


def bomb_zip(path: Path, n: int, member_bytes: int, declared_bytes: int | None = None, prefix: str = "bomb/") -> Path:
    """`n` members `prefix`NNNN.png of `member_bytes` zero bytes each, deflated. With `declared_bytes`, the central
    directory lies and declares that size instead (a check before extraction then passes; only counting the bytes
    while writing stops it)."""
    comp = zlib.compressobj(9, zlib.DEFLATED, -15)
    packed = comp.compress(b"\0" * member_bytes) + comp.flush()
    crc = zlib.crc32(b"\0" * member_bytes)
    declared = member_bytes if declared_bytes is None else declared_bytes
    local, central = bytearray(), bytearray()
    for i in range(n):
        name = f"{prefix}{i:04d}.png".encode()
        offset = len(local)
        local += struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, 8, 0, 0, crc, len(packed), member_bytes, len(name), 0)
        local += name + packed
        central += struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, 8, 0, 0, crc, len(packed), declared,
                               len(name), 0, 0, 0, 0, 0o644 << 16, offset) + name  # fmt: skip
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, n, n, len(central), len(local), 0)
    path.write_bytes(bytes(local + central + end))
    return path
