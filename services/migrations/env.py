"""Alembic environment of the job service (docs/service.md, "Database").

The service runs it in code (services.core.db.migrate) and hands over its own connection in
`config.attributes["connection"]`, already inside a transaction that holds the migration lock; alembic's command
line (services/migrations/alembic.ini) gets none, and connects to the service's configured database instead
(NEUMATEX_DATABASE_URL, default SQLite under NEUMATEX_DATA_DIR).
"""

from __future__ import annotations

from alembic import context
from sqlalchemy import Connection

from services import models  # noqa: F401  (registers the tables on Base.metadata)
from services.core.base import Base

config = context.config


def run(connection: Connection) -> None:
    # render_as_batch: SQLite alters a table by copying it (ALTER TABLE there cannot drop or change columns).
    context.configure(connection=connection, target_metadata=Base.metadata, compare_type=True,
                      render_as_batch=connection.dialect.name == "sqlite")  # fmt: skip
    with context.begin_transaction():
        context.run_migrations()


def main() -> None:
    if context.is_offline_mode():
        raise SystemExit("offline (--sql) migrations are not supported: run them against a database")
    connection = config.attributes.get("connection")
    if connection is not None:
        run(connection)
        return
    from services.core.db import configured_url, make_engine, migration_lock

    engine = make_engine(configured_url())
    try:
        with engine.begin() as conn, migration_lock(conn):
            run(conn)
    finally:
        engine.dispose()


main()
