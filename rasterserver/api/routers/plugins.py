"""``/plugins``: the stage plugins the registry found."""

from __future__ import annotations

from typing import Annotated

from fastapi import Query

from rasterserver.api.deps import PageDep, protected_router
from rasterserver.registry import PluginInfo, get_registry

router = protected_router("plugins")


@router.get("/plugins", name="list_plugins", response_model=list[PluginInfo])
def list_plugins(
    page: PageDep,
    stage: Annotated[str | None, Query(max_length=64, description="Stage kind.")] = None,
) -> list[PluginInfo]:
    """Every installed stage plugin: name, stage, version, package, status."""
    infos = get_registry().infos(stage) if stage else get_registry().infos()
    return list(infos)[page.offset: page.offset + page.limit]
