"""The 3-D viewer of a completed job's asset: the WebGL2 page of neumatex_core/viewer (docs/viewer.md) and its bundle,
served under a token so that a new browser tab (which sends no API key) can open it.

- `POST /v1/jobs/{id}/viewer-token` (API key or dashboard session) builds the asset's web bundle once (into the job's
  storage, `<asset>/viewer/`, removed with the asset) and returns `{"url": "/v1/jobs/{id}/viewer-token/<token>/
  index.html", "token", "expires_at"}`; the dashboard's job page opens that url in a new tab.
- `GET /v1/jobs/{id}/viewer-token/{token}/{path}`: the page (index.html, viewer.js) and its bundle (bundle.json,
  mesh.bin, material.bin, basis.bin, env/mapN.bin). The page fetches its files by relative URLs, so they all resolve
  under the same token.

The token is a `PathTokens("viewer-token")` (services/path_tokens.py, shared with the report links):
`base64url(job id, tenant id, expiry) . HMAC-SHA256` with its own key derived from the service's secret, valid for
`report_token_ttl_s`; nothing is stored.
Any failure (forged, garbled, for another job, expired, another tenant's job, a file that is not the viewer's) is a
404 that says nothing more. The page's maps are the shared CC0 maps ($NEUMATEX_SHARED/data/envmaps) when the service
has them, else a built-in sky.

Every response carries a Content-Security-Policy for exactly what the viewer does: its own script (no inline
script, no eval), WebGL (which needs no directive), same-origin fetches of its bundle, its inline style; nothing else,
framed by this origin only. Content types are fixed per file with `nosniff`.
"""

from __future__ import annotations

import os
import shutil
import threading
import uuid
from datetime import UTC, datetime
from pathlib import Path, PurePosixPath

from fastapi import APIRouter
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field
from starlette.responses import Response

from services import crud
from services.errors import ApiError, not_found
from services.path_tokens import PathTokens
from services.routes.assets import _asset_key, file_response, stored_file
from services.routes.deps import SessionDep, TenantDep
from services.storage import NotStored, get_storage

router = APIRouter(tags=["viewer"])

CSP = ("default-src 'none'; script-src 'self'; connect-src 'self'; style-src 'unsafe-inline'; img-src 'self' data:; "
       "base-uri 'none'; form-action 'none'; frame-ancestors 'self'")  # fmt: skip
HEADERS = {"Content-Security-Policy": CSP, "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer",
           "Cross-Origin-Resource-Policy": "same-origin", "Cache-Control": "private, max-age=300"}  # fmt: skip
STATIC = {"index.html": "text/html; charset=utf-8", "viewer.js": "text/javascript; charset=utf-8"}
DATA_TYPES = {".json": "application/json", ".bin": "application/octet-stream"}
ENV_HEIGHT = 128  # the service's maps: 256 x 128 texels each (0.6 MB), fetched only when chosen
_build_lock = threading.Lock()


class ViewerToken(BaseModel):
    token: str = Field(description="opens this job's viewer page and its data only, until expires_at")
    url: str = Field(description="the viewer page under the token (a path on this API)")
    expires_at: datetime


# -- tokens ------------------------------------------------------------------------------------------------------
TOKENS = PathTokens("viewer-token")


def mint(job_id: str, tenant_id: str, ttl_s: float | None = None, at: float | None = None) -> tuple[str, int]:
    """A token for the job's viewer and its expiry (unix seconds)."""
    return TOKENS.mint(job_id, tenant_id, ttl_s, at)


def check(token: str, job_id: str) -> str | None:
    """The tenant id the token was minted for, or None when it is malformed, forged, for another job or expired."""
    return TOKENS.verify(token, job_id)[0]


# -- the bundle --------------------------------------------------------------------------------------------------
def _shared_envmaps() -> Path | None:
    shared = os.environ.get("NEUMATEX_SHARED")
    folder = Path(shared) / "data" / "envmaps" if shared else None
    return folder if folder is not None and folder.is_dir() else None


def ensure_bundle(asset_key: str) -> str:
    """The storage key of the asset's viewer bundle, built now if it is not there yet: in a local workspace, then
    committed with its bundle.json last (the marker this function looks for: a rename on local storage)."""
    from neumatex_core.assets import read_asset
    from neumatex_core.viewer.web_bundle import BUNDLE, shared_envmaps, sky_envmap, write_bundle

    storage = get_storage()
    key = f"{asset_key}/viewer"
    with _build_lock:
        if storage.is_file(f"{key}/{BUNDLE}"):
            return key
        folder = _shared_envmaps()
        maps = shared_envmaps(folder) if folder is not None else []
        maps = maps or [sky_envmap()]
        default = "studio" if any(m.name == "studio" for m in maps) else maps[0].name
        tmp = storage.workspace(f"{asset_key}/.viewer-{uuid.uuid4().hex}")
        try:
            with storage.local_tree(f"{asset_key}/asset") as asset_dir:
                asset = read_asset(asset_dir)
                write_bundle(asset, tmp / "viewer", maps, default, ENV_HEIGHT, static=False)
            storage.commit_tree(tmp / "viewer", key, last=(BUNDLE,), replace=True)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return key


def _viewer_file(asset_key: str, file_path: str) -> Response:
    from neumatex_core.viewer.web_bundle import STATIC_DIR

    file_path = file_path or "index.html"
    if file_path in STATIC:
        return FileResponse(STATIC_DIR / file_path, media_type=STATIC[file_path], headers=HEADERS)
    storage = get_storage()
    media = DATA_TYPES.get(PurePosixPath(file_path).suffix.lower())
    key = stored_file(storage, f"{asset_key}/viewer", file_path) if media is not None else None
    if key is None:
        raise not_found("viewer file", file_path)
    try:
        return file_response(storage, key, media, HEADERS)
    except NotStored:
        raise not_found("viewer file", file_path) from None


@router.post("/jobs/{job_id}/viewer-token", response_model=ViewerToken,
             summary="A short-lived link to the 3-D viewer of a completed job's asset (opens in a new tab)")
def viewer_token(job_id: str, s: SessionDep, tenant: TenantDep) -> ViewerToken:
    asset_key = _asset_key(s, tenant.id, job_id)  # 404 for another tenant's job, 409/410 when there is no asset
    try:
        ensure_bundle(asset_key)
    except (ValueError, OSError) as exc:  # AssetError, BasisError, EnvmapError are ValueErrors
        raise ApiError(409, f"the asset of job {job_id} cannot be shown in the viewer: {exc}") from None
    token, expires = mint(job_id, tenant.id)
    return ViewerToken(token=token, url=f"/v1/jobs/{job_id}/viewer-token/{token}/index.html",
                       expires_at=datetime.fromtimestamp(expires, UTC))  # fmt: skip


@router.get("/jobs/{job_id}/viewer-token/{token}/{file_path:path}", response_class=FileResponse,
            summary="The viewer page and its data, through a token from POST .../viewer-token")
def viewer_file(job_id: str, token: str, file_path: str, s: SessionDep) -> Response:
    tenant_id = check(token, job_id)
    job = crud.job_of_tenant(s, tenant_id, job_id) if tenant_id is not None else None
    if job is None or job.state != "completed" or not job.asset_key:
        raise not_found("viewer", job_id)
    return _viewer_file(job.asset_key, file_path)
