"""A completed job's extraction report: the very `report/index.html` and PNGs the pipeline wrote into the asset
(neumatex_core/report.py), served file by file so the dashboard's job page can show it in a frame.

Two ways in, both scoped to the job and its tenant (another tenant's job is a 404, like every id):
- `GET /v1/jobs/{id}/report/{path}` with the API key (Authorization or X-API-Key), for programs;
- `GET /v1/jobs/{id}/report-token/{token}/{path}` with a token minted by `POST /v1/jobs/{id}/report-token` (which
  needs the key). A frame or an <img> cannot send an Authorization header, and the report's images are relative
  URLs (`src='curves.png'`), so the token is a path segment: every file the page references resolves under the
  same token: a `PathTokens("report-token")` (services/path_tokens.py), `base64url(job id, tenant id, expiry) .
  HMAC-SHA256` with a key derived from the service's secret: nothing is stored, it opens only that job's report
  files (not the API), and it expires after `REPORT_TOKEN_TTL_S`.

Only files under the asset's `report/` folder are served (`..`, absolute paths, NUL and links out of it are 404).
Every response carries a Content-Security-Policy that lets the page show its own images and inline style and
nothing else: no scripts, no connections, no forms, no plugins, framed only by this origin, and sandboxed
(scripts off even if the policy were ignored; `allow-same-origin` only so the dashboard can count the images the
frame loaded). Content types are fixed per suffix (HTML as UTF-8, PNG, JSON) with `nosniff`.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import PurePosixPath

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

router = APIRouter(tags=["reports"])

CSP = ("default-src 'none'; img-src 'self'; style-src 'unsafe-inline'; base-uri 'none'; form-action 'none'; "
       "frame-ancestors 'self'; sandbox allow-same-origin")  # fmt: skip
HEADERS = {"Content-Security-Policy": CSP, "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer",
           "Cross-Origin-Resource-Policy": "same-origin", "Cache-Control": "private, max-age=300"}  # fmt: skip
TYPES = {".html": "text/html; charset=utf-8", ".htm": "text/html; charset=utf-8", ".png": "image/png",
         ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".json": "application/json", ".css": "text/css; charset=utf-8",
         ".svg": "image/svg+xml", ".txt": "text/plain; charset=utf-8"}  # fmt: skip


class ReportToken(BaseModel):
    token: str = Field(description="opens this job's report files only, until expires_at")
    url: str = Field(description="the report page under the token (a path on this API)")
    expires_at: datetime


# -- tokens ------------------------------------------------------------------------------------------------------
TOKENS = PathTokens("report-token")


def mint(job_id: str, tenant_id: str, ttl_s: float | None = None, at: float | None = None) -> tuple[str, int]:
    """A token for the job's report and its expiry (unix seconds)."""
    return TOKENS.mint(job_id, tenant_id, ttl_s, at)


def check(token: str, job_id: str) -> str:
    """The tenant id the token was minted for; 403 when it is malformed, forged, for another job or expired."""
    tenant_id, problem = TOKENS.verify(token, job_id)
    if problem == "other job":
        raise ApiError(403, f"this report link is for another job, not {job_id}")
    if problem == "expired":
        raise ApiError(403, "this report link expired; open the job page again for a new one")
    if tenant_id is None:
        raise ApiError(403, "this report link is not valid; open the job page again for a new one")
    return tenant_id


# -- files -------------------------------------------------------------------------------------------------------
def _report_file(s: SessionDep, tenant_id: str, job_id: str, file_path: str) -> Response:
    storage = get_storage()
    file_path = file_path or "index.html"
    key = stored_file(storage, _asset_key(s, tenant_id, job_id) + "/asset/report", file_path)
    if key is None:  # also a link out of report/ (local storage: paths are resolved)
        raise not_found("report file", file_path)
    media = TYPES.get(PurePosixPath(key).suffix.lower(), "application/octet-stream")
    try:
        return file_response(storage, key, media, HEADERS)
    except NotStored:
        raise not_found("report file", file_path) from None


@router.post("/jobs/{job_id}/report-token", response_model=ReportToken,
             summary="A short-lived link to a completed job's report (for frames and images, which send no key)")
def report_token(job_id: str, s: SessionDep, tenant: TenantDep) -> ReportToken:
    _asset_key(s, tenant.id, job_id)  # 404 for another tenant's job, 409/410 when there is no asset
    token, expires = mint(job_id, tenant.id)
    return ReportToken(token=token, url=f"/v1/jobs/{job_id}/report-token/{token}/index.html",
                       expires_at=datetime.fromtimestamp(expires, UTC))  # fmt: skip


@router.get("/jobs/{job_id}/report/{file_path:path}", response_class=FileResponse,
            summary="A file of a completed job's report (index.html, its PNGs, history.json)")
def report_file(job_id: str, file_path: str, s: SessionDep, tenant: TenantDep) -> Response:
    return _report_file(s, tenant.id, job_id, file_path)


@router.get("/jobs/{job_id}/report-token/{token}/{file_path:path}", response_class=FileResponse,
            summary="A file of a completed job's report, through a token from POST .../report-token")
def report_file_by_token(job_id: str, token: str, file_path: str, s: SessionDep) -> Response:
    tenant_id = check(token, job_id)
    if crud.job_of_tenant(s, tenant_id, job_id) is None:
        raise not_found("job", job_id)
    return _report_file(s, tenant_id, job_id, file_path)
