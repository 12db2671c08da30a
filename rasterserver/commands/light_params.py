"""Plain option values without Pydantic: the CLI's start need not build a TypeAdapter.

Typer coerces every option value through a Pydantic ``TypeAdapter`` built on first use, also
for a ``str`` or an ``int``; importing Pydantic and building the adapters cost about 0.1 s of
CPU in ``rasterserver list``. :func:`lighten` gives the parameters of a built command a
coercion that handles the plain cases itself (a string, a decimal integer within its bounds,
a path without checks) with the result Typer's would give, and hands everything else (a
choice, a date, a bad value and its error message) to Typer's own coercion.

This leans on Typer's internals (``_TyperParameter._runtime_param``, ``RuntimeParam``); with
a Typer that lacks them, :func:`lighten` leaves the parameters as they are.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

try:
    from typer._coercion import RuntimeParam, build_runtime_param
    from typer.core import _TyperParameter
except ImportError:  # another Typer: its own coercion for everything
    RuntimeParam = None  # type: ignore[assignment,misc]

#: A decimal integer as Pydantic reads one from a string, in the form it surely accepts.
_PLAIN_INT = re.compile(r"-?(0|[1-9][0-9]{0,17})")

#: What a value is when the light coercion leaves it to Typer's.
_DEFER = object()


def _plain(descriptor: Any) -> bool:
    """Whether the parameter's type is one the light coercion may handle."""
    info = descriptor.parameter_info
    if descriptor.file_annotation is not None or info.parser is not None:
        return False
    if descriptor.annotation in (str, int, bool):
        return not getattr(info, "clamp", False)
    if descriptor.annotation is Path:
        # the path checks Typer makes on request (exists, file or folder, resolve, dash)
        return (
            not info.exists and not info.resolve_path and not info.allow_dash
            and info.path_type is None and info.file_okay and info.dir_okay
            and not info.writable
        )
    return False


def _light_value(descriptor: Any, value: Any) -> Any:
    """``value`` coerced as Typer would, or :data:`_DEFER` where the case is not plain."""
    annotation, info = descriptor.annotation, descriptor.parameter_info
    if annotation is str:
        return value if isinstance(value, str) else _DEFER
    if annotation is bool:
        # a flag's value (None, a flag not given, never comes here); "yes": Typer's
        return value if type(value) is bool else _DEFER
    if annotation is int:
        if isinstance(value, str) and _PLAIN_INT.fullmatch(value):
            number = int(value)
        elif type(value) is int:
            number = value
        else:
            return _DEFER
        if (info.min is not None and number < info.min) or (
            info.max is not None and number > info.max
        ):
            return _DEFER  # Typer's own says what the bound is
        return number
    if isinstance(value, str) and value:
        try:
            os.stat(value)
        except OSError:
            return Path(value)  # not there: Typer checks nothing more either
        if info.readable and not os.access(value, os.R_OK):
            return _DEFER
        return Path(value)
    return _DEFER


if RuntimeParam is not None:

    class _LightRuntimeParam(RuntimeParam):
        """Typer's coercion contract: plain cases here, the rest through Typer's own."""

        descriptor: Any

        def __init__(self, descriptor: Any) -> None:
            super().__init__(
                parameter_info=descriptor.parameter_info, annotation=descriptor.annotation
            )
            object.__setattr__(self, "descriptor", descriptor)  # a frozen dataclass

        def _coerce_value(self, value: Any, param: Any, ctx: Any) -> Any:
            light = _light_value(self.descriptor, value)
            if light is not _DEFER:
                return light
            full = build_runtime_param(self.descriptor)
            return full._coerce_value(value, param=param, ctx=ctx)


def lighten(command: Any) -> None:
    """Give the plain parameters of ``command`` (and of its sub-commands) the light coercion.

    Parameters
    ----------
    command : click.Command
        A command or group as Typer built it.
    """
    if RuntimeParam is None:
        return
    for param in command.params:
        _lighten_param(param)
    # the help option is made when the command parses its arguments: lighten it then
    made_by_click = command.get_help_option

    def get_help_option(ctx: Any) -> Any:
        option = made_by_click(ctx)
        if option is not None:
            _lighten_param(option)
        return option

    command.get_help_option = get_help_option
    for sub in getattr(command, "commands", {}).values():
        lighten(sub)


def _lighten_param(param: Any) -> None:
    if (
        isinstance(param, _TyperParameter)
        and param._runtime_param is None
        and not param.multiple
        and param.nargs == 1
        and _plain(param.type_descriptor)
    ):
        param._runtime_param = _LightRuntimeParam(param.type_descriptor)
