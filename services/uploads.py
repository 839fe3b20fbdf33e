"""Capture uploads: a zip streamed as the request body, a multi-file form, or a NodeODM-style session
(init, files in one or more requests, commit). The API receives and unpacks every upload in a local folder (the
storage's `workspace`: staging/<upload_id>/ inside the storage folder for local storage, so the commit is one
rename; under the scratch folder for S3); a capture is created only after the whole capture passed
`neumatex_core.capture` validation, by committing that folder to captures/<capture_id>/ (services/storage.py).
A session's files wait between its requests under the storage key staging/<upload_id>/files/. Any failure
removes what the request wrote, so nothing half-written remains.

Limits: the request body (max_upload_bytes, checked against Content-Length first and again on the bytes as they
arrive, form files included: services/multipart.py) and the file count -> 413; the unpacked size, zip-slip,
symlinks, zip bombs, bad file names -> 422 (the checks of `neumatex_core.capture.extract_zip`); file types outside
allowed_suffixes -> 415; free space on the disk of the local folder below min_free_bytes (or the disk full) -> 507.

Speed (docs/service.md, "Storage" and "Uploads through the proxy"): the body is written once as it arrives (no
spooling, no hashing: the zip's own CRCs are checked while unpacking), in large writes; stored members are unpacked
by the kernel (neumatex_core.capture.archive); the unpacked capture is moved into place by one rename. Behind the
reverse proxy (deploy/nginx/) the body never passes through Python: nginx writes it to a file and names it in
BODY_FILE_HEADER (`proxied_body_file`).
"""

from __future__ import annotations

import errno
import hmac
import os
import shutil
import stat
import zipfile
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import contextmanager
from pathlib import Path, PurePosixPath

import anyio
from starlette.requests import Request

from neumatex_core.capture import CaptureError, extract_zip
from neumatex_core.capture.archive import path_clashes, shown_name
from neumatex_core.capture.loader import find_capture_root
from neumatex_core.capture.validate import inspect_capture
from services.core.config import Settings
from services.errors import ApiError
from services.multipart import too_large
from services.storage import Storage, local_files

CHUNK = 1 << 20
WRITE_BYTES = 4 << 20  # the body is written in pieces of about this size
UNNAMED_ZIP = "the uploaded zip"
BODY_FILE_HEADER = "x-neumatex-body-file"  # set by the proxy (deploy/nginx/): the file holding the request body
BODY_TOKEN_HEADER = "x-neumatex-body-token"  # the proxy's secret (Settings.proxy_body_token)


def staging_key(upload_id: str) -> str:
    return f"staging/{upload_id}"


def check_content_length(request: Request, limit: int) -> None:
    length = request.headers.get("content-length")
    if length is not None and length.isdigit() and int(length) > limit:
        raise too_large(limit)


def storage_full(free: int, reserve: int) -> ApiError:
    return ApiError(507, f"the storage is full: {free / 1024**2:.0f} MiB free, {reserve / 1024**2:.0f} MiB must stay "
                    "free; the upload was not kept (try again later or ask the operator to free space)",
                    headers={"Connection": "close"})


def space_guard(root: Path, reserve: int) -> Callable[[int], None]:
    """A check to call before writing n more bytes under `root`: 507 when the free space would drop below
    `reserve` (shutil.disk_usage of the real file system, asked again after every CHUNK bytes)."""
    pending = [0]

    def check(n: int) -> None:
        pending[0] += n
        if pending[0] < CHUNK and n < CHUNK:
            return
        free = shutil.disk_usage(root).free
        if free - pending[0] < reserve:
            raise storage_full(free, reserve)
        pending[0] = 0

    check(CHUNK)  # once before anything is written
    return check


@contextmanager
def disk_full_is_507(root: Path, reserve: int) -> Iterator[None]:
    """A write that failed with ENOSPC (the disk filled despite the reserve) is a 507, not a 500."""
    try:
        yield
    except OSError as exc:
        if exc.errno != errno.ENOSPC:
            raise
        raise storage_full(shutil.disk_usage(root).free, reserve) from None


def proxied_body_file(request: Request, settings: Settings) -> Path | None:
    """The file in which the reverse proxy saved this request's body, or None when the body comes through the API.

    Honoured only with the proxy's secret (Settings.proxy_body_token) and for a regular file inside
    Settings.proxy_body_dir, so a client reaching the API directly cannot make it read another file (400). Checked
    once per request (the routes ask more than once)."""
    name = request.headers.get(BODY_FILE_HEADER, "")
    if not name:
        return None
    checked: Path | None = getattr(request.state, "proxied_body_file", None)
    if checked is not None:
        return checked
    token = request.headers.get(BODY_TOKEN_HEADER, "")
    folder = settings.proxy_body_dir
    if folder is None or not hmac.compare_digest(token.encode(), settings.proxy_body_token.encode()):
        raise ApiError(400, f"the {BODY_FILE_HEADER} header is only accepted from this service's proxy; send the "
                       "upload as the request body")
    path = Path(name)
    try:
        inside = path.is_absolute() and path.resolve().parent == folder.resolve()
        regular = inside and stat.S_ISREG(os.lstat(path).st_mode)
    except OSError:
        regular = False
    if not regular:
        raise ApiError(500, "the proxy named a request body file that is not in its body folder; check that "
                       "NEUMATEX_PROXY_BODY_DIR is the proxy's client_body_temp_path (deploy/nginx/)")
    request.state.proxied_body_file = path
    return path


