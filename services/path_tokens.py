"""Signed path tokens: a link to one job's files that needs no API key (docs/service.md, "report" and "viewer").

A frame, an <img> or a new tab cannot send an Authorization header, and pages reference their files by relative
URLs, so the token is a path segment: `base64url(job id, tenant id, expiry) . HMAC-SHA256` with a key derived from
the service's secret and the token's purpose (a report token does not open the viewer, nor the other way round).
Nothing is stored; a token opens only its job's files of its purpose (not the API) and expires after `ttl_s`
(default `REPORT_TOKEN_TTL_S`).
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import time
from dataclasses import dataclass
from typing import Literal

from services.core.config import get_settings

Problem = Literal["", "invalid", "other job", "expired"]


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


@dataclass(frozen=True)
class PathTokens:
    """Tokens of one purpose (e.g. "report-token", "viewer-token")."""

    purpose: str

    def _key(self) -> bytes:
        from services.webhooks import service_secret

        return hmac.new(service_secret(), self.purpose.encode(), hashlib.sha256).digest()

    def mint(self, job_id: str, tenant_id: str, ttl_s: float | None = None,
             at: float | None = None) -> tuple[str, int]:  # fmt: skip
        """A token for the job's files and its expiry (unix seconds)."""
        ttl = get_settings().report_token_ttl_s if ttl_s is None else ttl_s
        expires = int((time.time() if at is None else at) + ttl)
        payload = f"{job_id}\n{tenant_id}\n{expires}".encode()
        return f"{_b64(payload)}.{_b64(hmac.new(self._key(), payload, hashlib.sha256).digest())}", expires

    def verify(self, token: str, job_id: str) -> tuple[str | None, Problem]:
        """(the tenant id the token was minted for, "") or (None, what is wrong with it)."""
        body, _, sig = token.partition(".")
        try:
            payload, given = _unb64(body), _unb64(sig)
        except (binascii.Error, ValueError):
            return None, "invalid"
        if not hmac.compare_digest(hmac.new(self._key(), payload, hashlib.sha256).digest(), given):
            return None, "invalid"
        try:
            token_job, tenant_id, expires = payload.decode().split("\n")
            expiry = int(expires)
        except ValueError:
            return None, "invalid"
        if token_job != job_id:
            return None, "other job"
        if time.time() > expiry:
            return None, "expired"
        return tenant_id, ""
