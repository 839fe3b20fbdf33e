"""Dependencies: the database session and the caller's tenant from its API key (Authorization: Bearer KEY or
X-API-Key: KEY), or, with neither header, from the dashboard's session cookie (services/routes/dashboard_session.py:
signed, HttpOnly, SameSite=Strict; state-changing requests need its CSRF header and a same-origin Origin). A
missing or unknown key is 401."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Header, Query, Request
from sqlalchemy.orm import Session

from services import crud
from services.core.db import get_session
from services.errors import ApiError
from services.models import Tenant
from services.routes import dashboard_session

SessionDep = Annotated[Session, Depends(get_session)]
MAX_OFFSET = 2**31 - 1  # a page offset beyond this is a 422 (the database's integers end at 2**63)
Offset = Annotated[int, Query(ge=0, le=MAX_OFFSET, description="rows to skip")]


def current_tenant(request: Request, s: SessionDep, authorization: Annotated[str | None, Header()] = None,
                   x_api_key: Annotated[str | None, Header()] = None) -> Tenant:
    cookie = request.cookies.get(dashboard_session.COOKIE)
    if authorization is None and x_api_key is None and cookie:
        return dashboard_session.tenant_of(s, request, cookie)
    key = x_api_key
    if key is None and authorization:
        scheme, _, value = authorization.partition(" ")
        key = value.strip() if scheme.lower() == "bearer" else None
    challenge = {"WWW-Authenticate": "Bearer"}
    if not key:
        raise ApiError(401, "missing API key: send 'Authorization: Bearer <key>' or 'X-API-Key: <key>'",
                       headers=challenge)
    tenant = crud.tenant_for_key(s, key)
    if tenant is None:
        raise ApiError(401, "unknown or revoked API key", headers=challenge)
    return tenant


TenantDep = Annotated[Tenant, Depends(current_tenant)]
