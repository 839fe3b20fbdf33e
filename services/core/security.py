"""API keys: random 32-byte tokens shown once; only their SHA-256 is stored (high-entropy keys need no slow hash)."""

from __future__ import annotations

import hashlib
import hmac
import secrets

PREFIX = "nmx_"


def new_api_key() -> str:
    return PREFIX + secrets.token_urlsafe(32)


def hash_api_key(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


def same(a: str, b: str) -> bool:
    return hmac.compare_digest(a, b)
