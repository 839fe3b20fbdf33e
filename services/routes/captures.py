"""Capture uploads: POST /v1/captures (a zip body, or a multi-file form whose file names are paths inside the
capture), and the NodeODM-style session POST /v1/uploads, POST /v1/uploads/{id}/files, POST
/v1/uploads/{id}/commit. A capture exists only once validated (see services/uploads.py)."""

from __future__ import annotations

import json
import re
import shutil
import time
from pathlib import Path
from typing import Annotated
from urllib.parse import unquote

import anyio
from fastapi import APIRouter, Header, Query, Request, Response
from sqlalchemy import select

from neumatex_core.capture.archive import shown_name
from services import cleanup, quota, uploads
from services.core.config import get_settings
from services.core.db import session_scope
from services.errors import ApiError, not_found
from services.models import Capture, Upload, new_id
from services.multipart import checked_name, save_multipart
from services.routes.deps import Offset, SessionDep, TenantDep, current_tenant
from services.schemas import CaptureOut, Deleted, UploadInit, UploadOut
from services.storage import get_storage, start_sync

router = APIRouter(tags=["captures"])


async def _receive(request: Request, dest: Path, budget: int) -> tuple[int, int]:
    """Save a zip body (unpacked safely) or form files under the local folder dest; returns (files, bytes
    received). The body arrives through the API as it is sent, or was saved to a file by the proxy
    (uploads.proxied_body_file). The free space of dest's disk is checked as bytes are written (507 when full)."""
    st = get_settings()
    root = dest.parent  # a workspace folder (services/storage.py): it exists
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    body_file = uploads.proxied_body_file(request, st)
    if body_file is not None and body_file.stat().st_size > budget:
        raise uploads.too_large(budget)
    with uploads.disk_full_is_507(root, st.min_free_bytes):
        if ctype == "multipart/form-data":
            guard = uploads.space_guard(root, st.min_free_bytes)
            body = uploads.file_chunks(body_file) if body_file is not None else request.stream()
            names, received = await save_multipart(request.headers.get("content-type", ""), body, dest, budget,
                                                   st.max_files, guard)  # fmt: skip
            uploads.check_suffixes(names, st)
            return len(names), received
        if ctype in ("application/zip", "application/x-zip-compressed", "application/octet-stream"):
            t0 = time.perf_counter()
            if body_file is not None:
                zip_path, received = body_file, body_file.stat().st_size
            else:
                guard = uploads.space_guard(root, st.min_free_bytes)
                zip_path = dest.parent / f".{dest.name}.zip"
                received = await uploads.stream_to_file(request.stream(), zip_path, budget, guard)
            t1 = time.perf_counter()
            await anyio.to_thread.run_sync(uploads.unpack_zip, zip_path, dest, st, uploads.upload_label(request),
                                           body_file is None)  # fmt: skip
            request.state.timing = {"receive": t1 - t0, "unpack": time.perf_counter() - t1}
            return uploads.count_files(dest)[0], received
    raise ApiError(415, f"unsupported content type {ctype or 'none'!r}: send a zip (application/zip) or a "
                   "multipart/form-data form of files")


async def _commit(tenant_id: str, folder: Path, name: str, received: int, staged: bool = False) -> Capture:
    """Validate the local folder, check the quota, commit its capture root to captures/<id> and record it (the
    record is the commit's marker: on S3 it is written after every object)."""
    st, storage = get_settings(), get_storage()
    if storage.local_path("captures") is not None:
        start_sync(folder)  # to disk while it is validated (the commit waits for it)
    root, frames = await uploads.validate_folder(folder, st)
    files, size = uploads.count_files(root)
    with session_scope() as s:  # the staged bytes of this upload count already when it is a session's
        quota.check_storage(s, tenant_id, size - received if staged else size)
    capture_id = new_id("cap")
    try:
        key = await anyio.to_thread.run_sync(uploads.commit_folder, storage, root, capture_id)
        with session_scope() as s:
            cap = Capture(id=capture_id, tenant_id=tenant_id, name=name or root.name, storage_key=key, files=files,
                          bytes=size, frames=frames)  # fmt: skip
            s.add(cap)
        return cap
    except BaseException:
        storage.delete(f"captures/{capture_id}")
        raise


@router.post("/captures", status_code=201, response_model=CaptureOut,
             summary="Upload a capture in one request (zip body or multi-file form)")
async def create_capture(request: Request, response: Response, tenant: TenantDep,
                         name: Annotated[str, Query(max_length=200)] = "") -> Capture:
    st, storage = get_settings(), get_storage()
    uploads.check_content_length(request, st.max_upload_bytes)
    _check_quota(request, tenant.id)
    upload_id = new_id("upl")
    base = storage.workspace(uploads.staging_key(upload_id))
    try:
        _files, received = await _receive(request, base / "files", st.max_upload_bytes)
        t0 = time.perf_counter()
        cap = await _commit(tenant.id, base / "files", name, received)
        timing = {**getattr(request.state, "timing", {}), "validate_commit": time.perf_counter() - t0}
        response.headers["Server-Timing"] = ", ".join(f"{k};dur={1e3 * v:.1f}" for k, v in timing.items())
        return cap
    finally:
        shutil.rmtree(base, ignore_errors=True)


