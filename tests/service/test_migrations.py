"""The Alembic migrations (services/migrations) on SQLite and on a real PostgreSQL server: the migrated schema is
the models' (alembic's compare_metadata finds no difference), a database made by the old `create_all` is stamped
at the initial revision (its rows kept, tables it lacked created), processes migrating at once all succeed, and
the service's engine (get_engine) migrates at start."""

from __future__ import annotations

import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Engine, insert, inspect, text

from services import models
from services.core.db import INITIAL_REVISION, Base, alembic_config, make_engine, migrate

from .conftest import databases
from .postgres import Postgres

HEAD = ScriptDirectory.from_config(alembic_config()).get_current_head()


@pytest.fixture(params=databases("test_migrations"))
def url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """An empty database: a new SQLite file, or a new database on the session's PostgreSQL server."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'jobs.db'}"
    server: Postgres = request.getfixturevalue("postgres")
    return server.create_database(f"mig_{abs(hash(request.node.name)) % 10**8}")


@pytest.fixture
def engine(url: str) -> Iterator[Engine]:
    eng = make_engine(url)
    yield eng
    eng.dispose()


def schema_diff(engine: Engine) -> list[Any]:
    with engine.connect() as conn:
        return list(compare_metadata(MigrationContext.configure(conn, opts={"compare_type": True}), Base.metadata))


def revision(engine: Engine) -> str | None:
    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def test_one_head_and_migrated_schema_equals_the_models(engine: Engine) -> None:
    assert len(ScriptDirectory.from_config(alembic_config()).get_heads()) == 1
    assert migrate(engine) == HEAD and revision(engine) == HEAD
    assert schema_diff(engine) == []
    assert set(inspect(engine).get_table_names()) == {*Base.metadata.tables, "alembic_version"}
    assert migrate(engine) == HEAD  # again: nothing to do


def test_create_all_database_is_stamped_and_keeps_its_rows(engine: Engine) -> None:
    # The old start-up: create_all, as an older version made it (without the tables added later), with data. The
    # stamp is at INITIAL_REVISION, then the later revisions (none yet) run.
    assert ScriptDirectory.from_config(alembic_config()).get_revision(INITIAL_REVISION).down_revision is None
    Base.metadata.create_all(engine, tables=[t for name, t in Base.metadata.tables.items() if name != "worker_nodes"])
    with engine.begin() as conn:
        conn.execute(insert(models.Tenant).values(id="ten_1", name="old", created_at=models.now()))
    assert revision(engine) is None
    assert migrate(engine) == HEAD
    with engine.connect() as conn:
        assert conn.execute(text("SELECT name FROM tenants")).scalars().all() == ["old"]
        stamped = conn.execute(text("SELECT version_num FROM alembic_version")).scalars().all()
    assert stamped == [HEAD]
    assert schema_diff(engine) == []


def test_processes_migrating_at_once_all_succeed(url: str) -> None:
    """Six connections migrate an empty database at the same moment (the API and workers starting together):
    the migration lock lets one create the schema while the others wait, then find it done."""
    errors: list[BaseException] = []
    results: list[str] = []
    barrier = threading.Barrier(6)

    def one() -> None:
        eng = make_engine(url)
        try:
            with eng.connect():
                pass  # connected before the barrier, so the migrations themselves race
            barrier.wait()
            results.append(migrate(eng))
        except BaseException as exc:
            errors.append(exc)
        finally:
            eng.dispose()

    threads = [threading.Thread(target=one) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors, errors
    assert results == [HEAD] * 6
    eng = make_engine(url)
    try:
        assert schema_diff(eng) == []
    finally:
        eng.dispose()


def test_get_engine_migrates_at_start(url: str, tmp_path: Path) -> None:
    """A fresh process with NEUMATEX_DATABASE_URL set: its first session finds the schema at head."""
    code = ("from sqlalchemy import text\nfrom services.core.db import session_scope\n"
            "with session_scope() as s: print(s.execute(text('SELECT version_num FROM alembic_version')).scalar())")
    env = {"PATH": "/usr/bin:/bin", "NEUMATEX_DATABASE_URL": url, "NEUMATEX_DATA_DIR": str(tmp_path / "data")}
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == [HEAD]
