"""Exceptions of the client. Every refusal of the service is an `ApiError` (or a subclass by status) carrying the
server's `error` sentence and its `problems` list; `ServiceUnreachable` is a connection that kept failing after
the retries."""

from __future__ import annotations

from typing import Any


class NeuMatExError(Exception):
    """Base class of the client's errors."""


class ServiceUnreachable(NeuMatExError):
    """The service did not answer (connection refused, reset, timed out) after every retry."""


class ApiError(NeuMatExError):
    """The service refused the request: `status` and its plain-words `error` (and `problems`, one per file)."""

    def __init__(self, status: int, error: str, problems: list[dict[str, Any]] | None = None, method: str = "",
                 path: str = ""):  # fmt: skip
        self.status, self.error, self.problems = status, error, list(problems or [])
        self.method, self.path = method, path
        super().__init__(f"{status}: {error}")

    def __str__(self) -> str:
        lines = [f"{self.error} (HTTP {self.status})"]
        lines += [f"  {p.get('file', '')}: {p.get('message', '')}" for p in self.problems[:20]]
        if len(self.problems) > 20:
            lines.append(f"  ... and {len(self.problems) - 20} more")
        return "\n".join(lines)


class AuthError(ApiError):
    """401: the API key is missing, unknown or revoked."""


class NotFound(ApiError):
    """404: no such capture, job or file for this tenant."""


class Conflict(ApiError):
    """409: the job's state does not allow it, or an idempotency key was reused for another request."""


class Invalid(ApiError):
    """422: an invalid capture or job config (the problems name the files or fields)."""


class TooBusy(ApiError):
    """429/503 that outlasted the retries (e.g. the tenant's active-job limit)."""


class WaitTimeout(NeuMatExError):
    """`Client.wait` ran past its timeout before the job ended."""


BY_STATUS: dict[int, type[ApiError]] = {401: AuthError, 404: NotFound, 409: Conflict, 422: Invalid, 429: TooBusy,
                                        503: TooBusy}  # fmt: skip
