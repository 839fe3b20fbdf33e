"""`Client`: the job service's API in typed calls (docs/service.md).

    with Client("http://127.0.0.1:8000", api_key) as c:
        cap = c.upload_capture("examples/teapot")          # folder: init/upload/commit in chunks; .zip: streamed
        job = c.create_job(cap.id, preset="tiny", config={"init": "random"})
        job = c.wait(job.id, on_event=print)               # follows the SSE stream (reconnects, else polls)
        c.download_asset(job.id, "teapot-asset.zip")

Every request is retried with exponential backoff on connection errors and on 429, 502, 503 and 504 (at least
the server's Retry-After, capped at `max_backoff_s`); job creation always carries an idempotency key, so a retried
POST never makes a second job. Refusals raise `ApiError` subclasses carrying the server's `error` sentence.
"""

from __future__ import annotations

import fnmatch
import functools
import json
import os
import random
import threading
import time
import uuid
import zipfile
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx

from neumatex_client.errors import BY_STATUS, ApiError, Conflict, NeuMatExError, ServiceUnreachable, WaitTimeout
from neumatex_client.models import (
    AssetManifest,
    Capture,
    Deleted,
    Job,
    JobPage,
    Quota,
    Upload,
    WebhookSecret,
)

DEFAULT_URL = "http://127.0.0.1:8000"
RETRY_STATUS = (429, 502, 503, 504)
CHUNK_FILES = 50  # files per upload request: the server names up to 50 already-uploaded files in a 409
READ_BYTES = 1 << 20


@dataclass
class Event:
    """One server-sent event of a job's progress stream (`data` holds its JSON fields)."""

    event: str
    id: int | None = None
    data: dict[str, Any] = field(default_factory=dict)


def _capture_files(folder: Path, exclude: Iterable[str]) -> list[tuple[str, Path]]:
    patterns = list(exclude)
    out = []
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder).as_posix()
        if not p.is_file() or any(part.startswith(".") for part in rel.split("/")):
            continue
        if any(fnmatch.fnmatch(rel, pat) or fnmatch.fnmatch(rel.split("/")[0], pat) for pat in patterns):
            continue
        out.append((rel, p))
    return out



class _Progress:
    """Bytes sent so far, added to from several threads; `report(sent, total)` after each addition."""

    def __init__(self, total: int, report: Callable[[int, int], None] | None):
        self.total, self.report, self.sent = total, report, 0
        self._lock = threading.Lock()

    def add(self, n: int) -> None:
        with self._lock:
            self.sent += n
            if self.report:
                self.report(self.sent, self.total)


def _file_body(src: Path, on_block: Callable[[int], None]) -> dict[str, Any]:
    """A request's content: the file streamed (a fresh stream for each try)."""
    return {"content": _file_stream(src, on_block)}


def _file_stream(src: Path, on_block: Callable[[int], None]) -> Iterator[bytes]:
    """The file's bytes in READ_BYTES blocks, `on_block(its size)` after each."""
    with open(src, "rb") as f:
        while block := f.read(READ_BYTES):
            on_block(len(block))
            yield block


