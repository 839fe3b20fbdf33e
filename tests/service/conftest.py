"""Real infrastructure for the service tests (services.cluster): a redis-server on a free port (append-only file
on, restartable), the API under uvicorn and Celery worker processes, all started here as subprocesses with their
own data folder (local storage), on each database the service supports: SQLite in that folder, and PostgreSQL, the
deployed one, from a throwaway server (tests/service/postgres.py). Every test in this folder is marked `service`
(`pytest -m "not service"` skips them). This folder is a package so its conftest does not shadow
tests/conftest.py.

The session fixture `service` is parametrized by database: tests that use it run once per database in
`databases(module)` (ids `[sqlite]`, `[postgresql]`); NEUMATEX_TEST_DATABASES=sqlite (or postgresql) picks one.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from .helpers import KEY_A, KEY_B, Service, capture_zip, submit, upload, wait_state
from .postgres import Postgres

DATABASES = ("sqlite", "postgresql")
# The modules that run on PostgreSQL too (about 5 min more on 2 cores): those exercising the database's concurrency
# and the jobs' lifecycle (workers, beat's reaper and the API writing the same rows; restarts; kill -9), the
# migrations, the client with its webhooks, quotas and retention, and the status fast path. The others (request
# validation batteries, the dashboard in a browser, the viewer route) use the same SQLAlchemy code and would add
# minutes for little; NEUMATEX_TEST_DATABASES=postgresql runs any module on PostgreSQL alone.
POSTGRES_MODULES = ("test_jobs", "test_faults", "test_lifecycle", "test_migrations", "test_client", "test_operations",
                    "test_fastpath")


def databases(module: str) -> tuple[str, ...]:
    """The databases that the tests of `module` (its name, e.g. test_jobs) run on."""
    chosen = tuple(os.environ.get("NEUMATEX_TEST_DATABASES", ",".join(DATABASES)).replace(" ", "").split(","))
    unknown = set(chosen) - set(DATABASES)
    if unknown:
        raise pytest.UsageError(f"NEUMATEX_TEST_DATABASES: unknown {sorted(unknown)} (known: {', '.join(DATABASES)})")
    return tuple(d for d in chosen if d == "sqlite" or module in POSTGRES_MODULES) or chosen[:1]


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if Path(str(item.fspath)).parent == Path(__file__).parent:
            item.add_marker(pytest.mark.service)


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "service" in metafunc.fixturenames:
        module = metafunc.module.__name__.rpartition(".")[2]
        metafunc.parametrize("service", databases(module), indirect=True, scope="session")


@pytest.fixture(scope="session")
def postgres() -> Iterator[Postgres]:
    """A PostgreSQL server for the whole session (started on first use); databases made with create_database."""
    server = Postgres().start()
    yield server
    server.stop()


@pytest.fixture(scope="session")
def service(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    database = getattr(request, "param", "sqlite")
    root = tmp_path_factory.mktemp(f"service-{database}")
    url = request.getfixturevalue("postgres").create_database("service") if database == "postgresql" else None
    svc = Service(root, url)
    svc.redis.start()
    svc.add_tenant("a", KEY_A)
    svc.add_tenant("b", KEY_B)
    svc.start_api()
    yield svc
    svc.stop()


@pytest.fixture(autouse=True)
def stop_test_workers(request: pytest.FixtureRequest) -> Iterator[None]:
    """Stop the workers a test started when it ends, passed or failed: the service is shared by the session, so a
    worker left running by a failed test would take later tests' jobs and fail them too."""
    if "service" not in request.fixturenames:
        yield
        return
    service: Service = request.getfixturevalue("service")
    before = len(service.workers)
    yield
    for worker in service.workers[before:]:
        worker.stop()


@pytest.fixture(scope="module")
def done(service: Service) -> Iterator[dict[str, Any]]:
    """One completed tiny job of tenant A, once per module (its worker is stopped afterwards)."""
    worker = service.start_worker()
    try:
        with service.client() as c:
            r = upload(c, capture_zip())
            assert r.status_code == 201, r.text
            job = wait_state(c, submit(c, r.json()["id"])["id"], ("completed", "failed", "canceled"), 240, service)
            assert job["state"] == "completed", job["error"]
        yield job
    finally:
        worker.stop()