@router.get("/upload-check", include_in_schema=False, status_code=204)
def upload_check(request: Request, s: SessionDep, x_original_uri: Annotated[str, Header()] = "",
                 x_declared_length: Annotated[str, Header()] = "") -> Response:
    """Asked by the proxy (deploy/nginx/, `auth_request`) before it reads an upload's body: 204 when the caller's
    key (or session) is good, the upload session is theirs, the declared size fits the limit and the quota. A
    refusal is a 401 (bad key) or a 403 carrying the real answer in X-Neumatex-Refusal-Status and, as the body
    the proxy sends, X-Neumatex-Refusal: 404, 413 or 507, the same words as the upload route would say."""
    try:
        tenant = current_tenant(request, s, request.headers.get("authorization"), request.headers.get("x-api-key"))
        declared = int(x_declared_length) if x_declared_length.isdigit() else 0
        budget = get_settings().max_upload_bytes
        session = re.match(r"^/v1/uploads/([^/?]+)/files", x_original_uri)
        if session is not None:
            budget -= _upload_of(s, tenant.id, unquote(session.group(1))).bytes
        if declared > budget:
            raise uploads.too_large(budget)
        quota.check_storage(s, tenant.id, declared)
    except ApiError as exc:
        return Response(status_code=401 if exc.status_code == 401 else 403, headers={
            "X-Neumatex-Refusal": json.dumps(exc.detail, ensure_ascii=True),
            "X-Neumatex-Refusal-Status": str(exc.status_code)})  # fmt: skip
    return Response(status_code=204)


@router.get("/captures", response_model=list[CaptureOut])
def list_captures(s: SessionDep, tenant: TenantDep, limit: Annotated[int, Query(ge=1, le=500)] = 100,
                  offset: Offset = 0) -> list[Capture]:
    q = select(Capture).where(Capture.tenant_id == tenant.id).order_by(Capture.created_at.desc())
    return list(s.scalars(q.limit(limit).offset(offset)))


def _check_quota(request: Request, tenant_id: str) -> None:
    """507 before anything is received when the tenant is over its storage quota, or the declared body would not
    fit (the unpacked size is checked again at commit). Behind the proxy the body is already in its file, whose
    size counts."""
    body_file = uploads.proxied_body_file(request, get_settings())
    length = request.headers.get("content-length", "")
    declared = body_file.stat().st_size if body_file is not None else int(length) if length.isdigit() else 0
    with session_scope() as s:
        quota.check_storage(s, tenant_id, declared)


@router.get("/captures/{capture_id}", response_model=CaptureOut)
def get_capture(capture_id: str, s: SessionDep, tenant: TenantDep) -> Capture:
    cap = s.get(Capture, capture_id)
    if cap is None or cap.tenant_id != tenant.id:
        raise not_found("capture", capture_id)
    return cap


@router.delete("/captures/{capture_id}", response_model=Deleted,
               summary="Delete a capture with its finished jobs and their assets (409 while a job of it is active)")
def delete_capture(capture_id: str, s: SessionDep, tenant: TenantDep) -> Deleted:
    cap = s.get(Capture, capture_id)
    if cap is None or cap.tenant_id != tenant.id:
        raise not_found("capture", capture_id)
    jobs, freed = cleanup.delete_capture(s, cap)
    s.commit()
    return Deleted(deleted=f"capture {capture_id}", jobs=jobs, bytes_freed=freed)


# -- NodeODM-style sessions -----------------------------------------------------------------------------------
def _files_key(upload_id: str) -> str:
    return uploads.staging_key(upload_id) + "/files"


@router.post("/uploads", status_code=201, response_model=UploadOut, summary="Start a multi-request upload")
def init_upload(body: UploadInit, s: SessionDep, tenant: TenantDep) -> Upload:
    up = Upload(tenant_id=tenant.id, name=body.name)
    s.add(up)
    s.flush()
    storage = get_storage()
    if storage.local_path(_files_key(up.id)) is not None:  # S3: the files' keys appear with the files
        storage.workspace(_files_key(up.id))
    s.commit()  # before the answer: the client's next request (its files) must find the session
    return up


def _upload_of(s: SessionDep, tenant_id: str, upload_id: str) -> Upload:
    up = s.get(Upload, upload_id)
    if up is None or up.tenant_id != tenant_id:
        raise not_found("upload", upload_id)
    return up


@router.post("/uploads/{upload_id}/files", response_model=UploadOut, summary="Add files (form or zip) to an upload")
async def upload_files(upload_id: str, request: Request, tenant: TenantDep) -> Upload:
    storage = get_storage()
    budget = _session_budget(tenant.id, upload_id, request)
    base = storage.workspace(f"{uploads.staging_key(upload_id)}/{new_id('part')}")  # merged once all arrived
    try:
        files, received = await _receive(request, base / "files", budget)
        return await _add_part(tenant.id, upload_id, base / "files", files, received)
    finally:
        shutil.rmtree(base, ignore_errors=True)


