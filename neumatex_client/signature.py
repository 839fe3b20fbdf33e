"""Webhook signatures: `X-NeuMatEx-Signature: t=<unix seconds>,v1=<hex HMAC-SHA256(secret, "<t>." + raw body)>`
with the tenant's secret (`Client.webhook_secret()`). Verify over the raw request body, before parsing it."""

from __future__ import annotations

import hashlib
import hmac
import time


def sign(secret: str, body: bytes, timestamp: int) -> str:
    """The header value the service sends for `body` at `timestamp`."""
    digest = hmac.new(secret.encode(), f"{timestamp}.".encode() + body, hashlib.sha256).hexdigest()
    return f"t={timestamp},v1={digest}"


def verify_signature(secret: str, body: bytes, header: str | None, tolerance_s: float = 300.0,
                     now: float | None = None) -> bool:  # fmt: skip
    """True when `header` is a valid signature of `body` by `secret`, made within `tolerance_s` of now (replays of
    an old delivery are refused); compares in constant time."""
    if not header:
        return False
    fields = dict(part.split("=", 1) for part in header.split(",") if "=" in part)
    try:
        t = int(fields.get("t", ""))
    except ValueError:
        return False
    if abs((time.time() if now is None else now) - t) > tolerance_s:
        return False
    expected = sign(secret, body, t).split("v1=", 1)[1]
    return hmac.compare_digest(expected, fields.get("v1", ""))
