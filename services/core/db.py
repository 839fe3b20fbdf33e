"""SQLAlchemy engine, sessions and migrations. PostgreSQL is the deployed database (NEUMATEX_DATABASE_URL=
postgresql+psycopg://...); SQLite, the embedded default, runs in WAL mode with a busy timeout so the API, the workers
and the reaper can write concurrently. The schema is made by the Alembic migrations in services/migrations, brought
to the newest revision when a process first opens the database (docs/service.md, "Database")."""

from __future__ import annotations

import fcntl
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import Connection, Engine, create_engine, event, inspect, text
from sqlalchemy.orm import Session, sessionmaker

from services.core.base import Base
from services.core.config import get_settings

if TYPE_CHECKING:
    from alembic.config import Config

log = logging.getLogger(__name__)

MIGRATIONS = Path(__file__).resolve().parents[1] / "migrations"  # alembic's script_location, whatever the cwd
INITIAL_REVISION = "0001"  # the schema that Base.metadata.create_all made before there were migrations
# The key of the PostgreSQL advisory lock held while migrating (any constant bigint: "NMXD" then 1).
PG_MIGRATION_LOCK = 0x4E4D5844_00000001


def make_engine(url: str) -> Engine:
    if url.startswith("sqlite"):
        # A pool larger than the API's thread pool (40): a smaller one can deadlock FastAPI, whose sync dependencies
        # give their connection back on a thread of that same pool.
        engine = create_engine(url, connect_args={"timeout": 30, "check_same_thread": False}, pool_size=48,
                               max_overflow=16, pool_pre_ping=False)  # fmt: skip

        @event.listens_for(engine, "connect")
        def _pragmas(conn: Any, _record: Any) -> None:
            cur = conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA synchronous=NORMAL")
            cur.execute("PRAGMA busy_timeout=30000")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.close()

        return engine
    return create_engine(url, pool_pre_ping=True, pool_size=48, max_overflow=16)


def configured_url() -> str:
    """The settings' database URL (NEUMATEX_DATABASE_URL, default SQLite in the data folder, which is made)."""
    settings = get_settings()
    if settings.db_url.startswith("sqlite:///"):
        settings.data_dir.mkdir(parents=True, exist_ok=True)
    return settings.db_url


def alembic_config(connection: Connection | None = None) -> Config:
    """Alembic's configuration for services/migrations, built in code (no alembic.ini needed). With `connection`,
    the migrations run on it (services/migrations/env.py); without, on the configured database."""
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    if connection is not None:
        cfg.attributes["connection"] = connection
    return cfg


@contextmanager
def migration_lock(conn: Connection) -> Iterator[None]:
    """Held while migrating, so that processes starting at once (the API, workers, the CLI) migrate one after the
    other and the later ones find the schema done. `conn` must be inside a transaction (Engine.begin()).

    PostgreSQL: a transaction-level advisory lock (released at commit or rollback, so also by a crashed process;
    it works through transaction-mode poolers too), and the DDL commits with the version row. SQLite: an exclusive
    flock on `<database>.migrate-lock` next to the file (SQLite databases are on one machine), then BEGIN IMMEDIATE,
    which makes the DDL and the version row one transaction."""
    dialect = conn.dialect.name
    if dialect == "postgresql":
        conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": PG_MIGRATION_LOCK})
        yield
        return
    database = conn.engine.url.database if dialect == "sqlite" else None
    if not database or database == ":memory:" or database.startswith("file:"):
        yield  # in-memory SQLite (one process) or another database: nothing to serialise against
        return
    with open(f"{database}.migrate-lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            # pysqlite starts its own transaction only before DML; this one takes the write lock now and keeps the
            # DDL in it (pysqlite sees the open transaction and commits it at Connection.commit()).
            conn.exec_driver_sql("BEGIN IMMEDIATE")
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def upgrade(conn: Connection) -> str:
    """Migrate the database behind `conn` (holding migration_lock) to the newest revision; return it.

    A database made by the old `create_all` (the service's tables but no alembic version) is stamped at
    INITIAL_REVISION: that revision then creates only the tables it lacks, as create_all would have, and records
    itself, and the later revisions run as usual."""
    from alembic import command
    from alembic.script import ScriptDirectory

    from services import models  # noqa: F401  (registers the tables)

    def current() -> str | None:  # read directly: alembic's MigrationContext logs at INFO on every start
        if not inspect(conn).has_table("alembic_version"):
            return None
        return conn.execute(text("SELECT version_num FROM alembic_version")).scalar()

    head = ScriptDirectory.from_config(alembic_config()).get_current_head()
    at = current()
    if at is not None and at == head:
        return at  # the usual start: nothing to do
    ours = set(inspect(conn).get_table_names()) & set(Base.metadata.tables)
    if at is None and ours:
        log.warning("database without migrations (made by create_all), %d of the service's tables present: stamping "
                    "it at revision %s", len(ours), INITIAL_REVISION)  # fmt: skip
        legacy = alembic_config(conn)
        legacy.attributes["skip_existing_tables"] = True  # read by the initial revision
        command.upgrade(legacy, INITIAL_REVISION)
    command.upgrade(alembic_config(conn), "head")
    at = current()
    if at is None or at != head:
        raise RuntimeError(f"the database is at revision {at} after migrating, not at the head {head}")
    return at


def migrate(url: str | Engine | None = None) -> str:
    """Bring the database (an engine, a URL, or by default the configured one) to the newest migration, safely while
    other processes do the same; return the revision it is at. `python -m services migrate` runs this."""
    engine = url if isinstance(url, Engine) else make_engine(url or configured_url())
    try:
        with engine.begin() as conn, migration_lock(conn):
            return upgrade(conn)
    finally:
        if engine is not url:
            engine.dispose()


@lru_cache
def get_engine() -> Engine:
    """The process's engine, on a database migrated to the newest revision."""
    engine = make_engine(configured_url())
    migrate(engine)
    return engine


@lru_cache
def _factory() -> sessionmaker[Session]:
    return sessionmaker(get_engine(), expire_on_commit=False)


@contextmanager
def session_scope() -> Iterator[Session]:
    """A session committed on success and rolled back on error."""
    s = _factory()()
    try:
        yield s
        s.commit()
    except BaseException:
        s.rollback()
        raise
    finally:
        s.close()


def get_session() -> Iterator[Session]:
    """FastAPI dependency."""
    with session_scope() as s:
        yield s
