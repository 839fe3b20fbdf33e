"""Safe extraction of an uploaded capture zip, and the rules for the file names of any upload.

Before writing anything, every member is checked and every problem is reported at once: file names that are
unusable (`name_problem`: absolute, `..` escaping the folder (zip-slip), NUL or control characters, a part
longer than 255 bytes), a name that is both a file and a folder, symlinks, encrypted members, too many files,
a declared total size over the limit, members compressed more than `max_ratio` to 1 and a whole archive
compressed more than that (zip bombs made of many small members). While extracting, every byte written is
counted against the member's declared size and the total limit, because declared sizes can lie. Nothing is
written outside `dest`, existing files are never overwritten, and on any failure (a full disk included)
everything this call wrote is removed.
"""

from __future__ import annotations

import errno
import io
import mmap
import os
import stat
import struct
import zipfile
import zlib
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import IO

from neumatex_core.capture.model import CaptureError, Problem

DEFAULT_MAX_TOTAL_BYTES = 2 * 1024**3  # 2 GiB uncompressed
DEFAULT_MAX_FILES = 10_000
DEFAULT_MAX_RATIO = 200.0
RATIO_CHECK_MIN_BYTES = 1024**2  # small members may compress well (a blank mask); bombs are large
MAX_NAME_PART_BYTES = 255  # NAME_MAX of common file systems
MAX_NAME_BYTES = 1024
_CHUNK = 1024**2
_LOCAL_HEADER = struct.Struct("<4s5H3L2H")  # signature, versions, flags, method, time, date, crc, sizes, name/extra
_LOCAL_SIGNATURE = b"PK\x03\x04"


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


def name_problem(name: str) -> str | None:
    """Why `name` cannot be a file's path inside a capture (None when it can), in plain words."""
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        return "has a NUL or control character in its name"
    if len(name.encode("utf-8", "surrogateescape")) > MAX_NAME_BYTES:
        return f"has a name longer than {MAX_NAME_BYTES} bytes"
    rel = safe_member_path(name)
    if rel is None:
        return "has an absolute path or '..' that escapes the folder (zip-slip)"
    if str(rel) == ".":
        return "has an empty name"
    if any(len(part.encode("utf-8", "surrogateescape")) > MAX_NAME_PART_BYTES for part in rel.parts):
        return f"has a folder or file name longer than {MAX_NAME_PART_BYTES} bytes"
    return None


def path_clashes(files: list[str], folders: Sequence[str] = ()) -> list[str]:
    """The file names (each without a `name_problem`) that another name uses as a folder, e.g. `x.png` and
    `x.png/y.png`, or that appear twice."""
    paths = [safe_member_path(f) or PurePosixPath(".") for f in files]
    parents = {p for f in paths for p in f.parents} | {safe_member_path(d) or PurePosixPath(".") for d in folders}
    seen: set[PurePosixPath] = set()
    out = []
    for name, p in zip(files, paths, strict=True):
        if p in parents or p in seen:
            out.append(name)
        seen.add(p)
    return out


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
    packed = sum(i.compress_size for i in files)
    if total >= RATIO_CHECK_MIN_BYTES and total / max(packed, 1) > max_ratio:
        problems.append(
            Problem(
                label,
                f"expands {total / max(packed, 1):.0f}x ({packed} -> {total} bytes),"
                f" more than the allowed {max_ratio:.0f}x (zip bomb?)",
            )
        )
    bad_names: dict[str, str] = {}
    for info in infos:
        reason = name_problem(info.filename)
        if reason is not None and not (info.is_dir() and safe_member_path(info.filename) == PurePosixPath(".")):
            bad_names[info.filename] = reason
            problems.append(Problem(label, f"member {shown_name(info.filename)} {reason}"))
    good = [i.filename for i in files if i.filename not in bad_names]
    dirs = [i.filename for i in infos if i.is_dir() and i.filename not in bad_names]
    for name in path_clashes(good, dirs):
        problems.append(Problem(label, f"member {shown_name(name)} is both a file and a folder, or appears twice"))
    for info in infos:
        name = shown_name(info.filename)
        if _is_symlink(info):
            problems.append(Problem(label, f"member {name} is a symbolic link; links are not allowed"))
        if info.flag_bits & 0x1:
            problems.append(Problem(label, f"member {name} is encrypted"))
        if info.file_size >= RATIO_CHECK_MIN_BYTES:
            ratio = info.file_size / max(info.compress_size, 1)
            if ratio > max_ratio:
                problems.append(
                    Problem(
                        label,
                        f"member {name} expands {ratio:.0f}x"
                        f" ({info.compress_size} -> {info.file_size} bytes),"
                        f" more than the allowed {max_ratio:.0f}x (zip bomb?)",
                    )
                )
    return problems


