"""Alembic migrations of the rasterserver catalogue (installed as ``rasterserver_migrations``).

Run them with ``rasterserver db upgrade``; write a new one with ``rasterserver db revision -m``.
"""
