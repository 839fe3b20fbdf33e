"""Stored zip members unpacked by the kernel (neumatex_core.capture.archive._StoredCopier): the same files as
zipfile writes, and every check zipfile makes on the way (CRC-32, the local header, overlapping members)."""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import pytest
from zip_bombs import overlapping_stored_zip

from neumatex_core.capture import CaptureError, extract_zip


def _mixed_zip(path: Path) -> dict[str, bytes]:
    files = {"cap/transforms.json": b'{"frames": []}' * 50, "cap/big.bin": os.urandom(3 * 1024**2 + 17),
             "cap/empty.txt": b"", "cap/sub/deflated.txt": b"abc" * 10_000}  # fmt: skip
    with zipfile.ZipFile(path, "w") as z:
        for name, data in files.items():
            method = zipfile.ZIP_DEFLATED if name.endswith("deflated.txt") else zipfile.ZIP_STORED
            z.writestr(zipfile.ZipInfo(name), data, compress_type=method)
    return files


def test_stored_and_deflated_members_unpack_to_the_same_bytes(tmp_path: Path) -> None:
    files = _mixed_zip(tmp_path / "c.zip")
    dest = extract_zip(tmp_path / "c.zip", tmp_path / "out")
    got = {p.relative_to(dest).as_posix(): p.read_bytes() for p in dest.rglob("*") if p.is_file()}
    assert got == files
    assert (dest / "cap" / "big.bin").stat().st_mode & 0o777 == 0o644


def test_a_corrupt_stored_member_is_refused_and_nothing_is_left(tmp_path: Path) -> None:
    _mixed_zip(tmp_path / "c.zip")
    data = bytearray((tmp_path / "c.zip").read_bytes())
    at = data.index(b"cap/big.bin") + len(b"cap/big.bin") + 1000  # inside big.bin's data
    data[at] ^= 0xFF
    (tmp_path / "bad.zip").write_bytes(bytes(data))
    with pytest.raises(CaptureError, match=r"'cap/big.bin' is corrupt \(CRC-32 mismatch\)"):
        extract_zip(tmp_path / "bad.zip", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_overlapping_stored_members_are_refused(tmp_path: Path) -> None:
    path = overlapping_stored_zip(tmp_path / "overlap.zip")
    with pytest.raises(CaptureError, match="'a.txt' overlaps the next member"):
        extract_zip(path, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_local_header_that_disagrees_with_the_central_directory_is_refused(tmp_path: Path) -> None:
    with zipfile.ZipFile(tmp_path / "c.zip", "w") as z:
        z.writestr(zipfile.ZipInfo("cap/a.bin"), b"z" * 5000, compress_type=zipfile.ZIP_STORED)
    data = bytearray((tmp_path / "c.zip").read_bytes())
    data[30:39] = b"cap/b.bin"  # the local header's name (the central directory still says a.bin)
    (tmp_path / "bad.zip").write_bytes(bytes(data))
    with pytest.raises(CaptureError, match="does not match the central directory"):
        extract_zip(tmp_path / "bad.zip", tmp_path / "out")
