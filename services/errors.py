"""Errors the API returns: a status code and a body {"error": plain words, "problems": [{"file", "message"}]}."""

from __future__ import annotations

from typing import Any

from fastapi import HTTPException


class ApiError(HTTPException):
    def __init__(self, status: int, error: str, problems: list[dict[str, str]] | None = None,
                 headers: dict[str, str] | None = None):
        body: dict[str, Any] = {"error": error}
        if problems:
            body["problems"] = problems
        super().__init__(status, body, headers)


def not_found(what: str, ident: str) -> ApiError:
    return ApiError(404, f"{what} {ident!r} not found")
