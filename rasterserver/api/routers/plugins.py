"""``/plugins``: the stage plugins the registry found."""

from __future__ import annotations

from typing import Annotated

from fastapi import Query

from rasterserver.api.deps import PageDep, protected_router
from rasterserver.api.schemas import PluginOut
from rasterserver.registry import get_registry

router = protected_router("plugins")


@router.get("/plugins", name="list_plugins", response_model=list[PluginOut])
def list_plugins(
    page: PageDep,
    stage: Annotated[str | None, Query(max_length=64, description="Stage kind.")] = None,
) -> list[PluginOut]:
    """Every installed stage plugin: name, stage, version, package, status."""
    infos = get_registry().infos(stage) if stage else get_registry().infos()
    return [PluginOut(**i.to_dict()) for i in infos][page.offset: page.offset + page.limit]
