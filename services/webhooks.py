"""Webhooks: a job created with a `webhook_url` gets a signed JSON POST there each time it reaches a terminal state
(completed, failed, canceled).

The one hook is `lifecycle.add_event`: every terminal transition (the worker completing or failing a job, a cancel,
in the same transaction as the state change) writes a `state` event through it, and `enqueue` adds a
`WebhookDelivery` row beside it when the job has a URL. The `WebhookSender` thread of each API process sends the
due deliveries: claimed by a conditional UPDATE (one replica wins), POSTed without following
redirects, retried with exponential backoff (`webhook_backoff_s` doubling, at least the receiver's Retry-After on
429/503) until a 2xx or `webhook_max_attempts`; every attempt is logged on the row and shown in the job's JSON.

Signature: `X-NeuMatEx-Signature: t=<unix seconds>,v1=<hex HMAC-SHA256(secret, "<t>." + body)>`, the secret being
the tenant's (`GET /v1/webhook-secret`; derived from the service's `webhook_secret` and the tenant id, so nothing is
stored). Receivers recompute it over the raw body, compare in constant time and refuse old timestamps
(`neumatex_client.verify_signature`).

URLs must be http(s) on a public address (loopback, private, link-local, multicast and reserved ones are refused,
checked at creation and again before each attempt, as DNS may change) unless `webhook_allow_private` is set.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import json
import logging
import os
import secrets
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta
from functools import lru_cache
from typing import Any
from urllib.parse import urlsplit

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from services.core.config import get_settings
from services.core.db import session_scope
from services.models import Job, WebhookDelivery, now
from services.redact import redact_data, redact_text

log = logging.getLogger("neumatex.webhooks")
SIGNATURE_HEADER = "X-NeuMatEx-Signature"
CLAIM_S = 120.0  # a claimed delivery is retried by another sender after this if its claimer vanished


# -- secrets and signatures -----------------------------------------------------------------------------------
@lru_cache
def service_secret() -> bytes:
    """The `webhook_secret` setting, else the one kept in <data_dir>/webhook-secret.txt (created once)."""
    st = get_settings()
    if st.webhook_secret:
        return st.webhook_secret.encode()
    path = st.data_dir / "webhook-secret.txt"
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_hex(32) + "\n")
    except FileExistsError:
        for _ in range(50):  # another process is writing it
            if path.read_text().strip():
                break
            time.sleep(0.02)
    return path.read_text().strip().encode()


def tenant_secret(tenant_id: str) -> str:
    return "whsec_" + hmac.new(service_secret(), f"webhook:{tenant_id}".encode(), hashlib.sha256).hexdigest()


def sign(secret: str, body: bytes, timestamp: int) -> str:
    digest = hmac.new(secret.encode(), f"{timestamp}.".encode() + body, hashlib.sha256).hexdigest()
    return f"t={timestamp},v1={digest}"


# -- URL checks -----------------------------------------------------------------------------------------------
def _public(ip: ipaddress.IPv4Address | ipaddress.IPv6Address) -> bool:
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return ip.is_global and not ip.is_multicast


def url_problem(url: str, allow_private: bool | None = None) -> str | None:
    """Why `url` cannot be a webhook URL (None when it can): not http(s), no host, or an address that is not
    public (unless private ones are allowed), or a host that does not resolve."""
    allow = get_settings().webhook_allow_private if allow_private is None else allow_private
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        return f"webhook_url is not a valid URL ({exc})"
    if parts.scheme not in ("http", "https"):
        return f"webhook_url must be an http or https URL, not {parts.scheme or 'one without a scheme'!r}"
    host = parts.hostname
    if not host:
        return "webhook_url has no host"
    try:
        infos = socket.getaddrinfo(host, port or (443 if parts.scheme == "https" else 80), type=socket.SOCK_STREAM)
    except (OSError, UnicodeError):
        return f"webhook_url's host {host!r} does not resolve"
    if allow:
        return None
    for info in infos:
        ip = ipaddress.ip_address(str(info[4][0]).split("%")[0])
        if not _public(ip):
            return (f"webhook_url's host {host!r} is a loopback, private or reserved address ({ip}); the service "
                    "only calls public addresses (NEUMATEX_WEBHOOK_ALLOW_PRIVATE=true allows others)")
    return None


# -- the hook -------------------------------------------------------------------------------------------------
def enqueue(s: Session, job_id: str, state: str) -> None:
    """Called by lifecycle.add_event for every terminal `state` event, inside the transition's transaction."""
    job = s.get(Job, job_id)
    if job is not None and job.webhook_url:
        s.add(WebhookDelivery(job_id=job_id, tenant_id=job.tenant_id, url=job.webhook_url, state=state,
                              job_attempt=job.attempt, next_at=now()))  # fmt: skip


def deliveries_of(s: Session, job_id: str) -> list[WebhookDelivery]:
    q = select(WebhookDelivery).where(WebhookDelivery.job_id == job_id).order_by(WebhookDelivery.created_at)
    return list(s.scalars(q))


