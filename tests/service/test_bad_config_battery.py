"""Bad-input battery, job configs and headers (issue 15, part B), against the real service (no worker runs).

Every case asserts the status code and the message (naming the field or header and the problem), that no job was
created (no record, nothing new in the storage folder), and that tenant B was served meanwhile (its GETs run in a
thread during the request and all answer 200). A config the pipeline would fail on later is refused here: the
service promises "a bad config is a 422, never a failed job".
"""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest

from .helpers import KEY_A, KEY_B, TINY, Service, capture_zip, other_tenant_served, sql, upload

Case = Callable[[httpx.Client, dict[str, Any]], httpx.Response]


def job_post(config: Any = None, **body: Any) -> Case:
    def case(c: httpx.Client, world: dict[str, Any]) -> httpx.Response:
        payload = {"capture_id": world["cap_a"], "preset": "tiny", **body}
        if config is not None:
            payload["config"] = config
        return c.post("/v1/jobs", json=payload)

    return case


def raw(method: str, path: str, headers: dict[Any, Any] | None = None, content: bytes | None = None,
        auth: bool = True) -> Case:  # fmt: skip
    def case(c: httpx.Client, world: dict[str, Any]) -> httpx.Response:
        h = dict(headers or {})
        if auth:
            h.setdefault("Authorization", f"Bearer {KEY_A}")
        url = path.format(**world)
        with httpx.Client(base_url=str(c.base_url), timeout=60) as bare:
            return bare.request(method, url, headers=h, content=content)

    return case


DEEP = b'{"capture_id": "x", "config": ' + b'{"a": ' * 100_000 + b"1" + b"}" * 100_000 + b"}"
# kind -> (request, status, words the error must hold)
CASES: dict[str, tuple[Case, int, tuple[str, ...]]] = {
    # configs: types
    "steps not a whole number": (job_post({**TINY, "tto": {"steps": 2.5}}), 422,
                                 ("config.tto.steps", "valid integer", "2.5")),
    "steps as a string": (job_post({**TINY, "tto": {"steps": "3"}}), 422, ("config.tto.steps", "valid integer")),
    "seed a boolean": (job_post({**TINY, "seed": True}), 422, ("config.seed", "valid integer")),
    "tto an empty list": (job_post({**TINY, "tto": []}), 422, ("config.tto", "dictionary")),
    "tto a string": (job_post({**TINY, "tto": "fast"}), 422, ("config.tto", "dictionary")),
    "config a list": (job_post([1, 2]), 422, ("config", "dictionary")),
    # configs: ranges (the core's RANGES)
    "view_resolution 0": (job_post({**TINY, "view_resolution": 0}), 422,
                          ("config.view_resolution", "greater than or equal to 16", "0")),
    "view_resolution -8": (job_post({**TINY, "view_resolution": -8}), 422,
                           ("config.view_resolution", "greater than or equal to 16", "-8")),
    "steps absurdly many": (job_post({**TINY, "tto": {"steps": 10**9}}), 422,
                            ("config.tto.steps", "less than or equal to 100000")),
    "lr zero": (job_post({**TINY, "tto": {"lr": 0}}), 422, ("config.tto.lr", "greater than 0")),
    "name too long": (job_post({**TINY, "name": "n" * 300}), 422, ("config.name", "at most 200 characters")),
    # configs: unknown or fixed keys, choices
    "unknown config key": (job_post({**TINY, "stepz": 3}), 422, ("config.stepz", "unknown field")),
    "unknown TTO key": (job_post({**TINY, "tto": {"stepz": 3}}), 422, ("config.tto.stepz", "unknown field")),
    "lmrm_weights (a server path)": (job_post({**TINY, "lmrm_weights": "/etc/passwd"}), 422,
                                     ("config.lmrm_weights", "unknown field")),
    "tto.init (set at the top level)": (job_post({**TINY, "tto": {"init": "pbr"}}), 422,
                                        ("config.tto.init", "unknown field")),
    "unknown top-level key": (job_post(TINY, priority="high"), 422, ("priority", "unknown field")),
    "unknown preset": (job_post(TINY, preset="huge"), 422, ("preset", "'tiny', 'cpu' or 'gpu'", "huge")),
    "unknown device": (job_post({**TINY, "device": "tpu"}), 422, ("config.device", "'auto', 'cpu' or 'cuda'")),
    "unknown queue": (job_post(TINY, queue="fast"), 422, ("queue", "'cpu' or 'gpu'")),
    # configs the pipeline would fail on later
    "TTO reg oracle": (job_post({**TINY, "tto": {"reg": "oracle"}}), 422, ("bad job config", "oracle", "evaluation")),
    "TTO material pbr": (job_post({**TINY, "tto": {"material": "pbr"}}), 422,
                         ("bad job config", "material='pbr'", "PBR baseline")),
    "init pbr with a UV field": (job_post({"init": "pbr", "device": "cpu", "tto": {"field": "uv"}}), 422,
                                 ("bad job config", "init='pbr'", "triplane")),
    # device and queue the cluster cannot serve
    "device cuda, no CUDA worker": (job_post({**TINY, "device": "cuda"}), 422,
                                    ("bad job config", "device 'cuda'", "no worker is live")),
    "device cuda on the gpu queue": (job_post({**TINY, "device": "cuda"}, queue="gpu"), 422,
                                     ("device 'cuda'", "'gpu' queue")),
    # bodies
    "not JSON": (raw("POST", "/v1/jobs", {"Content-Type": "application/json"}, b"{capture_id: 1"), 422,
                 ("does not match the API", "JSON")),
    "deeply nested JSON": (raw("POST", "/v1/jobs", {"Content-Type": "application/json"}, DEEP), 400,
                           ("parsing the body",)),
    "another tenant's capture": (lambda c, w: c.post("/v1/jobs", json={"capture_id": w["cap_b"], "preset": "tiny",
                                                                       "config": TINY}), 404, ("capture", "not found")),
    # headers
    "Basic auth": (raw("GET", "/v1/jobs", {"Authorization": "Basic YTpi"}), 401, ("missing API key", "Bearer")),
    "Bearer with no key": (raw("GET", "/v1/jobs", {"Authorization": "Bearer"}), 401, ("missing API key",)),
    "Bearer with a wrong key": (raw("GET", "/v1/jobs", {"Authorization": "Bearer nmx_wrong"}), 401,
                                ("unknown or revoked API key",)),
    "empty X-API-Key": (raw("GET", "/v1/jobs", {"X-API-Key": ""}, auth=False), 401, ("missing API key",)),
    "non-ASCII key": (raw("GET", "/v1/jobs", {b"Authorization": b"Bearer \xff\xfe\x01"}), 401,
                      ("unknown or revoked API key",)),
    "oversize auth header": (raw("GET", "/v1/jobs", {"Authorization": "Bearer " + "k" * 60_000}), 401,
                             ("unknown or revoked API key",)),
    "oversize Idempotency-Key": (raw("POST", "/v1/jobs", {"Idempotency-Key": "i" * 300, "Content-Type":
                                 "application/json"}, json.dumps({"capture_id": "x"}).encode()), 422,
                                 ("idempotency-key", "at most 200 characters")),
    "metrics without the token": (raw("GET", "/metrics", auth=False), 401, ("/metrics", "Bearer")),
    "metrics with a tenant key": (raw("GET", "/metrics"), 401, ("/metrics", "metrics token")),
}  # fmt: skip


