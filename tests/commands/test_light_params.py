"""The CLI's light option coercion gives what Typer's own gives, or leaves the case to it."""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

import pytest
import typer
import typer.main
from typer._click.exceptions import BadParameter

from rasterserver.cli import _flow_help
from rasterserver.commands import COMMANDS, command_module, command_modules
from rasterserver.commands.light_params import _LightRuntimeParam, lighten


def _params(*, light: bool) -> dict[str, Any]:
    """The parameters of a small command as Typer builds them (each plain kind, and a path
    with a check), lightened or not."""
    scratch = typer.Typer(add_completion=False)

    @scratch.command()
    def run(
        name: str = "x",
        count: int = typer.Option(3, min=1, max=10),
        free: int = 0,
        flag: bool = False,
        where: Path = typer.Option(Path(".")),
        must: Path = typer.Option(Path("."), exists=True),
    ) -> None:
        """A command."""

    built = typer.main.get_command(scratch)
    if light:
        lighten(built)
    return {p.name: p for p in built.params}


def _coerces(param: Any, value: Any) -> Any:
    try:
        return param.get_runtime_param().coerce(value, param=param, ctx=None)
    except BadParameter as exc:
        return ("error", exc.message)


CASES = [
    ("name", "abc"), ("name", ""), ("name", None), ("count", "5"), ("count", 3),
    ("count", "0"), ("count", "11"), ("count", "-2"), ("count", "x"), ("count", "05"),
    ("count", " 5"), ("free", "-12"), ("free", "1_000"), ("free", "+4"), ("flag", True),
    ("flag", False), ("flag", "yes"), ("where", "nowhere/at/all"), ("where", "."),
    ("where", ""), ("must", "."), ("must", "nowhere/at/all"),
]


@pytest.mark.parametrize(("name", "value"), CASES)
def test_light_coercion_agrees_with_typer(name: str, value: Any) -> None:
    expected = _coerces(_params(light=False)[name], value)
    light = _params(light=True)[name]
    assert isinstance(light.get_runtime_param(), _LightRuntimeParam) == (name != "must")
    got = _coerces(light, value)
    assert got == expected and type(got) is type(expected)


def test_lighten_skips_what_is_not_plain() -> None:
    scratch = typer.Typer(add_completion=False)

    @scratch.command()
    def run(must: Path = typer.Option(Path("."), exists=True), name: str = "x") -> None:
        """A command."""

    built = typer.main.get_command(scratch)
    lighten(built)
    kinds = {p.name: type(p._runtime_param).__name__ for p in built.params}
    assert kinds == {"must": "NoneType", "name": "_LightRuntimeParam"}


def test_the_command_table_agrees_with_the_modules() -> None:
    """Each row of COMMANDS names the module registering the command and its first paragraph
    of help; every command the modules register has its row, in the order --help had."""
    scratch = typer.Typer()
    for module in command_modules():
        module.register(scratch)
    _flow_help(scratch)
    built = typer.main.get_group(scratch).commands
    assert list(built) == list(COMMANDS)
    for name, command in built.items():
        first = inspect.cleandoc(command.short_help or command.help or "").split("\n\n")[0]
        assert COMMANDS[name].help == first, name
        own = typer.Typer()
        command_module(name).register(own)
        assert name in typer.main.get_group(own).commands