def shown_name(name: str, limit: int = 80) -> str:
    """A file name for a message: quoted, control characters escaped, a long name shortened."""
    text = repr(name)
    return text if len(text) <= limit else f"{text[: limit // 2]}...{text[-limit // 2 :]} ({len(name)} characters)"


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
    label: str | None = None,
) -> Path:
    """Extract `zip_path` into the folder `dest` (created if needed) and return dest.

    Raises CaptureError with one Problem per reason (each naming the zip, as `label` or by its file name, and
    the member) when the archive is unsafe, unreadable or over a limit; in that case nothing that this call
    wrote is left behind. A full disk is an OSError (ENOSPC), raised after the same clean-up.
    """
    zip_path, dest = Path(zip_path), Path(dest)
    label = label or zip_path.name
    try:
        archive = zipfile.ZipFile(zip_path)
    except FileNotFoundError:
        raise CaptureError([Problem(label, "archive not found")]) from None
    except (zipfile.BadZipFile, OSError) as exc:
        reason = str(exc).replace(str(zip_path), label)
        raise CaptureError([Problem(label, f"is not a readable zip archive ({reason})")]) from None
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
    with _stored_copier(archive, label) as stored:
        for info in infos:
            total = _extract_member(archive, info, root, label, max_total_bytes, total, created, stored)
        if stored is not None:
            stored.check_crcs()


def _extract_member(
    archive: zipfile.ZipFile,
    info: zipfile.ZipInfo,
    root: Path,
    label: str,
    max_total_bytes: int,
    total: int,
    created: list[Path],
    stored: _StoredCopier | None,
) -> int:
    """Extract one checked member under `root`; returns the bytes written so far (`total` plus this member's)."""
    rel = safe_member_path(info.filename)
    assert rel is not None  # checked before extraction
    target = root / rel
    if target.resolve() != target or not target.is_relative_to(root):
        # a folder that already exists in dest links elsewhere
        raise CaptureError(
            [Problem(label, f"member {shown_name(info.filename)} would be written outside the folder")]
        )
    if info.is_dir():
        _mkdirs(target, created)
        return total
    try:
        _mkdirs(target.parent, created)
    except (FileExistsError, NotADirectoryError):
        raise CaptureError(
            [Problem(label, f"member {shown_name(info.filename)} is inside a folder that is a file")]
        ) from None
    # The member's budget: its declared size (which passed the ratio check) and what is left of the total
    # (declared sizes can lie; zipfile itself also stops at the declared size and checks the CRC).
    allowed = min(max_total_bytes - total, info.file_size)
    try:
        fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
    except FileExistsError:
        raise CaptureError(
            [Problem(label, f"member {shown_name(info.filename)} would overwrite an existing file")]
        ) from None
    created.append(target)
    try:
        if info.compress_type == zipfile.ZIP_STORED and stored is not None:
            with os.fdopen(fd, "wb") as out:
                total += stored.copy(info, out.fileno(), allowed)
        else:
            with os.fdopen(fd, "wb") as out, archive.open(info) as src:
                total += copy_limited(src, out, allowed)
    except _LimitExceeded:
        raise CaptureError(
            [Problem(label, f"member {shown_name(info.filename)} unpacks to more bytes than allowed or declared")]
        ) from None
    except OSError as exc:
        if exc.errno == errno.ENOSPC:
            raise  # the server's problem (storage full), not the upload's
        raise CaptureError(
            [Problem(label, f"member {shown_name(info.filename)} cannot be extracted ({exc.strerror})")]
        ) from None
    # zipfile raises NotImplementedError for a compression method it lacks (e.g. deflate64), RuntimeError for
    # an encrypted member: both are the upload's problem, reported like a corrupt member
    except (zipfile.BadZipFile, NotImplementedError, RuntimeError, EOFError) as exc:
        raise CaptureError(
            [Problem(label, f"member {shown_name(info.filename)} cannot be extracted ({exc})")]
        ) from None
    return total


