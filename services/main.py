"""The FastAPI app: /v1 routes, health, metrics, dashboard; errors as {"error", "problems"} bodies."""

from __future__ import annotations

import logging
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.core.config import get_settings
from services.core.db import get_engine, session_scope
from services.fastpath import FastStatus
from services.metrics import LATENCY, REQUESTS
from services.routes import assets, captures, dashboard, health, jobs, reports, tenants, viewer

log = logging.getLogger("neumatex.api")


class Measure:
    """Pure ASGI middleware (cheaper than @app.middleware): request counts and latency per route template, and a
    plain-words 500 for anything unhandled."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        status = [500]
        started = [False]

        async def send_wrapper(message: Message) -> None:
            if message["type"] == "http.response.start":
                status[0], started[0] = message["status"], True
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        except Exception:
            log.exception("unhandled error in %s %s", scope["method"], scope["path"])
            if not started[0]:
                await JSONResponse({"error": "internal error; the request was not completed"},
                                   status_code=500)(scope, receive, send)  # fmt: skip
        name = getattr(scope.get("route"), "path", "unmatched")  # the route's template; routers under /v1 omit it
        if scope["path"].startswith("/v1/") and not name.startswith("/v1"):
            name = "/v1" + name
        REQUESTS.labels(scope["method"], name, str(status[0])).inc()
        LATENCY.labels(name).observe(time.perf_counter() - t0)


def _message(error: Any) -> str:
    """pydantic's message, in plainer words for an unknown field, with the value given when it is a scalar."""
    if error.get("type") == "extra_forbidden":
        return "unknown field (the API has no field of this name here)"
    value = error.get("input")
    shown = f", got {value!r}"[:80] if isinstance(value, int | float | str | bool) or value == [] else ""
    return str(error.get("msg", "")) + shown


def create_app(reaper: bool = True) -> FastAPI:
    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        st = get_settings()
        get_engine()
        from services.shutdown import watch_signals

        watch_signals()  # progress streams end on SIGTERM, so the API stops at once
        if st.bootstrap_tenant and st.bootstrap_api_key:
            from services.crud import ensure_tenant

            with session_scope() as s:
                ensure_tenant(s, st.bootstrap_tenant, st.bootstrap_api_key)
        threads: list[Any] = []
        if reaper:
            from services.webhooks import WebhookSender

            threads = [WebhookSender()]
            for thread in threads:
                thread.start()
        yield
        for thread in threads:
            thread.stopped.set()

    app = FastAPI(title="NeuMatEx job service", version="1", lifespan=lifespan,
                  description="Upload captures, run extraction jobs, stream progress, download neural material "
                  "assets. Authenticate with 'Authorization: Bearer <API key>'.")  # fmt: skip
    for r in (captures.router, jobs.router, assets.router, reports.router, tenants.router, viewer.router):
        app.include_router(r, prefix="/v1")
    app.include_router(health.router)
    app.include_router(dashboard.router)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail: object = exc.detail  # Starlette types it str; FastAPI's HTTPException, which the routes raise, a dict
        body = detail if isinstance(detail, dict) else {"error": str(detail)}
        return JSONResponse(body, status_code=exc.status_code, headers=getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def bad_request(_: Request, exc: RequestValidationError) -> JSONResponse:
        problems = [{"file": ".".join(str(x) for x in e.get("loc", ())), "message": _message(e)}
                    for e in exc.errors()]  # fmt: skip
        first = f": {problems[0]['file']}: {problems[0]['message']}" if problems else ""
        return JSONResponse({"error": f"the request does not match the API{first}", "problems": problems},
                            status_code=422)  # fmt: skip

    app.add_middleware(FastStatus)  # GET /v1/jobs/{id} from in-process caches (services/fastpath.py)
    app.add_middleware(Measure)  # added last: the outermost, so it counts the fast path's requests too

    return app


app = create_app()
