"""Helpers shared by the CLI command modules."""

from __future__ import annotations

import typer

from rasterserver.config import Settings


def settings(ctx: typer.Context) -> Settings:
    """Return the settings resolved by the root callback (archive, database URL)."""
    obj = ctx.find_root().obj
    if not isinstance(obj, Settings):  # pragma: no cover - only when a command is run bare
        obj = Settings.from_env()
    return obj
