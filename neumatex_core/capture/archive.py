"""Safe extraction of an uploaded capture zip.

Before writing anything, every member is checked and every problem is reported at once: absolute paths or
`..` escaping the folder (zip-slip), symlinks, encrypted members, too many files, a declared total size over
the limit, and members compressed more than `max_ratio` to 1 (zip bombs). While extracting, the limits are
enforced again on the bytes actually produced, because declared sizes can lie. Nothing is written outside
`dest`, existing files are never overwritten, and on any failure everything this call wrote is removed.
"""

from __future__ import annotations

import os
import stat
import zipfile
from pathlib import Path, PurePosixPath
from typing import IO

from neumatex_core.capture.model import CaptureError, Problem

DEFAULT_MAX_TOTAL_BYTES = 2 * 1024**3  # 2 GiB uncompressed
DEFAULT_MAX_FILES = 10_000
DEFAULT_MAX_RATIO = 200.0
RATIO_CHECK_MIN_BYTES = 1024**2  # small members may compress well (a blank mask); bombs are large
_CHUNK = 1024**2


class _LimitExceeded(Exception):
    pass


def safe_member_path(name: str) -> PurePosixPath | None:
    """The member's path relative to the extraction folder, or None when it is absolute or escapes it."""
    unified = name.replace("\\", "/")
    if unified.startswith("/") or (len(unified) >= 2 and unified[1] == ":"):
        return None
    parts: list[str] = []
    for part in unified.split("/"):
        if part in ("", "."):
            continue
        if part == "..":
            if not parts:
                return None
            parts.pop()
        else:
            parts.append(part)
    return PurePosixPath(*parts) if parts else PurePosixPath(".")


def _is_symlink(info: zipfile.ZipInfo) -> bool:
    return stat.S_ISLNK(info.external_attr >> 16)


def check_members(
    infos: list[zipfile.ZipInfo],
    label: str,
    max_total_bytes: int,
    max_files: int,
    max_ratio: float,
) -> list[Problem]:
    """Every reason the listed members must not be extracted (empty when they may)."""
    problems: list[Problem] = []
    files = [i for i in infos if not i.is_dir()]
    if len(files) > max_files:
        problems.append(Problem(label, f"holds {len(files)} files; at most {max_files} are allowed"))
    total = sum(i.file_size for i in files)
    if total > max_total_bytes:
        problems.append(
            Problem(label, f"unpacks to {total} bytes; at most {max_total_bytes} bytes are allowed")
        )
    for info in infos:
        name = info.filename
        if safe_member_path(name) is None:
            problems.append(
                Problem(
                    label, f"member {name!r} has an absolute path or '..' that escapes the folder (zip-slip)"
                )
            )
        if _is_symlink(info):
            problems.append(Problem(label, f"member {name!r} is a symbolic link; links are not allowed"))
        if info.flag_bits & 0x1:
            problems.append(Problem(label, f"member {name!r} is encrypted"))
        if info.file_size >= RATIO_CHECK_MIN_BYTES:
            ratio = info.file_size / max(info.compress_size, 1)
            if ratio > max_ratio:
                problems.append(
                    Problem(
                        label,
                        f"member {name!r} expands {ratio:.0f}x"
                        f" ({info.compress_size} -> {info.file_size} bytes),"
                        f" more than the allowed {max_ratio:.0f}x (zip bomb?)",
                    )
                )
    return problems


def copy_limited(src: IO[bytes], dst: IO[bytes], max_bytes: int) -> int:
    """Copy src to dst in chunks; raise _LimitExceeded as soon as more than `max_bytes` come out."""
    written = 0
    while True:
        chunk = src.read(_CHUNK)
        if not chunk:
            return written
        written += len(chunk)
        if written > max_bytes:
            raise _LimitExceeded
        dst.write(chunk)


def extract_zip(
    zip_path: str | Path,
    dest: str | Path,
    max_total_bytes: int = DEFAULT_MAX_TOTAL_BYTES,
    max_files: int = DEFAULT_MAX_FILES,
    max_ratio: float = DEFAULT_MAX_RATIO,
) -> Path:
    """Extract `zip_path` into the folder `dest` (created if needed) and return dest.

    Raises CaptureError with one Problem per reason (each naming the zip and the member) when the archive is
    unsafe, unreadable or over a limit; in that case nothing that this call wrote is left behind.
    """
    zip_path, dest = Path(zip_path), Path(dest)
    label = zip_path.name
    try:
        archive = zipfile.ZipFile(zip_path)
    except FileNotFoundError:
        raise CaptureError([Problem(label, "archive not found")]) from None
    except (zipfile.BadZipFile, OSError) as exc:
        raise CaptureError([Problem(label, f"not a readable zip archive ({exc})")]) from None
    with archive:
        infos = archive.infolist()
        problems = check_members(infos, label, max_total_bytes, max_files, max_ratio)
        if problems:
            raise CaptureError(problems)
        created: list[Path] = []  # files and folders this call made, in creation order
        try:
            _extract_members(archive, infos, dest, label, max_total_bytes, created)
        except BaseException:
            _remove(created)
            raise
    return dest


def _mkdirs(path: Path, created: list[Path]) -> None:
    missing: list[Path] = []
    p = path
    while not p.exists():
        missing.append(p)
        p = p.parent
    for d in reversed(missing):
        d.mkdir()
        created.append(d)


def _extract_members(
    archive: zipfile.ZipFile,
    infos: list[zipfile.ZipInfo],
    dest: Path,
    label: str,
    max_total_bytes: int,
    created: list[Path],
) -> None:
    _mkdirs(dest, created)
    root = dest.resolve()
    total = 0
    for info in infos:
        rel = safe_member_path(info.filename)
        assert rel is not None  # checked before extraction
        target = root / rel
        if target.resolve() != target or not target.is_relative_to(root):
            # a folder that already exists in dest links elsewhere
            raise CaptureError(
                [Problem(label, f"member {info.filename!r} would be written outside the folder")]
            )
        if info.is_dir():
            _mkdirs(target, created)
            continue
        _mkdirs(target.parent, created)
        # The member's budget: its declared size (which passed the ratio check) and what is left of the total
        # (declared sizes can lie; zipfile itself also stops at the declared size and checks the CRC).
        allowed = min(max_total_bytes - total, info.file_size)
        try:
            fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
        except FileExistsError:
            raise CaptureError(
                [Problem(label, f"member {info.filename!r} would overwrite an existing file")]
            ) from None
        created.append(target)
        try:
            with os.fdopen(fd, "wb") as out, archive.open(info) as src:
                total += copy_limited(src, out, allowed)
        except _LimitExceeded:
            raise CaptureError(
                [Problem(label, f"member {info.filename!r} unpacks to more bytes than allowed or declared")]
            ) from None
        # zipfile raises NotImplementedError for a compression method it lacks (e.g. deflate64), RuntimeError for
        # an encrypted member: both are the upload's problem, reported like a corrupt member
        except (zipfile.BadZipFile, NotImplementedError, RuntimeError, OSError, EOFError) as exc:
            raise CaptureError(
                [Problem(label, f"member {info.filename!r} cannot be extracted ({exc})")]
            ) from None


def _remove(created: list[Path]) -> None:
    for path in reversed(created):
        try:
            if path.is_dir() and not path.is_symlink():
                path.rmdir()
            else:
                path.unlink()
        except OSError:
            pass
