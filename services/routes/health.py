"""GET /healthz (the process answers), GET /readyz (database, broker and storage reachable; 503 naming what is
not), GET /metrics (Prometheus)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from fastapi.responses import JSONResponse, PlainTextResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import text

from services.core.config import get_settings
from services.core.db import session_scope
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
    return JSONResponse({"status": "ready" if ok else "not ready", "checks": checks}, status_code=200 if ok else 503)


def _db() -> None:
    with session_scope() as s:
        s.execute(text("SELECT 1"))


@router.get("/metrics", response_class=PlainTextResponse)
def metrics() -> PlainTextResponse:
    return PlainTextResponse(generate_latest(REGISTRY).decode(), media_type=CONTENT_TYPE_LATEST)
