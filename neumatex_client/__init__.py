"""A typed Python client of the NeuMatEx job service (services/, docs/service.md) and the `neumatex submit | jobs
| job` commands. Imports only httpx, pydantic and tqdm: nothing of the service or of neumatex_core."""

from neumatex_client.client import Client, Event
from neumatex_client.errors import (
    ApiError,
    AuthError,
    Conflict,
    Invalid,
    NeuMatExError,
    NotFound,
    ServiceUnreachable,
    TooBusy,
    WaitTimeout,
)
from neumatex_client.models import AssetManifest, Capture, Job, JobPage, Quota, WebhookDelivery
from neumatex_client.signature import sign, verify_signature

__all__ = ["ApiError", "AssetManifest", "AuthError", "Capture", "Client", "Conflict", "Event", "Invalid", "Job",
           "JobPage", "NeuMatExError", "NotFound", "Quota", "ServiceUnreachable", "TooBusy", "WaitTimeout",
           "WebhookDelivery", "sign", "verify_signature"]  # fmt: skip
