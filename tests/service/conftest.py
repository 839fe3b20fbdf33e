"""Real infrastructure for the service tests (services.cluster): a redis-server on a free port (append-only file
on, restartable), the API under uvicorn and Celery worker processes, all started here as subprocesses with their
own data folder (SQLite + local storage). Every test in this folder is marked `service` (`pytest -m "not service"`
skips them). This folder is a package so its conftest does not shadow tests/conftest.py.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from .helpers import KEY_A, KEY_B, Service


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if Path(str(item.fspath)).parent == Path(__file__).parent:
            item.add_marker(pytest.mark.service)


@pytest.fixture(scope="session")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    root = tmp_path_factory.mktemp("service")
    svc = Service(root)
    svc.redis.start()
    svc.add_tenant("a", KEY_A)
    svc.add_tenant("b", KEY_B)
    svc.start_api()
    yield svc
    svc.stop()