def adopt_body_file(body_file: Path, target: Path, budget: int) -> int:
    """Make the proxy's body file the file `target` (mode 0644) without copying it where possible: a hard link
    (the proxy removes its own name when the answer is sent), else a copy (another file system). Returns its
    size; 413 over `budget`."""
    size = body_file.stat().st_size
    if size > budget:
        raise too_large(budget)
    try:
        os.link(body_file, target)
    except OSError as exc:
        if exc.errno not in (errno.EXDEV, errno.EPERM, errno.EMLINK, errno.ENOTSUP):
            raise
        shutil.copyfile(body_file, target)
    target.chmod(0o644)
    return size


async def file_chunks(path: Path) -> AsyncIterator[bytes]:
    """A saved body read in CHUNK pieces (for the multipart parser)."""
    with open(path, "rb") as f:
        while chunk := await anyio.to_thread.run_sync(f.read, CHUNK):
            yield chunk


def upload_label(request: Request) -> str:
    """How messages name a zip body: its file name from Content-Disposition, else UNNAMED_ZIP."""
    from python_multipart.multipart import parse_options_header

    _, options = parse_options_header(request.headers.get("content-disposition", ""))
    name = options.get(b"filename", b"").decode("utf-8", "replace")
    return shown_name(PurePosixPath(name.replace("\\", "/")).name) if name else UNNAMED_ZIP


async def stream_to_file(chunks: AsyncIterator[bytes], target: Path, limit: int,
                         on_bytes: Callable[[int], None]) -> int:
    """Write the body to `target`; 413 as soon as more than `limit` bytes arrived (the partial file is removed).
    `on_bytes(n)` is called before n more bytes are written (the free-space check). The server hands over small
    pieces (64 KiB); a WRITE_BYTES buffer turns them into few large writes."""
    target.parent.mkdir(parents=True, exist_ok=True)
    written = 0
    try:
        with open(target, "wb", buffering=WRITE_BYTES) as out:
            async for chunk in chunks:
                written += len(chunk)
                if written > limit:
                    raise too_large(limit)
                on_bytes(len(chunk))
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


def declared_size(zip_path: Path) -> int:
    """The unpacked size a zip declares (0 when it cannot be read: extract_zip then says why)."""
    try:
        with zipfile.ZipFile(zip_path) as z:
            return sum(i.file_size for i in z.infolist())
    except (zipfile.BadZipFile, OSError, ValueError):
        return 0


def unpack_zip(zip_path: Path, dest: Path, settings: Settings, label: str, remove: bool = True) -> None:
    """Safe extraction (zip-slip, links, bombs, names, limits: neumatex_core.capture.extract_zip), named `label`
    in messages; 507 first when the declared size would not leave min_free_bytes free; the zip is removed unless
    `remove` is false (the proxy's body file, which the proxy removes)."""
    try:
        space_guard(dest.parent, settings.min_free_bytes)(min(declared_size(zip_path), settings.max_capture_bytes))
        extract_zip(zip_path, dest, settings.max_capture_bytes, settings.max_files, settings.max_zip_ratio, label)
    except CaptureError as exc:
        first = exc.problems[0].message if len(exc.problems) == 1 else f"{len(exc.problems)} problems"
        raise ApiError(422, f"{label} cannot be unpacked safely: {first}", problems_of(exc)) from None
    finally:
        if remove:
            zip_path.unlink(missing_ok=True)


def merge_clashes(part: Path, old: set[str]) -> tuple[list[str], list[str]]:
    """The files of a session's new part (a local folder) that were uploaded already (`old`: the names stored so
    far), and those whose name clashes with an earlier file or folder as file versus folder (`x.png` then
    `x.png/y.png`, or the reverse)."""
    new = local_files(part)
    twice = sorted(set(new) & old)
    clashing = set(path_clashes(sorted(old) + new)) - set(twice)
    clashes = [n for n in new if n in clashing or any(p.as_posix() in clashing for p in PurePosixPath(n).parents)]
    return twice, clashes


def merge_part(storage: Storage, part: Path, files_key: str) -> None:
    """Add a session's checked part (a local folder, consumed) to its files under `files_key`: a rename per file
    into the storage folder, or an upload per file to S3."""
    files_dir = storage.local_path(files_key)
    if files_dir is None:
        storage.put_tree(part, files_key)
        return
    for rel in local_files(part):
        (files_dir / rel).parent.mkdir(parents=True, exist_ok=True)
        (part / rel).rename(files_dir / rel)


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
        raise ApiError(422, "the upload is not a capture: transforms.json is missing", problems_of(exc)) from None
    report = await anyio.to_thread.run_sync(inspect_capture, root)
    if report.problems:
        n, p = len(report.problems), report.problems[0]
        head = "1 problem with the capture" if n == 1 else f"{n} problems with the capture, the first"
        raise ApiError(422, f"{head}: {p.file}: {p.message}", problems_of(CaptureError(report.problems)))
    return root, report.n_frames


def commit_folder(storage: Storage, root: Path, capture_id: str) -> str:
    """Move a validated capture root (a local folder, consumed) into captures/<capture_id> (one rename, or an
    upload whose marker is the capture's database row, written after); returns its key."""
    key = f"captures/{capture_id}"
    storage.commit_tree(root, key)
    return key
