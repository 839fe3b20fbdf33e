"""Zip bombs for tests, built fast: one member's data deflated once and written `n` times by hand (zip format:
local headers, data, central directory), so a 4,000 x 1 MiB bomb takes milliseconds and a few MB."""

from __future__ import annotations

import os
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


def _stored_entry(name: bytes, data: bytes, offset: int, declared: int | None = None) -> tuple[bytes, bytes]:
    """A stored member's local header + data, and its central directory record (declaring `declared` bytes)."""
    crc, size = zlib.crc32(data), len(data) if declared is None else declared
    local = struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, 0, 0, 0, crc, size, size, len(name), 0) + name + data
    central = struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, 0, 0, 0, crc, size, size, len(name), 0, 0,
                          0, 0, 0o644 << 16, offset) + name  # fmt: skip
    return local, central


def overlapping_stored_zip(path: Path) -> Path:
    """Two stored members where the first declares a size that runs over the second's header and data (the way
    overlapping-member bombs reuse bytes): sizes and ratios look honest, so only the layout gives it away."""
    second_local, _ = _stored_entry(b"b.txt", b"y" * 1000, 0)
    first_local, first_central = _stored_entry(b"a.txt", b"x" * 1000, 0, declared=1000 + len(second_local))
    first_local = first_local[: -1000] + b"x" * 1000  # the header declares the long size; its data is 1000 bytes
    offset2 = len(first_local)
    second_local, second_central = _stored_entry(b"b.txt", b"y" * 1000, offset2)
    local = first_local + second_local
    central = first_central + second_central
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, 2, 2, len(central), len(local), 0)
    path.write_bytes(local + central + end)
    return path


def folder_bytes(folder: Path) -> int:
    """The bytes of the files under `folder` now (files that vanish while it walks count as 0): what a bomb has
    written so far."""
    total = 0
    for dirpath, _, files in os.walk(folder):
        for f in files:
            try:
                total += os.stat(os.path.join(dirpath, f)).st_size
            except FileNotFoundError:
                pass
    return total