class Client:
    """The NeuMatEx job service at `url` with one tenant's `api_key` (default: $NEUMATEX_API_KEY)."""

    def __init__(self, url: str | None = None, api_key: str | None = None, *, timeout: float = 120.0,
                 retries: int = 6, backoff_s: float = 0.5, max_backoff_s: float = 30.0,
                 transport: httpx.BaseTransport | None = None):  # fmt: skip
        self.url = (url or os.environ.get("NEUMATEX_URL") or DEFAULT_URL).rstrip("/")
        key = api_key if api_key is not None else os.environ.get("NEUMATEX_API_KEY", "")
        if not key:
            raise NeuMatExError("no API key: pass api_key or set NEUMATEX_API_KEY (`neumatex serve` prints one)")
        self.retries, self.backoff_s, self.max_backoff_s = retries, backoff_s, max_backoff_s
        self.sleep: Callable[[float], None] = time.sleep
        self._http = httpx.Client(base_url=self.url, timeout=httpx.Timeout(timeout, connect=10.0),
                                  headers={"Authorization": f"Bearer {key}", "User-Agent": "neumatex-client/1"},
                                  transport=transport)  # fmt: skip

    # -- plumbing ---------------------------------------------------------------------------------------------
    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def delay(self, attempt: int, retry_after: str | None = None) -> float:
        """Seconds before retry number `attempt + 1`: backoff_s * 2^attempt with jitter, at least Retry-After."""
        d = self.backoff_s * 2**attempt * (0.8 + 0.4 * random.random())
        if retry_after:
            try:
                d = max(d, float(retry_after))
            except ValueError:
                pass
        return float(min(d, self.max_backoff_s))

    @staticmethod
    def error_of(r: httpx.Response, method: str, path: str) -> ApiError:
        try:
            body = r.json()
            error, problems = str(body.get("error") or body), body.get("problems") or []
        except (ValueError, AttributeError):
            error, problems = (r.text.strip()[:300] or r.reason_phrase), []
        return BY_STATUS.get(r.status_code, ApiError)(r.status_code, error, problems, method, path)

    def request(self, method: str, path: str, *, body: Callable[[], dict[str, Any]] | None = None,
                **kw: Any) -> httpx.Response:  # fmt: skip
        """One API call with retries; `body()` makes the content/files/json arguments afresh for each try (a
        stream cannot be sent twice). Raises ApiError (>= 400 after retries) or ServiceUnreachable."""
        for attempt in range(self.retries + 1):
            try:
                r = self._http.request(method, path, **kw, **(body() if body else {}))
            except httpx.TransportError as exc:
                if attempt == self.retries:
                    raise ServiceUnreachable(f"{method} {self.url}{path}: {type(exc).__name__}: {exc} "
                                             f"(after {self.retries + 1} tries)") from exc  # fmt: skip
                self.sleep(self.delay(attempt))
                continue
            if r.status_code in RETRY_STATUS and attempt < self.retries:
                self.sleep(self.delay(attempt, r.headers.get("retry-after")))
                continue
            if r.status_code >= 400:
                raise self.error_of(r, method, path)
            return r
        raise AssertionError("unreachable")

    def _json(self, method: str, path: str, **kw: Any) -> Any:
        return self.request(method, path, **kw).json()

    # -- captures ---------------------------------------------------------------------------------------------
    def upload_capture(self, path: str | Path, name: str | None = None, *, chunk_bytes: int = 8 << 20,
                       exclude: Iterable[str] = (), progress: Callable[[int, int], None] | None = None) -> Capture:
        """Upload a capture folder (holding transforms.json) or a capture .zip; returns the validated capture.

        A folder goes through an upload session (POST /v1/uploads, files in requests of at most `chunk_bytes` and
        50 files, each file larger than `chunk_bytes` alone as a raw PUT streamed from disk, commit), each request
        retried on its own: a request whose answer was lost and that the server had stored is recognised by its
        409 naming exactly its files, so the upload goes on from there. A zip is streamed in one request.
        `exclude`: glob patterns of paths (or top-level folders) left out. `progress`
        is called with (bytes sent, total bytes)."""
        src = Path(path)
        if src.name == "transforms.json":
            src = src.parent
        label = name or (src.stem if src.suffix.lower() == ".zip" else src.name)
        if src.is_file() and src.suffix.lower() == ".zip":
            return self._upload_zip(src, label, progress)
        if not (src / "transforms.json").is_file():
            raise NeuMatExError(f"{path} is neither a capture folder (no transforms.json in it) nor a .zip")
        files = _capture_files(src, exclude)
        total = sum(p.stat().st_size for _, p in files)
        up = Upload.model_validate(self._json("POST", "/v1/uploads", json={"name": label}))
        sent = _Progress(total, progress)
        try:
            large = [(rel, p) for rel, p in files if p.stat().st_size > chunk_bytes]
            # the large files on a second connection while the forms go on this one: the server handles a form
            # while its proxy receives a large file
            with ThreadPoolExecutor(1, thread_name_prefix="neumatex-put") as pool:
                puts = pool.submit(self._put_files, up.id, large, sent)
                for chunk in self._chunks([f for f in files if f not in large], chunk_bytes):
                    if puts.done():
                        puts.result()  # a failed PUT stops the upload now
                    self._upload_chunk(up.id, chunk)
                    sent.add(sum(p.stat().st_size for _, p in chunk))
                puts.result()
            return Capture.model_validate(self._json("POST", f"/v1/uploads/{up.id}/commit"))
        except BaseException:
            try:  # the staged files count against the quota: drop them
                self._http.delete(f"/v1/uploads/{up.id}", timeout=10)
            except httpx.HTTPError:
                pass
            raise

    @staticmethod
    def _chunks(files: list[tuple[str, Path]], chunk_bytes: int) -> Iterator[list[tuple[str, Path]]]:
        chunk: list[tuple[str, Path]] = []
        size = 0
        for rel, p in files:
            n = p.stat().st_size
            if chunk and (size + n > chunk_bytes or len(chunk) >= CHUNK_FILES):
                yield chunk
                chunk, size = [], 0
            chunk.append((rel, p))
            size += n
        if chunk:
            yield chunk

    def _upload_chunk(self, upload_id: str, chunk: list[tuple[str, Path]]) -> None:
        data = [(rel, p.read_bytes()) for rel, p in chunk]

        def form() -> dict[str, Any]:
            return {"files": [("files", (rel, blob, "application/octet-stream")) for rel, blob in data]}

        try:
            self.request("POST", f"/v1/uploads/{upload_id}/files", body=form)
        except Conflict as exc:  # stored by an earlier try whose answer was lost: all of it, or it is a real 409
            if {p.get("file") for p in exc.problems} != {rel for rel, _ in chunk}:
                raise

    def _put_files(self, upload_id: str, files: list[tuple[str, Path]], sent: _Progress) -> None:
        """PUT each file as the raw body (streamed from disk); a 409 naming it means an earlier try stored it."""
        for rel, src in files:
            try:
                self.request("PUT", f"/v1/uploads/{upload_id}/files/{quote(rel)}",
                             headers={"Content-Type": "application/octet-stream",
                                      "Content-Length": str(src.stat().st_size)},
                             body=functools.partial(_file_body, src, sent.add))  # fmt: skip
            except Conflict as exc:
                if {p.get("file") for p in exc.problems} != {rel}:
                    raise

    def _upload_zip(self, src: Path, name: str, progress: Callable[[int, int], None] | None) -> Capture:
        total = src.stat().st_size

        def body() -> dict[str, Any]:  # each try counts from 0
            return _file_body(src, _Progress(total, progress).add)

        headers = {"Content-Type": "application/zip", "Content-Length": str(total),
                   "Content-Disposition": f'attachment; filename="{src.name}"'}  # fmt: skip
        return Capture.model_validate(self._json("POST", "/v1/captures", params={"name": name}, headers=headers,
                                                 body=body))  # fmt: skip

    def get_capture(self, capture_id: str) -> Capture:
        return Capture.model_validate(self._json("GET", f"/v1/captures/{capture_id}"))

    def list_captures(self, limit: int = 100, offset: int = 0) -> list[Capture]:
        rows = self._json("GET", "/v1/captures", params={"limit": limit, "offset": offset})
        return [Capture.model_validate(c) for c in rows]

    def delete_capture(self, capture_id: str) -> Deleted:
        return Deleted.model_validate(self._json("DELETE", f"/v1/captures/{capture_id}"))

    # -- jobs -------------------------------------------------------------------------------------------------
    def create_job(self, capture_id: str, preset: str = "cpu", config: dict[str, Any] | None = None,
                   queue: str | None = None, idempotency_key: str | None = None,
                   webhook_url: str | None = None) -> Job:  # fmt: skip
        """POST /v1/jobs. Without an idempotency key one is made up, so a retried request never makes two jobs."""
        body: dict[str, Any] = {"capture_id": capture_id, "preset": preset, "config": config or {},
                                "idempotency_key": idempotency_key or f"client-{uuid.uuid4().hex}"}  # fmt: skip
        if queue:
            body["queue"] = queue
        if webhook_url:
            body["webhook_url"] = webhook_url
        return Job.model_validate(self._json("POST", "/v1/jobs", json=body))

    def get_job(self, job_id: str) -> Job:
        return Job.model_validate(self._json("GET", f"/v1/jobs/{job_id}"))

    def list_jobs(self, state: str | None = None, capture_id: str | None = None, stage: str | None = None,
                  limit: int = 50, offset: int = 0) -> JobPage:  # fmt: skip
        params = {k: v for k, v in {"state": state, "capture_id": capture_id, "stage": stage}.items() if v}
        return JobPage.model_validate(self._json("GET", "/v1/jobs", params={**params, "limit": limit,
                                                                            "offset": offset}))  # fmt: skip

    def iter_jobs(self, **filters: Any) -> Iterator[Job]:
        offset: int | None = 0
        while offset is not None:
            page = self.list_jobs(**filters, offset=offset, limit=200)
            yield from page.items
            offset = page.next_offset

    def cancel(self, job_id: str) -> Job:
        return Job.model_validate(self._json("POST", f"/v1/jobs/{job_id}/cancel"))

    def retry(self, job_id: str, from_stage: str | None = None) -> Job:
        body = {"from_stage": from_stage} if from_stage else {}
        return Job.model_validate(self._json("POST", f"/v1/jobs/{job_id}/retry", json=body))

    def events(self, job_id: str, last_event_id: int | None = None, read_timeout: float = 60.0) -> Iterator[Event]:
        """The job's server-sent events from after `last_event_id`, until the server ends the stream (`end` once
        the job ended, `shutdown` when the API stops). Comments (keep-alives) come as Event("comment")."""
        headers = {"Accept": "text/event-stream"}
        if last_event_id is not None:
            headers["Last-Event-ID"] = str(last_event_id)
        path = f"/v1/jobs/{job_id}/events"
        timeout = httpx.Timeout(read_timeout, connect=10.0)
        with self._http.stream("GET", path, headers=headers, timeout=timeout) as r:
            if r.status_code >= 400:
                r.read()
                raise self.error_of(r, "GET", path)
            kind, ident, data = "message", None, ""
            for line in r.iter_lines():
                if line.startswith(":"):
                    yield Event("comment")
                elif line.startswith("event:"):
                    kind = line[6:].strip()
                elif line.startswith("id:"):
                    ident = int(line[3:].strip())
                elif line.startswith("data:"):
                    data += line[5:].strip()
                elif line == "" and data:
                    yield Event(kind, ident, json.loads(data))
                    kind, ident, data = "message", None, ""

    def wait(self, job_id: str, timeout: float | None = None, on_event: Callable[[Event], None] | None = None,
             stream: bool = True, poll_s: float = 1.0) -> Job:  # fmt: skip
        """Block until the job is completed, failed or canceled; returns it (check `.state`). Follows the progress
        stream, reconnecting with Last-Event-ID when it drops; after repeated stream failures (or `stream=False`)
        polls the job with backoff from `poll_s`. Raises WaitTimeout after `timeout` seconds."""
        deadline = None if timeout is None else time.monotonic() + timeout
        last: int | None = None
        failures = polls = 0

        def check_time() -> None:
            if deadline is not None and time.monotonic() > deadline:
                raise WaitTimeout(f"job {job_id} did not end within {timeout:.0f} s")

        while True:
            check_time()
            if stream and failures < 5:
                try:
                    for ev in self.events(job_id, last):
                        check_time()
                        if ev.id is not None:
                            last = ev.id
                        if ev.event != "comment" and on_event is not None:
                            on_event(ev)
                        if ev.event == "end":
                            return self.get_job(job_id)
                        failures = 0
                except (httpx.TransportError, ValueError):
                    failures += 1  # dropped stream or a garbled line: reconnect (or poll)
            job = self.get_job(job_id)
            if job.done:
                return job
            if stream and failures < 5:
                self.sleep(self.delay(failures))
                continue
            if on_event is not None:
                on_event(Event("poll", None, job.model_dump(mode="json")))
            self.sleep(min(poll_s * 1.5 ** min(polls, 10), self.max_backoff_s))
            polls += 1

    # -- assets, tenant ---------------------------------------------------------------------------------------
    def asset(self, job_id: str) -> AssetManifest:
        return AssetManifest.model_validate(self._json("GET", f"/v1/jobs/{job_id}/asset"))

    def download_asset(self, job_id: str, dest: str | Path) -> Path:
        """The job's asset zip into `dest` (a file, or an existing folder: <job id>.zip in it), written to a
        temporary file first and checked to be a zip; retried from the start when the connection drops."""
        target = Path(dest)
        if target.is_dir():
            target = target / f"{job_id}.zip"
        tmp = target.with_name(f".{target.name}.part")
        path = f"/v1/jobs/{job_id}/asset.zip"
        for attempt in range(self.retries + 1):
            try:
                with self._http.stream("GET", path) as r:
                    if r.status_code in RETRY_STATUS and attempt < self.retries:
                        self.sleep(self.delay(attempt, r.headers.get("retry-after")))
                        continue
                    if r.status_code >= 400:
                        r.read()
                        raise self.error_of(r, "GET", path)
                    with open(tmp, "wb") as f:
                        for block in r.iter_bytes(READ_BYTES):
                            f.write(block)
                break
            except httpx.TransportError as exc:
                if attempt == self.retries:
                    tmp.unlink(missing_ok=True)
                    raise ServiceUnreachable(f"GET {self.url}{path}: {exc}") from exc
                self.sleep(self.delay(attempt))
        if not zipfile.is_zipfile(tmp):
            tmp.unlink(missing_ok=True)
            raise NeuMatExError(f"the asset of job {job_id} downloaded from {self.url} is not a zip")
        os.replace(tmp, target)
        return target

    def quota(self) -> Quota:
        return Quota.model_validate(self._json("GET", "/v1/quota"))

    def me(self) -> dict[str, Any]:
        return dict(self._json("GET", "/v1/me"))

    def webhook_secret(self) -> str:
        """The key this tenant's webhook deliveries are signed with (see `verify_signature`)."""
        return WebhookSecret.model_validate(self._json("GET", "/v1/webhook-secret")).secret
