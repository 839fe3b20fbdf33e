"""The declarative base of the service's tables (services/models.py), on its own so that the models and the engine
(services/core/db.py, which migrates to them) need not import each other."""

from __future__ import annotations

from sqlalchemy.orm import DeclarativeBase


class Base(DeclarativeBase):
    pass
