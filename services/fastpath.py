"""The status poll without the framework: a pure ASGI middleware that answers GET /v1/jobs/{id} from two small
in-process caches and hands every other request (and anything unusual about this one) to the FastAPI app.

- API keys: SHA-256 of the key -> tenant id, checked against the database at most once per KEY_TTL_S per key and
  process (KEY_TTL_S = crud.KEY_CACHE_S, the routes' own key cache), so a revoked key stops working within it here
  as everywhere (an unknown or revoked key is answered 401 with the route's own body).
- Job bodies: job id -> (tenant id, the JSON bytes the route itself produces: routes/jobs.job_out serialized by
  JobOut like FastAPI's response_model does), loaded at most once per JOB_TTL_S per job and process. An entry is
  dropped (a) when a Redis message arrives on `neumatex:job:<id>` (services/lifecycle.py publishes one after each
  committed job event), (b) when any other /v1 request that may change data (not GET/HEAD) finishes in this
  process, and (c) JOB_TTL_S after its load began, which bounds staleness when messages are missed or a change
  comes without an event (heartbeats, eta_s and `waiting`, which depend on the clock and the live workers). Loads
  run on a thread, one at a time per job or key (single flight).

Another tenant's job is 404 exactly as on the route (handed to it). What goes to the route instead: another method,
path or query string, no key header (the dashboard's cookie), repeated auth headers, a job not found. docs/service.md
(Status path and load) gives the measured figures.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import threading
import time
from collections.abc import Awaitable, Callable
from types import SimpleNamespace
from typing import Any, TypeVar

import anyio
from pydantic import TypeAdapter
from sqlalchemy import select
from starlette.types import ASGIApp, Receive, Scope, Send

from services.core.config import get_settings
from services.core.db import session_scope
from services.core.security import hash_api_key
from services.crud import KEY_CACHE_S as KEY_TTL_S
from services.lifecycle import CHANNEL_PREFIX
from services.models import ApiKey, Job
from services.schemas import JobOut

log = logging.getLogger("neumatex.fastpath")

JOB_TTL_S = 0.5  # a job's body is at most this old (from the start of its load) when no invalidation message came
JOB_PATH = re.compile(r"/v1/jobs/([A-Za-z0-9_-]{1,64})")
ROUTE = SimpleNamespace(path="/v1/jobs/{job_id}")  # the route template services.main.Measure labels metrics with
JOB_JSON = TypeAdapter(JobOut)
UNAUTHORIZED = json.dumps({"error": "unknown or revoked API key"}, separators=(",", ":")).encode()
T = TypeVar("T")


def _api_key(headers: list[tuple[bytes, bytes]]) -> str | None:
    """The API key as services/routes/deps.current_tenant reads it (X-API-Key first, else 'Authorization: Bearer
    KEY'); None when the route should decide (no key header, an empty key, a header given twice)."""
    auth = xkey = None
    for name, value in headers:
        if name == b"authorization":
            if auth is not None:
                return None
            auth = value
        elif name == b"x-api-key":
            if xkey is not None:
                return None
            xkey = value
    if xkey is not None:
        key = xkey.decode("latin-1")
    elif auth:
        scheme, _, rest = auth.decode("latin-1").partition(" ")
        key = rest.strip() if scheme.lower() == "bearer" else ""
    else:
        return None
    return key or None


def _tenant_of_key(digest: str) -> str | None:
    """The tenant id of an unrevoked key (by its SHA-256 hex digest), None when unknown or revoked."""
    with session_scope() as s:
        row = s.scalar(select(ApiKey.tenant_id).where(ApiKey.key_hash == digest, ApiKey.revoked.is_(False)))
        return None if row is None else str(row)


def _job_body(job_id: str) -> tuple[str, bytes] | None:
    """(tenant id, the route's JSON body) of a job, None when there is no such job."""
    from services.routes.jobs import job_out  # the route's own function: the same fields and redaction

    with session_scope() as s:
        job = s.get(Job, job_id)
        if job is None:
            return None
        return job.tenant_id, JOB_JSON.dump_json(job_out(s, job), by_alias=True)


class FastStatus:
    """ASGI middleware: GET /v1/jobs/{id} answered from the caches above, everything else passed to `app`."""

    def __init__(self, app: ASGIApp, key_ttl_s: float = KEY_TTL_S, job_ttl_s: float = JOB_TTL_S,
                 subscribe: bool = True):  # fmt: skip
        self.app = app
        self.key_ttl_s, self.job_ttl_s = key_ttl_s, job_ttl_s
        self.keys: dict[str, tuple[float, str | None]] = {}  # key digest -> (expiry, tenant id or None: refused)
        self.jobs: dict[str, tuple[float, str, bytes]] = {}  # job id -> (expiry, tenant id, body)
        self.generation = 0  # bumped by every invalidation: a load that began before one is served, not stored
        self._inflight: dict[tuple[str, str], asyncio.Future[Any]] = {}  # single flight per (kind, ident)
        self._subscribe = subscribe
        self._subscriber: threading.Thread | None = None

    # -- invalidation -------------------------------------------------------------------------------------------
    def invalidate(self, job_id: str | None = None) -> None:
        """Drop one job's body (all of them with None). Safe from any thread (dict operations are atomic)."""
        self.generation += 1
        if job_id is None:
            self.jobs.clear()
        else:
            self.jobs.pop(job_id, None)

    def _listen(self) -> None:
        """Drop a job's body on each `neumatex:job:<id>` message; reconnect after errors (the cache is cleared then,
        as messages may have been missed)."""
        import redis

        while True:
            try:
                client = redis.Redis.from_url(get_settings().redis_url, socket_connect_timeout=5,
                                              health_check_interval=30)  # fmt: skip
                pubsub = client.pubsub(ignore_subscribe_messages=True)
                pubsub.psubscribe(CHANNEL_PREFIX + "*")
                self.invalidate()
                for message in pubsub.listen():
                    channel = message.get("channel")
                    if isinstance(channel, bytes) and message.get("type") == "pmessage":
                        self.invalidate(channel.decode()[len(CHANNEL_PREFIX):])
            except Exception as exc:  # redis down or restarting: the TTL alone bounds staleness meanwhile
                log.debug("job invalidation channel unavailable (%s); retrying in 2 s", exc)
                time.sleep(2.0)

    # -- loads ----------------------------------------------------------------------------------------------------
    async def _once(self, kind: str, ident: str, load: Callable[[], Awaitable[T]]) -> T:
        """`load()` run once for concurrent callers asking for the same (kind, ident); it runs as its own task, so a
        caller that goes away does not cancel it for the others."""
        task = self._inflight.get((kind, ident))
        if task is None:
            task = asyncio.ensure_future(load())
            self._inflight[(kind, ident)] = task
            task.add_done_callback(lambda _: self._inflight.pop((kind, ident), None))
        return await asyncio.shield(task)

    async def _tenant(self, key: str) -> str | None:
        digest = hash_api_key(key)
        hit = self.keys.get(digest)
        if hit is not None and hit[0] > time.monotonic():
            return hit[1]

        async def load() -> str | None:
            start = time.monotonic()
            tenant = await anyio.to_thread.run_sync(_tenant_of_key, digest)
            if len(self.keys) > 10_000:
                self.keys.clear()
            if tenant is not None:  # refusals are not cached: a new key works at once
                self.keys[digest] = (start + self.key_ttl_s, tenant)
            return tenant

        return await self._once("key", digest, load)

    async def _job(self, job_id: str) -> tuple[str, bytes] | None:
        hit = self.jobs.get(job_id)
        if hit is not None and hit[0] > time.monotonic():
            return hit[1], hit[2]

        async def load() -> tuple[str, bytes] | None:
            start, generation = time.monotonic(), self.generation
            found = await anyio.to_thread.run_sync(_job_body, job_id)
            if found is not None and generation == self.generation:
                if len(self.jobs) > 10_000:
                    self.jobs.clear()
                self.jobs[job_id] = (start + self.job_ttl_s, *found)
            return found

        return await self._once("job", job_id, load)

    # -- ASGI -----------------------------------------------------------------------------------------------------
    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        method, path = scope["method"], scope["path"]
        if method != "GET":
            try:
                await self.app(scope, receive, send)
            finally:
                if method != "HEAD" and path.startswith("/v1/"):
                    self.invalidate()  # this process's own changes are seen at once (read your writes)
            return
        match = JOB_PATH.fullmatch(path)
        key = _api_key(scope["headers"]) if match and not scope.get("query_string") else None
        if match is None or key is None:
            await self.app(scope, receive, send)
            return
        if self._subscribe and self._subscriber is None:
            self._subscriber = threading.Thread(target=self._listen, name="fastpath-invalidation", daemon=True)
            self._subscriber.start()
        scope["route"] = ROUTE
        tenant = await self._tenant(key)
        if tenant is None:
            await self._respond(send, 401, UNAUTHORIZED, [(b"www-authenticate", b"Bearer")])
            return
        found = await self._job(match.group(1))
        if found is None or found[0] != tenant:  # no such job, or another tenant's: the route's own 404
            await self.app(scope, receive, send)
            return
        await self._respond(send, 200, found[1])

    @staticmethod
    async def _respond(send: Send, status: int, body: bytes, extra: list[tuple[bytes, bytes]] | None = None) -> None:
        headers = [(b"content-length", str(len(body)).encode()), (b"content-type", b"application/json"),
                   *(extra or [])]  # fmt: skip
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})
