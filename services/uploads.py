"""Capture uploads: a zip streamed as the request body, a multi-file form, or a NodeODM-style session
(init, files in one or more requests, commit). Everything lands in staging/<upload_id>/ first; a capture is
created only after the whole capture passed `neumatex_core.capture` validation, by one rename into
captures/<capture_id>/. Any failure removes the staging folder, so nothing half-written remains.

Limits: the request body (max_upload_bytes, checked against Content-Length first and again on the bytes that
arrive) and the file count -> 413; the unpacked size, zip-slip, symlinks, zip bombs -> 422 (the checks of
`neumatex_core.capture.extract_zip`); file types outside allowed_suffixes -> 415.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path, PurePosixPath

import anyio
from starlette.datastructures import UploadFile
from starlette.requests import Request

from neumatex_core.capture import CaptureError, extract_zip, validate_capture
from neumatex_core.capture.archive import safe_member_path
from neumatex_core.capture.loader import find_capture_root
from services.core.config import Settings
from services.errors import ApiError
from services.storage import LocalStorage

CHUNK = 1 << 20


def staging_key(upload_id: str) -> str:
    return f"staging/{upload_id}"


def too_large(limit: int) -> ApiError:
    return ApiError(413, f"upload larger than the limit of {limit} bytes ({limit / 1024**2:.1f} MiB)")


def check_content_length(request: Request, limit: int) -> None:
    length = request.headers.get("content-length")
    if length is not None and length.isdigit() and int(length) > limit:
        raise too_large(limit)


async def stream_to_file(chunks: AsyncIterator[bytes], target: Path, limit: int) -> int:
    """Write the body to `target`; 413 as soon as more than `limit` bytes arrived (the partial file is removed)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    written = 0
    try:
        with open(target, "wb") as out:
            async for chunk in chunks:
                written += len(chunk)
                if written > limit:
                    raise too_large(limit)
                out.write(chunk)
    except BaseException:
        target.unlink(missing_ok=True)
        raise
    return written


def problems_of(exc: CaptureError) -> list[dict[str, str]]:
    return [{"file": p.file, "message": p.message} for p in exc.problems]


def check_suffixes(files: list[str], settings: Settings) -> None:
    bad = [f for f in files if PurePosixPath(f).suffix.lower() not in settings.allowed_suffixes
           and not PurePosixPath(f).name.startswith("._") and "__MACOSX" not in f]  # fmt: skip
    if bad:
        allowed = ", ".join(settings.allowed_suffixes)
        raise ApiError(415, f"{len(bad)} file(s) of a type a capture does not hold (allowed: {allowed})",
                       [{"file": f, "message": "file type not allowed"} for f in bad[:50]])


def unpack_zip(zip_path: Path, dest: Path, settings: Settings) -> None:
    """Safe extraction (zip-slip, links, bombs, limits: neumatex_core.capture.extract_zip); the zip is removed."""
    try:
        extract_zip(zip_path, dest, settings.max_capture_bytes, settings.max_files, settings.max_zip_ratio)
    except CaptureError as exc:
        raise ApiError(422, f"the zip {zip_path.name} cannot be unpacked safely", problems_of(exc)) from None
    finally:
        zip_path.unlink(missing_ok=True)


async def save_form_files(form_files: list[UploadFile], dest: Path, settings: Settings,
                          budget: int) -> tuple[int, int]:
    """Copy the form's files under `dest` at their (relative) file names; returns (files, bytes)."""
    names: list[tuple[UploadFile, PurePosixPath]] = []
    bad: list[dict[str, str]] = []
    for f in form_files:
        name = f.filename or ""
        rel = safe_member_path(name) if name else None
        if rel is None or str(rel) == ".":
            bad.append({"file": name, "message": "file name is empty, absolute or escapes the capture folder"})
        else:
            names.append((f, rel))
    if bad:
        raise ApiError(422, "bad file names in the upload", bad)
    check_suffixes([str(r) for _, r in names], settings)
    total = 0
    for f, rel in names:
        target = dest / rel
        if target.exists():
            raise ApiError(409, f"file {str(rel)!r} was uploaded twice")
        target.parent.mkdir(parents=True, exist_ok=True)
        with open(target, "wb") as out:
            while chunk := await f.read(CHUNK):
                total += len(chunk)
                if total > budget:
                    raise too_large(settings.max_upload_bytes)
                out.write(chunk)
    return len(names), total


def count_files(folder: Path) -> tuple[int, int]:
    files = [p for p in folder.rglob("*") if p.is_file()]
    return len(files), sum(p.stat().st_size for p in files)


async def validate_folder(folder: Path, settings: Settings) -> tuple[Path, int]:
    """The capture root inside `folder` and its frame count; 422 with every problem when it is not usable."""
    rel_files = [p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()]
    if len(rel_files) > settings.max_files:
        raise ApiError(413, f"the capture holds {len(rel_files)} files; at most {settings.max_files} are allowed")
    check_suffixes(rel_files, settings)
    try:
        root = find_capture_root(folder, "the upload")
    except CaptureError as exc:
        raise ApiError(422, "the upload is not a capture", problems_of(exc)) from None
    problems = await anyio.to_thread.run_sync(validate_capture, root)
    if problems:
        raise ApiError(422, f"{len(problems)} problem(s) with the capture",
                       [{"file": p.file, "message": p.message} for p in problems])
    import json

    frames = len(json.loads((root / "transforms.json").read_text()).get("frames", []))
    return root, frames


def commit_folder(storage: LocalStorage, root: Path, capture_id: str) -> str:
    """Move a validated capture root into captures/<capture_id> (one rename); returns its key."""
    key = f"captures/{capture_id}"
    rel = root.relative_to(storage.root).as_posix()
    storage.move(rel, key)
    return key
