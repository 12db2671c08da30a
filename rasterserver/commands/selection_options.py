"""The selection options of ``process`` (uids, --all, --patient, --since, --before, --station,
--from-plugin) as reusable Typer annotations, for the commands that select acquisitions the
same way (``diff``, ``reprocess``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

import typer

from rasterserver.commands.common import parse_datetime
from rasterserver.errors import InputError

if TYPE_CHECKING:
    from rasterserver.processing_jobs import Selection

Uids = Annotated[
    list[str] | None,
    typer.Argument(help="Acquisition uids (see `rasterserver list`).", show_default=False),
]
Every = Annotated[
    bool, typer.Option("--all", help="Every acquisition with a raster frame (narrowed by the "
                       "options below).")
]
Patient = Annotated[str | None, typer.Option(help="Acquisitions of this patient.",
                                             show_default=False)]
Since = Annotated[
    str | None,
    typer.Option(metavar="TIME", help="Acquired at or after this time (ISO 8601 with zone, "
                 "or a date: 00:00 UTC).", show_default=False),
]
Before = Annotated[
    str | None, typer.Option(metavar="TIME", help="Acquired before this time.",
                             show_default=False)
]
StationName = Annotated[str | None, typer.Option("--station", help="Taken at this station.",
                                                 show_default=False)]
FromPlugin = Annotated[
    str | None,
    typer.Option(metavar="PLUGIN[@VERSION]", help="Whose stored results came from this plugin "
                 "(of this algorithm version), e.g. peaks.first-moment@3.", show_default=False),
]


def selection(
    uids: list[str] | None, every: bool, patient: str | None, since: str | None,
    before: str | None, station: str | None, from_plugin: str | None, *,
    default_all: bool = False,
) -> Selection:
    """The :class:`~rasterserver.processing_jobs.Selection` the options ask for.

    Parameters
    ----------
    default_all : bool
        Select every acquisition when nothing is named or filtered (``diff``); otherwise
        that is refused (exit 2), as ``process`` does.

    Raises
    ------
    InputError
        A malformed time or ``--from-plugin``, or nothing selected.
    """
    from rasterserver.processing_jobs import Selection

    plugin, _, version = (from_plugin or "").partition("@")
    if from_plugin is not None and (not plugin.strip() or (version == "" and "@" in from_plugin)):
        raise InputError(f"--from-plugin {from_plugin!r}: expected PLUGIN or PLUGIN@VERSION")
    chosen = Selection(
        uids=tuple(uids or ()), all=every, patient=patient,
        since=parse_datetime(since, "--since"), before=parse_datetime(before, "--before"),
        station=station, plugin=plugin.strip() or None, plugin_version=version.strip() or None,
    )
    if not chosen.uids and not chosen.filtered:
        if default_all:
            return Selection(uids=(), all=True)
        raise InputError("name acquisitions, or use --all, --patient, --since/--before, "
                         "--station or --from-plugin")
    return chosen
