"""The ``rasterserver`` command line: thin Typer commands over the services.

Each command group lives in its own module under :mod:`rasterserver.commands` and adds itself
to an app through a ``register(app)`` function. The root group here is lazy
(:class:`LazyGroup`): it knows the commands' names and one-line help from
:data:`rasterserver.commands.COMMANDS` and imports a command's module, and lets Typer build
its options, only when that command runs or shows its own help. This file also turns
:class:`~rasterserver.errors.RasterServerError` into a message and an exit code.
"""

from __future__ import annotations

import inspect
import logging
import re
import sys
from collections.abc import Iterator, MutableMapping
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
import typer.main
from typer.core import TyperCommand, TyperGroup
from typer.models import CommandInfo

if TYPE_CHECKING:
    # the context type of the click that Typer vendors, which its group methods take
    from typer._click import Context as ClickContext

from rasterserver.commands import COMMANDS, command_module
from rasterserver.commands.light_params import lighten
from rasterserver.config import Settings
from rasterserver.errors import InputError, RasterServerError, UnavailableError
from rasterserver.interrupts import install as install_interrupt_handler
from rasterserver.interrupts import interrupted

log = logging.getLogger(__name__)

class _LazyCommands(MutableMapping[str, Any]):
    """The root's commands by name: a command module is imported at its first look-up.

    Click and Typer read a group's ``commands`` mapping (to resolve, list and suggest
    commands); this one has every name of :data:`~rasterserver.commands.COMMANDS` as a key
    from the start, and builds the click commands of a module (all it registers, in a
    scratch Typer app of its own) when one of them is first asked for.
    """

    def __init__(self, given: MutableMapping[str, Any]) -> None:
        self._loaded: dict[str, Any] = dict(given)

    def _load(self, name: str) -> None:
        if name in self._loaded or name not in COMMANDS:
            return
        scratch = typer.Typer()
        command_module(name).register(scratch)
        _flow_help(scratch)
        for built_name, built in typer.main.get_group(scratch).commands.items():
            lighten(built)
            self._loaded.setdefault(built_name, built)

    def __getitem__(self, name: str) -> Any:
        self._load(name)
        return self._loaded[name]

    def __setitem__(self, name: str, command: Any) -> None:
        self._loaded[name] = command

    def __delitem__(self, name: str) -> None:
        del self._loaded[name]

    def __iter__(self) -> Iterator[str]:
        yield from COMMANDS
        yield from (name for name in self._loaded if name not in COMMANDS)

    def __len__(self) -> int:
        return len(COMMANDS) + sum(name not in COMMANDS for name in self._loaded)

    def __contains__(self, name: object) -> bool:
        return name in COMMANDS or name in self._loaded


class LazyGroup(TyperGroup):
    """The root command group: builds only the command being run.

    Building every command's options at each start cost about 0.08 s of CPU (and imported
    every command module); now ``rasterserver list`` builds ``list`` alone. The group's own
    ``--help`` lists every command from the table's one-line help, importing none of them;
    ``rasterserver COMMAND --help`` builds that command as usual.
    """

    def __init__(self, **attrs: Any) -> None:
        super().__init__(**attrs)
        lighten(self)  # before the commands turn lazy: the root's own options only
        self.commands = _LazyCommands(self.commands)
        self._listing = False

    def get_command(self, ctx: ClickContext, cmd_name: str) -> Any:
        if self._listing and cmd_name in COMMANDS:
            # the command list of --help: the table's line stands in for the command
            return TyperCommand(name=cmd_name, help=COMMANDS[cmd_name].help)
        return super().get_command(ctx, cmd_name)

    def list_commands(self, ctx: ClickContext) -> list[str]:
        # Typer's own walks the mapping's items, which would build every command
        return list(self.commands)

    def format_help(self, ctx: ClickContext, formatter: Any) -> None:
        self._listing = True
        try:
            super().format_help(ctx, formatter)
        finally:
            self._listing = False


app = typer.Typer(
    cls=LazyGroup,
    name="rasterserver",
    help=(
        "Archive and process video rasterstereographs: ingest camera frames into a write-once "
        "HDF5 archive with an SQL catalogue, verify it, and run the reconstruction pipeline.\n\n"
        "Settings come from options or the environment: RASTERSERVER_ARCHIVE (archive folder, "
        "default ./archive) and RASTERSERVER_DATABASE_URL (default: SQLite inside the archive)."
    ),
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)


def _version(value: bool) -> None:
    if value:
        # read here, not at import: the version comes from the installed metadata, which
        # every other command would pay for at start
        from rasterserver import __version__

        typer.echo(f"rasterserver {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    ctx: typer.Context,
    archive: Annotated[
        Path | None,
        typer.Option(help="Archive folder (overrides RASTERSERVER_ARCHIVE).", show_default=False),
    ] = None,
    database_url: Annotated[
        str | None,
        typer.Option(
            help="SQLAlchemy URL of the catalogue (overrides RASTERSERVER_DATABASE_URL).",
            show_default=False,
        ),
    ] = None,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log progress details.")] = False,
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Show the version.")
    ] = False,
) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    ctx.obj = Settings.from_env(archive=archive, database_url=database_url)


