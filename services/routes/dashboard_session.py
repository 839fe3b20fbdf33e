"""The dashboard's login: an API key exchanged once (`POST /v1/session`) for a signed session cookie, so the page
never keeps the key in script-readable storage or in a URL.

The cookie `nmx_session` is `base64url(tenant id, API key row id, expiry) . HMAC-SHA256` with a key derived from
the service's secret (like the report tokens): nothing is stored server-side. It is `HttpOnly` (no script reads it),
`SameSite=Strict` (no other site's page or link sends it), `Path=/`, `Secure` when the service is served over https
(`session_cookie_secure`, default: `public_url` is https), and it expires after `session_ttl_s`. Each request checks
that the API key it was made from still exists unrevoked and belongs to the tenant, so revoking the key ends its
sessions at once; logging out (`DELETE /v1/session`) removes the cookie from the browser.

CSRF: a cookie-authenticated request that changes something (any method but GET, HEAD and OPTIONS) must also carry
the header `X-NeuMatEx-CSRF: 1`, which a form of another site cannot send and a script of another site could only
send after a CORS preflight this API does not grant; and when the browser says where the request came from
(`Origin`, `Sec-Fetch-Site`) it must be this service. Programs sending `Authorization: Bearer` or `X-API-Key` are
not affected (a browser never adds those headers by itself).
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import time
from urllib.parse import urlsplit

from fastapi import Request, Response
from sqlalchemy import select
from sqlalchemy.orm import Session

from services.core.config import get_settings
from services.core.security import hash_api_key
from services.errors import ApiError
from services.models import ApiKey, Tenant

COOKIE = "nmx_session"
CSRF_HEADER = "X-NeuMatEx-CSRF"
SAFE_METHODS = ("GET", "HEAD", "OPTIONS")


def _key() -> bytes:
    from services.webhooks import service_secret

    return hmac.new(service_secret(), b"dashboard-session", hashlib.sha256).digest()


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


def mint(tenant_id: str, key_id: int, ttl_s: float | None = None, at: float | None = None) -> tuple[str, int]:
    """A session value for the tenant's API key row and its expiry (unix seconds)."""
    ttl = get_settings().session_ttl_s if ttl_s is None else ttl_s
    expires = int((time.time() if at is None else at) + ttl)
    payload = f"{tenant_id}\n{key_id}\n{expires}".encode()
    return f"{_b64(payload)}.{_b64(hmac.new(_key(), payload, hashlib.sha256).digest())}", expires


def read(value: str) -> tuple[str, int]:
    """(tenant id, API key row id) of a session value; 401 when it is malformed, forged or expired."""
    bad = ApiError(401, "your dashboard session is not valid; log in again with your API key",
                   headers={"WWW-Authenticate": "Bearer"})  # fmt: skip
    body, _, sig = value.partition(".")
    try:
        payload, given = _unb64(body), _unb64(sig)
        if not hmac.compare_digest(hmac.new(_key(), payload, hashlib.sha256).digest(), given):
            raise bad
        tenant_id, key_id, expires = payload.decode().split("\n")
        key_row, until = int(key_id), int(expires)
    except (binascii.Error, ValueError, UnicodeDecodeError):
        raise bad from None
    if time.time() > until:
        raise ApiError(401, "your dashboard session expired; log in again with your API key",
                       headers={"WWW-Authenticate": "Bearer"})  # fmt: skip
    return tenant_id, key_row


def key_row(s: Session, key: str) -> ApiKey | None:
    """The unrevoked API key row of `key`."""
    return s.scalar(select(ApiKey).where(ApiKey.key_hash == hash_api_key(key), ApiKey.revoked.is_(False)))


def _same_origin(request: Request, origin: str) -> bool:
    parts = urlsplit(origin)
    public = urlsplit(get_settings().public_url)
    host = request.headers.get("host", "")
    return (parts.netloc == host and parts.scheme in ("http", "https")) or \
        (parts.scheme, parts.netloc) == (public.scheme, public.netloc)  # fmt: skip


def check_csrf(request: Request) -> None:
    """403 unless a state-changing cookie-authenticated request comes from this service's own page."""
    if request.method in SAFE_METHODS:
        return
    site = request.headers.get("sec-fetch-site")
    if site is not None and site not in ("same-origin", "none"):
        raise ApiError(403, f"refused a {site} request made with the dashboard's session cookie")
    origin = request.headers.get("origin")
    if origin is not None and not _same_origin(request, origin):
        raise ApiError(403, f"refused a request from another origin ({origin[:100]}) made with the dashboard's "
                       "session cookie")
    if request.headers.get(CSRF_HEADER) != "1":
        raise ApiError(403, f"a request made with the dashboard's session cookie needs the header '{CSRF_HEADER}: 1' "
                       "(programs: send 'Authorization: Bearer <key>' instead)")


def tenant_of(s: Session, request: Request, value: str) -> Tenant:
    """The tenant of a session cookie (401 when it is not valid or its API key was revoked), CSRF checked."""
    tenant_id, key_id = read(value)
    row = s.get(ApiKey, key_id)
    tenant = s.get(Tenant, tenant_id) if row is not None and not row.revoked and row.tenant_id == tenant_id else None
    if tenant is None:
        raise ApiError(401, "the API key of this dashboard session was revoked; log in again",
                       headers={"WWW-Authenticate": "Bearer"})  # fmt: skip
    check_csrf(request)
    return tenant


def set_cookie(response: Response, value: str) -> None:
    st = get_settings()
    secure = st.session_cookie_secure
    if secure is None:
        secure = st.public_url.lower().startswith("https:")
    response.set_cookie(COOKIE, value, max_age=int(st.session_ttl_s), path="/", httponly=True, samesite="strict",
                        secure=secure)  # fmt: skip


def clear_cookie(response: Response) -> None:
    response.delete_cookie(COOKIE, path="/", httponly=True, samesite="strict")
