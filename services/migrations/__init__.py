"""Alembic migrations of the job service's database (services/models.py); run at start by
services.core.db.get_engine() and by `python -m services migrate`. See docs/service.md, "Database"."""