#: A line that starts a list item or is indented: its line break is meant, not a source wrap.
_MEANT_BREAK = re.compile(r"\s|[-*\u2022] |\d+[.)] ")


def flowing(text: str) -> str:
    """Un-wrap the paragraphs of a help text: each becomes one line, for the terminal to wrap.

    Docstrings are hard-wrapped to the source's line length; Typer keeps those breaks, so a
    terminal of another width shows ragged lines. Paragraphs stay apart (blank lines), and a
    paragraph holding a list item or an indented line (or starting with Click's ``\\b``
    marker) is kept as written.

    Parameters
    ----------
    text : str
        A help text or docstring (indentation is removed first).

    Returns
    -------
    str
    """
    paragraphs = re.split(r"\n[ \t]*\n", inspect.cleandoc(text).strip())
    flowed = []
    for paragraph in paragraphs:
        lines = paragraph.splitlines()
        if paragraph.startswith("\b") or any(_MEANT_BREAK.match(line) for line in lines[1:]):
            flowed.append(paragraph)
        else:
            flowed.append(" ".join(line.strip() for line in lines))
    return "\n\n".join(flowed)


def _flow_help(group: typer.Typer) -> None:
    """Give every command of ``group`` (and of its sub-groups) flowing help text."""
    if isinstance(group.info.help, str):
        group.info.help = flowing(group.info.help)
    for command in group.registered_commands:
        _flow_command(command)
    for sub in group.registered_groups:
        sub.help = flowing(typer.main.solve_typer_info_help(sub))
        if sub.typer_instance is not None:
            _flow_help(sub.typer_instance)


def _flow_command(command: CommandInfo) -> None:
    # Typer falls back on the docstring when no help is given; do the same, then un-wrap
    text = command.help if command.help is not None else inspect.getdoc(command.callback)
    if text:
        command.help = flowing(text)


# the root's own help; each command's is made to flow when the lazy group builds it
_flow_help(app)


def main(argv: list[str] | None = None) -> int:
    """Run the CLI and return its exit code.

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name; defaults to ``sys.argv[1:]``.

    Returns
    -------
    int
        0 on success, the error's ``exit_code`` for a :class:`RasterServerError`; 2 for
        a catalogue URL that cannot be parsed, 8 when the catalogue cannot be reached or the
        archive folder cannot be used, 1 for anything else (a bug, said as such).
    """
    try:
        # Standalone mode lets Typer print usage errors and --help itself; it ends with
        # SystemExit, whose code is the exit code.
        app(args=argv, prog_name="rasterserver", standalone_mode=True)
    except SystemExit as exc:
        if exc.code is None or isinstance(exc.code, int):
            # Ctrl-C whose KeyboardInterrupt a finaliser swallowed still ends with 130
            return exc.code or (_interrupted() if interrupted() else 0)
        typer.echo(str(exc.code), err=True)
        return 1
    except RasterServerError as exc:
        typer.echo(f"error: {exc}", err=True)
        return exc.exit_code
    except KeyboardInterrupt:
        return _interrupted()
    except Exception as exc:
        # No traceback reaches a user: what the environment refused gets its sentence and
        # code; anything else is a bug, said as such (the traceback with --verbose).
        known = _environment_error(exc)
        if known is not None:
            typer.echo(f"error: {known}", err=True)
            return known.exit_code
        log.info("unexpected failure", exc_info=exc)
        typer.echo(
            f"error: unexpected failure, a bug in rasterserver or a plugin: {_one_line(exc)} "
            "(run with --verbose for the traceback)",
            err=True,
        )
        return 1
    return 0


def _interrupted() -> int:
    typer.echo("interrupted", err=True)
    return 130  # the shell's code for a command stopped by Ctrl-C (SIGINT)


def _one_line(exc: BaseException) -> str:
    # SQLAlchemy is imported on this error path only: `--help` and light commands start
    # without it
    import sqlalchemy.exc

    if isinstance(exc, sqlalchemy.exc.StatementError) and exc.orig is not None:
        exc = exc.orig  # its own text, without the SQL and parameters (patient data)
    first = (str(exc).strip().splitlines() or [""])[0]
    return f"{type(exc).__name__}: {first}" if first else type(exc).__name__


def _environment_error(exc: Exception) -> RasterServerError | None:
    """The error a user can act on that ``exc`` stands for, or None for a bug.

    The catalogue's URL (password hidden) or the file the operating system names is given,
    with its reason; never the SQL or its parameters, which may hold patient data.
    """
    from rasterserver.extras import missing_extra

    extra = missing_extra(exc)  # an optional extra not installed: name it
    if extra is not None:
        return extra
    import sqlalchemy.exc

    if isinstance(exc, sqlalchemy.exc.ArgumentError):  # incl. an unknown dialect
        return InputError(f"the catalogue URL is not usable: {_one_line(exc)}")
    if isinstance(exc, sqlalchemy.exc.OperationalError | sqlalchemy.exc.InterfaceError):
        return UnavailableError(f"cannot use the catalogue: {_one_line(exc)}")
    if isinstance(exc, OSError) and exc.filename is not None:
        return UnavailableError(f"cannot use {exc.filename}: {exc.strerror or exc}")
    return None


def run() -> None:
    """Console-script entry point."""
    install_interrupt_handler()
    sys.exit(main())
