"""GET /healthz (the process answers), GET /readyz (database, broker and storage reachable; 503 naming what is
not; also the live workers per queue), GET /metrics (Prometheus; counts over every tenant, so it needs
'Authorization: Bearer <metrics_token>' unless metrics_public is set: 403 when neither is configured)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Header
from fastapi.responses import JSONResponse, PlainTextResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import text

from services.core.config import get_settings
from services.core.db import session_scope
from services.core.security import same
from services.errors import ApiError
from services.metrics import REGISTRY
from services.storage import get_storage

router = APIRouter(tags=["health"])


@router.get("/healthz")
def healthz() -> dict[str, str]:
    return {"status": "ok"}


def broker_ping() -> None:
    import redis

    client = redis.Redis.from_url(get_settings().redis_url, socket_timeout=2, socket_connect_timeout=2)
    try:
        client.ping()
    finally:
        client.close()


@router.get("/readyz")
def readyz() -> JSONResponse:
    checks: dict[str, Any] = {}
    storage = get_storage()
    for name, check in (("database", _db), ("broker", broker_ping), ("storage", storage.check_writable)):
        try:
            check()
            checks[name] = "ok"
        except Exception as exc:
            checks[name] = f"unavailable: {exc}"
    ok = all(v == "ok" for v in checks.values())
    body: dict[str, Any] = {"status": "ready" if ok else "not ready", "checks": checks}
    try:
        from services import fleet

        with session_scope() as s:
            body["workers"] = fleet.summary(s)  # live workers per queue (informational: jobs wait for one)
    except Exception as exc:
        body["workers"] = f"unavailable: {exc}"
    return JSONResponse(body, status_code=200 if ok else 503)


def _db() -> None:
    with session_scope() as s:
        s.execute(text("SELECT 1"))


def check_metrics_access(authorization: str | None) -> None:
    st = get_settings()
    if st.metrics_public:
        return
    if not st.metrics_token:
        raise ApiError(403, "/metrics is off: set NEUMATEX_METRICS_TOKEN (and scrape with 'Authorization: Bearer "
                       "<token>') or NEUMATEX_METRICS_PUBLIC=true on a private network")  # fmt: skip
    scheme, _, value = (authorization or "").partition(" ")
    if scheme.lower() != "bearer" or not same(value.strip(), st.metrics_token):
        raise ApiError(401, "/metrics needs 'Authorization: Bearer <metrics token>'",
                       headers={"WWW-Authenticate": "Bearer"})  # fmt: skip


@router.get("/metrics", response_class=PlainTextResponse)
def metrics(authorization: Annotated[str | None, Header()] = None) -> PlainTextResponse:
    check_metrics_access(authorization)
    return PlainTextResponse(generate_latest(REGISTRY).decode(), media_type=CONTENT_TYPE_LATEST)
