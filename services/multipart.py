"""A multipart/form-data body streamed straight into a folder: each file part is written at its (checked) file
name as its bytes arrive, counted against the byte budget, the file count and the free space, so an oversized or
endless body is cut at the limit with nothing spooled to TMPDIR. Non-file fields are ignored (bounded too)."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from pathlib import Path, PurePosixPath
from typing import IO

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header

from neumatex_core.capture.archive import name_problem, safe_member_path
from neumatex_core.capture.archive import shown_name as shown
from services.errors import ApiError

MAX_FIELD_BYTES = 64 * 1024  # a non-file field (ignored) or a part's headers


class _FormWriter:
    """python-multipart callbacks: open a file per part, write its data, close it; raises ApiError on a limit."""

    def __init__(self, dest: Path, budget: int, max_files: int, on_bytes: Callable[[int], None]):
        self.dest, self.budget, self.max_files, self.on_bytes = dest, budget, max_files, on_bytes
        self.files: list[str] = []
        self.total = 0
        self._field, self._value = b"", b""
        self._headers: dict[bytes, bytes] = {}
        self._out: IO[bytes] | None = None
        self._other = 0

    # header parsing
    def on_part_begin(self) -> None:
        self._headers = {}

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._field += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._value += data[start:end]
        if len(self._value) > MAX_FIELD_BYTES:
            raise ApiError(400, "a multipart header is too long")

    def on_header_end(self) -> None:
        self._headers[self._field.lower()] = self._value
        self._field, self._value = b"", b""

    def on_headers_finished(self) -> None:
        _, options = parse_options_header(self._headers.get(b"content-disposition", b""))
        raw = options.get(b"filename")
        if raw is None:
            self._out = None  # a plain field: ignored
            return
        name = raw.decode("utf-8", "surrogateescape")
        rel = checked_name(name)
        if len(self.files) >= self.max_files:
            raise ApiError(413, f"too many files in one request; at most {self.max_files} are allowed")
        target = self.dest / rel
        clash = next((p for p in [target, *target.parents] if p != self.dest and p.is_relative_to(self.dest)
                      and p.is_file()), None)  # fmt: skip
        if clash == target:
            raise ApiError(409, f"the file {shown(name)} was uploaded twice",
                           [{"file": shown(name), "message": "uploaded twice"}])  # fmt: skip
        if clash is not None or target.is_dir():
            other = (clash or target).relative_to(self.dest).as_posix()
            raise ApiError(422, f"the uploaded file {shown(name)} clashes with {shown(other)}: a name cannot be "
                           "both a file and a folder", [{"file": shown(name), "message": "both a file and a folder"}])
        target.parent.mkdir(parents=True, exist_ok=True)
        self._out = open(target, "xb")
        self.files.append(rel.as_posix())

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        n = end - start
        if self._out is None:
            self._other += n
            if self._other > MAX_FIELD_BYTES:
                raise ApiError(413, f"a form field that is not a file holds more than {MAX_FIELD_BYTES} bytes")
            return
        self.total += n
        if self.total > self.budget:
            raise too_large(self.budget)
        self.on_bytes(n)
        self._out.write(data[start:end])

    def on_part_end(self) -> None:
        self.close()

    def close(self) -> None:
        if self._out is not None:
            self._out.close()
            self._out = None


def checked_name(name: str) -> PurePosixPath:
    """An uploaded file's path inside the capture; 422 naming it when it is unusable (neumatex_core's rules)."""
    reason = name_problem(name)
    if reason is not None:
        raise ApiError(422, f"the uploaded file {shown(name)} {reason}", [{"file": shown(name), "message": reason}])
    rel = safe_member_path(name)
    assert rel is not None
    return rel


def too_large(limit: int) -> ApiError:
    # Connection: close, so the server stops reading (uvicorn would otherwise drain an endless body)
    return ApiError(413, f"upload larger than the limit of {limit} bytes ({limit / 1024**2:.1f} MiB)",
                    headers={"Connection": "close"})


async def save_multipart(content_type: str, body: AsyncIterator[bytes], dest: Path, budget: int, max_files: int,
                         on_bytes: Callable[[int], None]) -> tuple[list[str], int]:
    """Write the files of the form `body` (a multipart/form-data `content_type` header) under `dest` as they
    arrive; returns (their relative names, bytes).

    `on_bytes(n)` is called before n more bytes are written (the caller's free-space check). Raises ApiError:
    413 over `budget` bytes or `max_files` files, 422 a bad file name or a name both file and folder, 409 a
    file twice, 400 a malformed body. The caller removes `dest` on error.
    """
    _, params = parse_options_header(content_type)
    boundary = params.get(b"boundary")
    if not boundary:
        raise ApiError(400, "the multipart form has no boundary in its Content-Type header")
    dest.mkdir(parents=True, exist_ok=True)
    writer = _FormWriter(dest, budget, max_files, on_bytes)
    callbacks = {k: getattr(writer, k) for k in ("on_part_begin", "on_header_field", "on_header_value",
                                                  "on_header_end", "on_headers_finished", "on_part_data",
                                                  "on_part_end")}  # fmt: skip
    parser = MultipartParser(boundary, callbacks)  # type: ignore[arg-type]
    try:
        async for chunk in body:
            parser.write(chunk)
        parser.finalize()
    except MultipartParseError as exc:
        raise ApiError(400, f"could not read the multipart form ({exc})") from None
    finally:
        writer.close()
    if not writer.files:
        raise ApiError(422, "the form holds no files (send the capture's files as 'files' parts named by their "
                       "path inside the capture, or a zip as the request body)")
    return writer.files, writer.total
