"""Helpers of the service tests: the tests' cluster (services.cluster with fast heartbeats and small limits) on
SQLite or PostgreSQL, SQL on its database, capture zips, upload/submit/wait helpers and an SSE reader."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import threading
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from functools import lru_cache
from pathlib import Path
from typing import Any

import httpx
from sqlalchemy import Engine, create_engine, text
from sqlalchemy.pool import NullPool

from services.cluster import FAST, REPO, Cluster, wait_for

EXAMPLE = REPO / "examples" / "teapot"
KEY_A = "nmx_test_tenant_a_0123456789abcdefghij"
KEY_B = "nmx_test_tenant_b_0123456789abcdefghij"
# The smallest real configuration: the tiny preset from a random triplane (no LMRM checkpoint needed).
TINY = {"init": "random", "device": "cpu"}
METRICS_TOKEN = "nmx_test_metrics_token_0123456789"


class Service(Cluster):
    """The tests' cluster: fast heartbeats and reaping, small upload limits. Its database: `database_url` (e.g. a
    PostgreSQL one from tests/service/postgres.py, passed as NEUMATEX_DATABASE_URL), else SQLite in its data
    folder. With `proxy`, nginx in front (services/proxy.py): `url` is the proxy's, `api_url` the API's."""

    def __init__(self, root: Path, database_url: str | None = None, proxy: bool = False):
        (root / "tmp").mkdir(parents=True, exist_ok=True)  # the processes' TMPDIR, so tests can see what spools there
        self.database_url = database_url or f"sqlite:///{(root / 'data' / 'jobs.db').resolve()}"
        self.database = "postgresql" if self.database_url.startswith("postgresql") else "sqlite"
        super().__init__(root, {**FAST, "NEUMATEX_DATABASE_URL": self.database_url,
                                "NEUMATEX_MAX_UPLOAD_BYTES": str(8 * 1024**2),
                                "NEUMATEX_MAX_CAPTURE_BYTES": str(32 * 1024**2), "NEUMATEX_MAX_FILES": "200",
                                "TMPDIR": str(root / "tmp"), "NEUMATEX_METRICS_TOKEN": METRICS_TOKEN,
                                # webhooks to a receiver in the test (loopback), retried quickly
                                "NEUMATEX_WEBHOOK_ALLOW_PRIVATE": "true", "NEUMATEX_WEBHOOK_BACKOFF_S": "0.5",
                                "NEUMATEX_WEBHOOK_POLL_S": "0.2"}, proxy=proxy)  # fmt: skip
        self.env["NEUMATEX_PUBLIC_URL"] = self.url

    def client(self, key: str = KEY_A) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers={"Authorization": f"Bearer {key}"}, timeout=60)


@lru_cache(maxsize=8)
def _engine(url: str) -> Engine:
    # NullPool: every call opens and closes its connection, so none is held while the service's processes run.
    return create_engine(url, poolclass=NullPool, **({"connect_args": {"timeout": 30}} if url.startswith("sqlite")
                                                     else {}))  # fmt: skip


def sql(service: Service, query: str, **params: Any) -> list[tuple[Any, ...]]:
    """Run `query` on the service's database (SQLite or PostgreSQL) in its own transaction, committed; its rows
    (none for a statement without result). Parameters are named, `:name` in the query, e.g.
    sql(service, "UPDATE jobs SET state = :state WHERE id = :id", state="failed", id=job_id). Write portable SQL:
    times as parameters (helpers.db_time), JSON columns as json.dumps(...) strings, booleans as true/false."""
    with _engine(service.database_url).begin() as conn:
        result = conn.execute(text(query), params)
        return [tuple(row) for row in result] if result.returns_rows else []


def db_time(seconds_ago: float = 0.0) -> datetime:
    """A time as the service stores it (naive UTC, services/models.py now()), `seconds_ago` before now."""
    return datetime.now(UTC).replace(tzinfo=None) - timedelta(seconds=seconds_ago)


def capture_zip(source: Path = EXAMPLE, prefix: str = "teapot/", skip: tuple[str, ...] = ("photos", "gbuffers"),
                extra: dict[str, bytes] | None = None, drop: tuple[str, ...] = ()) -> bytes:
    """A zip of a capture folder (the example teapot by default, without its photos/ and gbuffers/ folders)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for p in sorted(source.rglob("*")):
            rel = p.relative_to(source).as_posix()
            if p.is_file() and rel.split("/")[0] not in skip and rel not in drop:
                z.write(p, prefix + rel)
        for name, data in (extra or {}).items():
            z.writestr(prefix + name, data)
    return buf.getvalue()