# -- sending --------------------------------------------------------------------------------------------------
def payload(job: Job, delivery: WebhookDelivery) -> dict[str, Any]:
    base = get_settings().public_url.rstrip("/")
    return {"id": delivery.id, "event": f"job.{delivery.state}", "job_id": job.id, "state": delivery.state,
            "attempt": delivery.job_attempt, "capture_id": job.capture_id, "preset": job.preset,
            "error": redact_text(job.error) if delivery.state == "failed" else "",
            "metrics": redact_data(job.metrics or {}), "timings": job.timings or {},
            "finished_at": job.finished_at.isoformat() if job.finished_at else None,
            "job_url": f"{base}/v1/jobs/{job.id}",
            "asset_url": f"{base}/v1/jobs/{job.id}/asset.zip" if delivery.state == "completed" else None}  # fmt: skip


def backoff(attempts: int, retry_after: float | None = None) -> float:
    st = get_settings()
    delay = st.webhook_backoff_s * 2 ** max(attempts - 1, 0)
    if retry_after is not None:
        delay = max(delay, retry_after)
    return float(min(delay, st.webhook_max_backoff_s))


def _retry_after(value: str | None) -> float | None:
    try:
        return max(0.0, float(value)) if value else None
    except ValueError:
        return None


def _claim(limit: int = 32) -> list[str]:
    """Due deliveries taken by this sender (their next_at pushed CLAIM_S ahead by a conditional UPDATE)."""
    taken = []
    with session_scope() as s:
        due = s.execute(select(WebhookDelivery.id, WebhookDelivery.next_at).where(
            WebhookDelivery.status == "pending", WebhookDelivery.next_at <= now())
            .order_by(WebhookDelivery.next_at).limit(limit)).all()  # fmt: skip
        for ident, next_at in due:
            r = s.execute(update(WebhookDelivery).where(WebhookDelivery.id == ident,
                                                        WebhookDelivery.next_at == next_at,
                                                        WebhookDelivery.status == "pending")
                          .values(next_at=now() + timedelta(seconds=CLAIM_S)))  # fmt: skip
            if r.rowcount:  # type: ignore[attr-defined]
                taken.append(ident)
    return taken


def send(delivery_id: str) -> str:
    """One attempt of one claimed delivery; returns its status afterwards."""
    import httpx

    st = get_settings()
    with session_scope() as s:
        d = s.get(WebhookDelivery, delivery_id)
        if d is None:
            return "gone"
        job = s.get(Job, d.job_id)
        body = json.dumps(payload(job, d), sort_keys=True).encode() if job is not None else b""
        url, tenant_id, state = d.url, d.tenant_id, d.state
    code: int | None = None
    error, retry_after = "", None
    t0 = time.perf_counter()
    if job is None:
        error = "the job was deleted"
    else:
        problem = url_problem(url)
        if problem:
            error = problem
        else:
            headers = {"Content-Type": "application/json", "User-Agent": "NeuMatEx-Webhook/1",
                       "X-NeuMatEx-Event": f"job.{state}", "X-NeuMatEx-Delivery": delivery_id,
                       SIGNATURE_HEADER: sign(tenant_secret(tenant_id), body, int(time.time()))}  # fmt: skip
            try:
                r = httpx.post(url, content=body, headers=headers, timeout=st.webhook_timeout_s,
                               follow_redirects=False)  # fmt: skip
                code = r.status_code
                if not 200 <= code < 300:
                    error = f"the receiver answered {code}"
                    if code in (429, 503):
                        retry_after = _retry_after(r.headers.get("retry-after"))
            except httpx.HTTPError as exc:
                error = f"{type(exc).__name__}: {exc}"[:300]
    with session_scope() as s:
        d = s.get(WebhookDelivery, delivery_id)
        if d is None:
            return "gone"
        d.attempts += 1
        d.log = [*(d.log or []), {"at": now().isoformat(), "status_code": code, "error": redact_text(error),
                                  "seconds": round(time.perf_counter() - t0, 3)}]  # fmt: skip
        if not error:
            d.status, d.delivered_at = "delivered", now()
        elif job is None or d.attempts >= st.webhook_max_attempts:
            d.status = "failed"
        else:
            d.next_at = now() + timedelta(seconds=backoff(d.attempts, retry_after))
        if error:
            log.warning("webhook %s of job %s, attempt %d: %s", delivery_id, d.job_id, d.attempts, error)
        return d.status


def deliver_due(pool: ThreadPoolExecutor | None = None) -> list[str]:
    """One pass: send every due delivery (concurrently on `pool`); returns their statuses."""
    taken = _claim()
    if pool is None:
        return [send(i) for i in taken]
    return list(pool.map(send, taken))


class WebhookSender(threading.Thread):
    """Sends due webhook deliveries every webhook_poll_s (a thread of each API process)."""

    def __init__(self) -> None:
        super().__init__(daemon=True, name="neumatex-webhooks")
        self.stopped = threading.Event()

    def run(self) -> None:
        every = get_settings().webhook_poll_s
        with ThreadPoolExecutor(8, thread_name_prefix="webhook") as pool:
            while not self.stopped.wait(every):
                try:
                    deliver_due(pool)
                except Exception as exc:  # database briefly away: next pass
                    log.warning("webhook pass failed: %s", exc)
