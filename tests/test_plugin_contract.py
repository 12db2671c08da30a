"""The plugin contract, checked for every stage in the ``rasterserver.stages`` group.

Like datasette's plugin tests: whatever plugins are installed (the built-ins arrive through
the same entry points as any package's), each one gets one test case here. A third-party
fixture plugin, installed from ``tmp_path`` through real entry-point metadata, is always
checked too, so the contract itself is exercised even while no stage is installed.
"""

from __future__ import annotations

import json
import sys
import textwrap
from collections.abc import Iterator
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel, ValidationError

from rasterserver.records import Record, record_type
from rasterserver.registry import STAGE_GROUP, Registry
from rasterserver.stage import Stage, params_hash, stage_problems

FIXTURE_PLUGIN = "contract.invert"

FIXTURE_MODULE = '''
"""A well-behaved third-party stage: the contract must accept it."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from rasterserver.records import Image
from rasterserver.stage import Stage, StageContext, StageParams


class InvertImage(Stage[Image, Image]):
    """Invert grey values relative to the dtype's maximum."""

    name = "contract.invert"
    stage = "invert"
    version = "1.0"
    input_type = Image
    output_type = Image

    class Params(StageParams):
        role: str = Field("inverted", description="Role of the output image.")
        scale: tuple[float, float] = Field((1.0, 1.0), description="A tuple, to test JSON.")

    def run(self, data: Image, params: Params, context: StageContext) -> Image:
        return Image(np.iinfo(data.pixels.dtype).max - data.pixels, role=params.role)


class Undocumented(InvertImage):
    name = "contract.undocumented"
'''

INSTALLED = sorted({ep.name for ep in entry_points(group=STAGE_GROUP)})


def contract_violations(stage: Stage[Any, Any]) -> list[str]:
    """Return what ``stage`` gets wrong; empty when it honours the plugin contract."""
    problems = stage_problems(stage)
    cls = type(stage)
    # The class's own docstring: the inherited one from a base class says nothing about it.
    if not (cls.__doc__ or "").strip():
        problems.append(f"{cls.__qualname__} has no docstring")
    if problems:
        return problems  # the checks below rely on the declarations being there
    for attr in ("input_type", "output_type"):
        record_cls: type[Record] = getattr(stage, attr)
        if record_type(record_cls.kind) is not record_cls:
            problems.append(f"{attr} {record_cls.__name__} is not the registered record class")
    params_cls: type[BaseModel] = stage.Params
    defaults = params_cls()
    if params_hash(params_cls()) != params_hash(defaults):
        problems.append("params_hash of the defaults is not stable")
    # Parameters arrive as JSON (HTTP, stored provenance): they must survive the trip.
    as_json = json.loads(json.dumps(defaults.model_dump(mode="json")))
    try:
        again = params_cls.model_validate(as_json)
    except ValidationError as exc:
        problems.append(f"default Params do not survive a JSON round trip: {exc}")
    else:
        if params_hash(again) != params_hash(defaults):
            problems.append("default Params change in a JSON round trip")
    try:
        hash(defaults)
    except TypeError as exc:
        problems.append(f"Params are not hashable: {exc}")
    try:
        params_cls.model_validate({"__surely_not_a_parameter__": 1})
    except ValidationError:
        pass
    else:
        problems.append("Params accept unknown keys")
    return problems


@pytest.fixture
def contract_plugins(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """Install the fixture distribution ``contract-plugin 1.0`` through entry-point metadata."""
    (tmp_path / "contract_plugin.py").write_text(textwrap.dedent(FIXTURE_MODULE))
    info = tmp_path / "contract_plugin-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: contract-plugin\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        f"[{STAGE_GROUP}]\n"
        f"{FIXTURE_PLUGIN} = contract_plugin:InvertImage\n"
        "contract.undocumented = contract_plugin:Undocumented\n"
    )
    sys.modules.pop("contract_plugin", None)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    sys.modules.pop("contract_plugin", None)


@pytest.mark.parametrize(
    "name",
    [*INSTALLED, pytest.param(FIXTURE_PLUGIN, id=f"{FIXTURE_PLUGIN} (test fixture)")],
)
def test_plugin_honours_the_contract(name: str, request: pytest.FixtureRequest) -> None:
    if name == FIXTURE_PLUGIN:
        request.getfixturevalue("contract_plugins")
    registry = Registry().discover()
    info = registry.info(name)
    assert info.ok, f"{name} is broken: {info.error}"
    assert info.package and info.package_version, f"{name}: no distribution metadata"
    stage = registry.get(name)
    assert contract_violations(stage) == []


def test_installed_plugins_are_all_checked() -> None:
    # Guards the parametrisation: every entry point of the group is one case above.
    assert sorted({ep.name for ep in entry_points(group=STAGE_GROUP)}) == INSTALLED


def test_the_contract_catches_a_missing_docstring(contract_plugins: Path) -> None:
    stage = Registry().discover().get("contract.undocumented")
    assert contract_violations(stage) == ["Undocumented has no docstring"]