def upload(client: httpx.Client, data: bytes, name: str = "teapot") -> httpx.Response:
    return client.post("/v1/captures", params={"name": name}, content=data,
                       headers={"Content-Type": "application/zip"})  # fmt: skip


def submit(client: httpx.Client, capture_id: str, tto: dict[str, Any] | None = None, **kw: Any) -> dict[str, Any]:
    config = {**TINY, "tto": tto or {}}
    r = client.post("/v1/jobs", json={"capture_id": capture_id, "preset": "tiny", "config": config, **kw})
    assert r.status_code in (200, 201), r.text
    return dict(r.json())


def job(client: httpx.Client, job_id: str) -> dict[str, Any]:
    r = client.get(f"/v1/jobs/{job_id}")
    assert r.status_code == 200, r.text
    return dict(r.json())


def wait_state(client: httpx.Client, job_id: str, states: tuple[str, ...], timeout: float,
               service: Cluster | None = None) -> dict[str, Any]:
    try:
        return dict(wait_for(lambda: (j := job(client, job_id))["state"] in states and j, timeout,
                             f"job {job_id} to reach {states}", every=0.25))  # fmt: skip
    except AssertionError:
        if service is not None:
            for w in service.workers:
                print(f"--- {w.log.name}\n{w.tail()}")
            print(json.dumps(job(client, job_id), indent=1))
        raise


def tto_step(client: httpx.Client, job_id: str) -> int:
    j = job(client, job_id)
    if j["stage"] != "tto" or j["state"] != "running":
        return 0
    return round(j["stage_fraction"] * 1000)  # fraction of the TTO schedule, in thousandths


def sse_events(service: Service, job_id: str, key: str = KEY_A, timeout: float = 240) -> list[dict[str, Any]]:
    """Every event of the job's SSE stream until the server ends it (terminal state)."""
    events: list[dict[str, Any]] = []
    with httpx.stream("GET", f"{service.url}/v1/jobs/{job_id}/events", headers={"Authorization": f"Bearer {key}"},
                      timeout=httpx.Timeout(timeout, read=60)) as r:  # fmt: skip
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        kind, ident = None, None
        for line in r.iter_lines():
            if line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("id: "):
                ident = int(line[4:])
            elif line.startswith("data: "):
                events.append({"event": kind, "id": ident, **json.loads(line[6:])})
                if kind == "end":
                    break
                kind, ident = None, None
    return events


def blank_masks(source: Path = EXAMPLE) -> dict[str, bytes]:
    """The capture's masks (relative path -> PNG bytes) all zero: a capture that passes the upload's validation but
    whose job fails in its TTO stage ("the mesh covers no pixel of any photo")."""
    import numpy as np
    from PIL import Image

    out: dict[str, bytes] = {}
    for p in sorted((source / "masks").glob("*.png")):
        buf = io.BytesIO()
        Image.fromarray(np.zeros_like(np.asarray(Image.open(p)))).save(buf, format="PNG")
        out[p.relative_to(source).as_posix()] = buf.getvalue()
    return out


def mint_in_service(service: Service, purpose: str, job_id: str, *grants: tuple[str, float]) -> list[str]:
    """Path tokens of `purpose` ("report-token", "viewer-token"; services/path_tokens.py) minted with the running
    service's own secret (its data folder) for (tenant id, seconds to live) each, e.g. one that has already expired."""
    code = ("import sys; from services.path_tokens import PathTokens; t = PathTokens(sys.argv[1]); "
            "[print(t.mint(sys.argv[2], g, ttl_s=float(s))[0]) for g, s in zip(sys.argv[3::2], sys.argv[4::2])]")
    args = [str(x) for grant in grants for x in grant]
    out = subprocess.run([sys.executable, "-c", code, purpose, job_id, *args], env=service.env, cwd=REPO, check=True,
                         capture_output=True, text=True)  # fmt: skip
    return out.stdout.split()


@contextmanager
def other_tenant_served(service: Service, capture_id: str) -> Iterator[None]:
    """Tenant B's GET of its capture `capture_id`, repeated in a thread while the block runs (tenant A's bad request
    or the service's bad config): every answer must be 200."""
    codes: list[int] = []
    done = threading.Event()

    def poll() -> None:
        with service.client(KEY_B) as c:
            while True:
                codes.append(c.get(f"/v1/captures/{capture_id}").status_code)
                if done.wait(0.05):
                    return

    t = threading.Thread(target=poll)
    t.start()
    try:
        yield
    finally:
        done.set()
        t.join(60)
    assert codes and set(codes) == {200}, f"tenant B was not served meanwhile: {codes}"
