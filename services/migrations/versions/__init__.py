"""Alembic revisions, one module each (alembic skips this file)."""