class _StoredCopier:
    """Stored (uncompressed) members copied by the kernel (os.copy_file_range: no bytes pass through Python)
    straight from the archive's file, their CRC-32s checked on a second thread meanwhile (zlib releases the GIL),
    so a large capture unpacks at the speed of the page cache. What zipfile checks is checked here too: the local
    header (signature, method, the name equal to the central directory's) and that a member's data ends before
    the next member or the central directory begins (overlapping members are a zip bomb the sizes do not show)."""

    def __init__(self, archive: zipfile.ZipFile, fd: int, label: str):
        self.fd, self.size, self.label = fd, os.fstat(fd).st_size, label
        self.view = mmap.mmap(fd, self.size, access=mmap.ACCESS_READ) if self.size else None
        starts = sorted({i.header_offset for i in archive.infolist()} | {archive.start_dir, self.size})
        self.end_of = {a: b for a, b in zip(starts, starts[1:], strict=False)}  # header offset -> next one
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="zip-crc")
        self.crcs: list[tuple[zipfile.ZipInfo, memoryview, Future[int]]] = []

    def _problem(self, info: zipfile.ZipInfo, what: str) -> CaptureError:
        return CaptureError([Problem(self.label, f"member {shown_name(info.filename)} {what}")])

    def _data_range(self, info: zipfile.ZipInfo) -> tuple[int, int]:
        """[start, end) of the member's bytes in the archive."""
        at = info.header_offset
        head = self.view[at : at + _LOCAL_HEADER.size] if self.view is not None else b""
        if len(head) != _LOCAL_HEADER.size:
            raise self._problem(info, "cannot be extracted (its local header is past the end of the archive)")
        sig, _, flags, method, _, _, _, _, _, name_len, extra_len = _LOCAL_HEADER.unpack(head)
        assert self.view is not None
        raw_name = bytes(self.view[at + _LOCAL_HEADER.size : at + _LOCAL_HEADER.size + name_len])
        name = raw_name.decode("utf-8" if flags & 0x800 else "cp437", "replace")
        if sig != _LOCAL_SIGNATURE or method != zipfile.ZIP_STORED or name != info.orig_filename:
            raise self._problem(info, "cannot be extracted (its local header does not match the central directory)")
        start = at + _LOCAL_HEADER.size + name_len + extra_len
        end = start + info.file_size
        if end > self.end_of.get(at, self.size):
            raise self._problem(info, "overlaps the next member or runs past the archive's end (zip bomb?)")
        return start, end

    def copy(self, info: zipfile.ZipInfo, out_fd: int, allowed: int) -> int:
        """Write the stored member to `out_fd`; returns its size. _LimitExceeded over `allowed` bytes."""
        if info.compress_size != info.file_size:
            raise self._problem(info, "cannot be extracted (it is stored but declares two different sizes)")
        if info.file_size > allowed:
            raise _LimitExceeded
        start, end = self._data_range(info)
        pos = start
        while pos < end:
            try:
                n = os.copy_file_range(self.fd, out_fd, end - pos, pos)
            except OSError as exc:  # no copy_file_range here (EXDEV, ENOSYS, ...): copy through memory
                if exc.errno not in (errno.EXDEV, errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP):
                    raise
                assert self.view is not None
                n = os.write(out_fd, self.view[pos : min(end, pos + _CHUNK)])
            if n <= 0:
                raise self._problem(info, "cannot be extracted (the archive ends inside it)")
            pos += n
        if self.view is None or start == end:
            if info.CRC != 0:
                raise self._problem(info, "is corrupt (CRC-32 mismatch)")
        else:
            data = memoryview(self.view)[start:end]
            self.crcs.append((info, data, self.pool.submit(zlib.crc32, data)))
        return info.file_size

    def check_crcs(self) -> None:
        """CaptureError naming every member whose bytes do not match its CRC-32 (waits for the checks)."""
        bad = [info for info, _, crc in self.crcs if crc.result() != info.CRC]
        if bad:
            raise CaptureError([Problem(self.label, f"member {shown_name(i.filename)} is corrupt (CRC-32 mismatch)")
                                for i in bad])  # fmt: skip

    def close(self) -> None:
        for _, _, crc in self.crcs:
            crc.cancel()
        self.pool.shutdown(wait=True)
        for _, data, _ in self.crcs:
            data.release()
        self.crcs.clear()
        if self.view is not None:
            self.view.close()


@contextmanager
def _stored_copier(archive: zipfile.ZipFile, label: str) -> Iterator[_StoredCopier | None]:
    """A _StoredCopier for an archive read from a regular file (None otherwise: zipfile copies every member)."""
    try:
        fd = archive.fp.fileno() if archive.fp is not None else -1
        regular = fd >= 0 and stat.S_ISREG(os.fstat(fd).st_mode)
    except (OSError, AttributeError, ValueError, io.UnsupportedOperation):
        regular = False
    if not regular:
        yield None
        return
    copier = _StoredCopier(archive, fd, label)
    try:
        yield copier
    finally:
        copier.close()


def _remove(created: list[Path]) -> None:
    for path in reversed(created):
        try:
            if path.is_dir() and not path.is_symlink():
                path.rmdir()
            else:
                path.unlink()
        except OSError:
            pass