@router.put("/uploads/{upload_id}/files/{path:path}", response_model=UploadOut,
            summary="Add one file, the raw request body, to an upload at `path` inside the capture")
async def put_upload_file(upload_id: str, path: str, request: Request, tenant: TenantDep) -> Upload:
    """The way for large files: no form to parse, and behind the proxy (deploy/nginx/) no copy at all, since the
    proxy's file of the body is hard-linked into place."""
    st, storage = get_settings(), get_storage()
    rel = checked_name(path)
    uploads.check_suffixes([rel.as_posix()], st)
    budget = _session_budget(tenant.id, upload_id, request)
    base = storage.workspace(f"{uploads.staging_key(upload_id)}/{new_id('part')}")
    try:
        target = base / "files" / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        body_file = uploads.proxied_body_file(request, st)
        with uploads.disk_full_is_507(base, st.min_free_bytes):
            if body_file is not None:
                received = await anyio.to_thread.run_sync(uploads.adopt_body_file, body_file, target, budget)
            else:
                guard = uploads.space_guard(base, st.min_free_bytes)
                received = await uploads.stream_to_file(request.stream(), target, budget, guard)
        up = await _add_part(tenant.id, upload_id, base / "files", 1, received)
        files_dir = storage.local_path(_files_key(upload_id))
        if files_dir is not None:  # after the rename, which would wait for the flush (ext4 data=ordered)
            start_sync(files_dir / rel)  # the disk writes it while the client sends the rest (the commit waits)
        return up
    finally:
        shutil.rmtree(base, ignore_errors=True)


def _session_budget(tenant_id: str, upload_id: str, request: Request) -> int:
    """The bytes the session may still take (413 when the request declares more), after the quota check."""
    st = get_settings()
    with session_scope() as s:
        up = _upload_of(s, tenant_id, upload_id)
        budget = st.max_upload_bytes - up.bytes
    uploads.check_content_length(request, budget)
    _check_quota(request, tenant_id)
    return budget


async def _add_part(tenant_id: str, upload_id: str, part: Path, files: int, received: int) -> Upload:
    """Merge a received part (a local folder of `files` files) into the session's files; 413 over the file count,
    409 a file uploaded before, 422 a name both file and folder."""
    st, storage = get_settings(), get_storage()
    files_key = _files_key(upload_id)
    with session_scope() as s:
        held = _upload_of(s, tenant_id, upload_id).files + files
    if held > st.max_files:
        raise ApiError(413, f"the upload would hold {held} files; at most {st.max_files} are allowed")
    twice, clashes = uploads.merge_clashes(part, set(storage.list(files_key)))
    if twice:
        more = f" (and {len(twice) - 1} more)" if len(twice) > 1 else ""
        raise ApiError(409, f"the file {shown_name(twice[0])}{more} was already uploaded",
                       [{"file": c, "message": "already uploaded"} for c in twice[:50]])
    if clashes:
        raise ApiError(422, f"the uploaded file {shown_name(clashes[0])} clashes with an earlier file of the "
                       "upload: a name cannot be both a file and a folder",
                       [{"file": c, "message": "both a file and a folder"} for c in clashes[:50]])
    await anyio.to_thread.run_sync(uploads.merge_part, storage, part, files_key)
    with session_scope() as s:
        up = _upload_of(s, tenant_id, upload_id)
        up.files += files
        up.bytes += received
        return up


@router.post("/uploads/{upload_id}/commit", status_code=201, response_model=CaptureOut,
             summary="Validate the uploaded files and create the capture")
async def commit_upload(upload_id: str, tenant: TenantDep) -> Capture:
    storage = get_storage()
    with session_scope() as s:
        up = _upload_of(s, tenant.id, upload_id)
        name, received = up.name, up.bytes
    files_key = _files_key(upload_id)
    local = storage.local_path(files_key)
    if local is not None:  # in place: the commit renames the capture root out of the session's folder
        local.mkdir(parents=True, exist_ok=True)
        cap = await _commit(tenant.id, local, name, received, staged=True)  # on error the files stay staged
    else:
        base = storage.workspace(f"{uploads.staging_key(upload_id)}/{new_id('commit')}")
        try:
            await anyio.to_thread.run_sync(storage.get_tree, files_key, base / "files")
            cap = await _commit(tenant.id, base / "files", name, received, staged=True)
        finally:
            shutil.rmtree(base, ignore_errors=True)
    storage.delete(uploads.staging_key(upload_id))
    with session_scope() as s:
        up2 = s.get(Upload, upload_id)
        if up2 is not None:
            s.delete(up2)
    return cap


@router.delete("/uploads/{upload_id}", status_code=204, summary="Abandon an upload")
def delete_upload(upload_id: str, s: SessionDep, tenant: TenantDep) -> None:
    up = _upload_of(s, tenant.id, upload_id)
    get_storage().delete(uploads.staging_key(upload_id))
    s.delete(up)
    s.commit()  # before the answer: a request right after it must not find the session