def job_rows(service: Service) -> int:
    return int(sql(service, "SELECT COUNT(*) FROM jobs")[0][0])


def listing(root: Path) -> set[str]:
    return {p.relative_to(root).as_posix() for p in root.rglob("*") if "staging" not in p.parts}


@pytest.fixture(scope="module")
def world(service: Service) -> dict[str, Any]:
    with service.client(KEY_A) as a, service.client(KEY_B) as b:
        return {"cap_a": upload(a, capture_zip()).json()["id"], "cap_b": upload(b, capture_zip()).json()["id"]}


def test_at_least_twelve_kinds() -> None:
    assert len(CASES) >= 12


@pytest.mark.parametrize("kind", list(CASES))
def test_bad_config_or_header(service: Service, world: dict[str, Any], kind: str) -> None:
    case, status, words = CASES[kind]
    rows, files = job_rows(service), listing(service.storage)
    with other_tenant_served(service, world["cap_b"]), service.client() as c:
        r = case(c, world)
    assert r.status_code == status, (kind, r.status_code, r.text[:500])
    error = r.json()["error"]
    for word in words:
        assert word.lower() in error.lower(), (kind, word, error)
    assert str(service.root) not in r.text  # no server path in the answer
    assert job_rows(service) == rows, f"{kind}: a job record was created"
    assert listing(service.storage) == files, f"{kind}: something was written to the storage"


def test_name_is_accepted_and_reaches_the_config(service: Service, world: dict[str, Any]) -> None:
    """`config.name` is allowed, and works (it used to be listed as allowed and refused with a 422 about preset())."""
    with service.client() as c:
        r = c.post("/v1/jobs", json={"capture_id": world["cap_a"], "preset": "tiny",
                                     "config": {**TINY, "name": "red teapot", "tto": {"steps": 2}}})  # fmt: skip
        assert r.status_code == 201, r.text
        job = r.json()
        assert job["config"] == {**TINY, "name": "red teapot", "tto": {"steps": 2}}
        assert c.post(f"/v1/jobs/{job['id']}/cancel").status_code == 200  # no worker runs it


def test_a_long_head_split_by_tcp_still_reaches_the_app(service: Service) -> None:
    """A 60 KB Authorization header sent in three pieces with pauses between them (as a slow link would deliver it)
    gets the API's 401, not uvicorn's bare 400 and a reset: h11 buffers up to MAX_HEADER_BYTES of a head."""
    url = httpx.URL(service.url)
    head = (f"GET /v1/jobs HTTP/1.1\r\nHost: {url.host}\r\nConnection: close\r\nAuthorization: Bearer "
            + "k" * 60_000 + "\r\n\r\n").encode()
    with socket.create_connection((url.host, url.port), timeout=30) as s:
        for piece in (head[:10_000], head[10_000:30_000], head[30_000:]):
            s.sendall(piece)
            time.sleep(0.2)
        answer = b""
        while chunk := s.recv(65536):
            answer += chunk
    status_line, _, rest = answer.partition(b"\r\n")
    assert status_line.split()[1] == b"401", answer[:300]
    assert b"unknown or revoked API key" in rest
