"""GET /: the dashboard (services/routes/dashboard_page.py: one page, vanilla JS, no build step), and its login.

- `POST /v1/session` `{"api_key"}` checks the key and answers with the session cookie (signed, HttpOnly,
  SameSite=Strict, expiring: services/routes/dashboard_session.py); every API route then accepts the cookie in
  place of `Authorization`/`X-API-Key` (services/routes/deps.py), with a CSRF header and an Origin check on
  requests that change something. `DELETE /v1/session` logs out (the cookie is removed).
- The page: the jobs list (state, stage, progress bar, ETA, TTO loss/PSNR, the asset; a state filter and pages of
  20; queued and running jobs on the page follow their progress streams, `/v1/jobs/{id}/events`, live), an upload
  form (a capture zip, or a folder through `webkitdirectory`, with a preset and config overrides) that creates a
  job, and a page per job (`/#job/<id>`): state, stage, progress, the error of a failed job, metrics and timings
  per stage, the TTO's loss and PSNR curves (live from the progress events, then every step from the report's
  history.json), cancel, retry, the asset zip, a 3-D viewer button (`POST /v1/jobs/{id}/viewer-token`, disabled
  with a note when this API has no such route) and the extraction report itself: the pipeline's own
  report/index.html in a sandboxed frame, through a short-lived link from `POST /v1/jobs/{id}/report-token`
  (services/routes/reports.py), so there is one renderer of the report. The job page writes how many of the
  report's images loaded into `#report-status` (`data-loaded`, `data-total`, `data-failed`).

The page's own Content-Security-Policy allows only its script and style files (no inline script), connections and
frames to this origin, and no framing of the dashboard by other sites.
"""

from __future__ import annotations

from datetime import UTC, datetime

from fastapi import APIRouter, Request, Response
from fastapi.responses import HTMLResponse
from pydantic import BaseModel, Field

from services.errors import ApiError
from services.models import Tenant
from services.routes import dashboard_session
from services.routes.dashboard_page import CSS, HTML, JS
from services.routes.deps import SessionDep

router = APIRouter()

PAGE_CSP = ("default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
            "connect-src 'self'; frame-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; "
            "frame-ancestors 'none'")  # fmt: skip
PAGE_HEADERS = {"Content-Security-Policy": PAGE_CSP, "X-Content-Type-Options": "nosniff",
                "Referrer-Policy": "same-origin", "X-Frame-Options": "DENY", "Cache-Control": "no-cache"}  # fmt: skip


@router.get("/", response_class=HTMLResponse, include_in_schema=False)
def dashboard() -> HTMLResponse:
    return HTMLResponse(HTML, headers=PAGE_HEADERS)


@router.get("/dashboard.js", include_in_schema=False)
def dashboard_js() -> Response:
    return Response(JS, media_type="text/javascript; charset=utf-8", headers=PAGE_HEADERS)


@router.get("/dashboard.css", include_in_schema=False)
def dashboard_css() -> Response:
    return Response(CSS, media_type="text/css; charset=utf-8", headers=PAGE_HEADERS)


class SessionLogin(BaseModel):
    api_key: str = Field(min_length=1, max_length=400, description="the tenant's API key, exchanged for a cookie")


class SessionTenant(BaseModel):
    id: str
    name: str


class SessionOut(BaseModel):
    tenant: SessionTenant
    expires_at: datetime


@router.post("/v1/session", tags=["session"], response_model=SessionOut,
                     summary="Log in to the dashboard: the API key for an HttpOnly, SameSite=Strict session cookie")
def login(body: SessionLogin, request: Request, response: Response, s: SessionDep) -> SessionOut:
    dashboard_session.check_csrf(request)
    row = dashboard_session.key_row(s, body.api_key.strip())
    tenant = s.get(Tenant, row.tenant_id) if row is not None else None
    if row is None or tenant is None:
        raise ApiError(401, "unknown or revoked API key")
    value, expires = dashboard_session.mint(tenant.id, row.id)
    dashboard_session.set_cookie(response, value)
    response.headers["Cache-Control"] = "no-store"
    return SessionOut(tenant=SessionTenant(id=tenant.id, name=tenant.name),
                      expires_at=datetime.fromtimestamp(expires, UTC))  # fmt: skip


@router.delete("/v1/session", tags=["session"], status_code=204,
               summary="Log out of the dashboard (the cookie is removed)")
def logout() -> Response:
    response = Response(status_code=204)
    dashboard_session.clear_cookie(response)
    return response

