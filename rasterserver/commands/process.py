"""``rasterserver process``: run the stage chain over archived acquisitions."""

from __future__ import annotations

import json
from typing import Annotated

import typer

from rasterserver.commands.common import open_archive, progress_bar
from rasterserver.errors import InputError, RasterServerError
from rasterserver.jobs import JobOutcome, process_many
from rasterserver.pipeline import DEFAULT_TARGETS, Pipeline, parse_stage_options, resolve_chain


class ProcessingFailedError(RasterServerError):
    """Some acquisitions of a ``process`` command failed; each is listed with its reason.

    The exit code says what kind of failure it was when they are all of one kind (3 for
    unknown acquisitions or a missing calibration, 2 for frames that do not fit), else 1.
    """

    def __init__(self, message: str, *, exit_code: int) -> None:
        super().__init__(message)
        self.exit_code = exit_code

    @staticmethod
    def code_of(failed: list[JobOutcome]) -> int:
        """The failures' common exit code, or 1 when they differ."""
        codes = {o.exit_code or 1 for o in failed}
        return codes.pop() if len(codes) == 1 else 1


def parse_calibration(text: str | None) -> tuple[str, int | None] | None:
    """Parse ``STATION:VERSION`` (or ``STATION`` for its newest calibration)."""
    if text is None:
        return None
    usage = f"--calibration {text!r}: expected STATION:VERSION, e.g. clinic-1:3"
    station, sep, version = text.rpartition(":")
    if not sep:
        return text.strip(), None
    try:
        number = int(version)
    except ValueError:
        raise InputError(usage) from None
    if not station.strip() or number < 1:
        raise InputError(usage)
    return station.strip(), number


def process(
    ctx: typer.Context,
    uids: Annotated[
        list[str] | None,
        typer.Argument(help="Acquisition uids (see `rasterserver list`).", show_default=False),
    ] = None,
    patient: Annotated[str | None, typer.Option(help="All acquisitions of this patient.")] = None,
    all_unprocessed: Annotated[
        bool,
        typer.Option(
            "--all-unprocessed",
            help="Every acquisition (of --patient, if given) without a successful run.",
        ),
    ] = False,
    stage: Annotated[
        list[str] | None,
        typer.Option(help="KIND=PLUGIN: use another plugin for a stage; repeatable."),
    ] = None,
    calibration: Annotated[
        str | None,
        typer.Option(
            help="STATION:VERSION (or STATION for its newest): use this calibration instead of "
            "the one attached at ingest; it must be of the acquisition's station.",
        ),
    ] = None,
    until: Annotated[
        list[str] | None,
        typer.Option(
            metavar="KIND",
            help="Last stage kind to run; repeatable (default: mesh and analysis). Any kind of "
            "the stage graph: see `rasterserver plugins --graph`.",
            show_default=False,
        ),
    ] = None,
    dask: Annotated[
        bool,
        typer.Option(
            "--dask/--no-dask",
            help="Compute on Dask: RASTERSERVER_DASK_SCHEDULER if set, else a local cluster.",
        ),
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per line.")] = False,
) -> None:
    """Process acquisitions: every stage's result is stored with its provenance.

    Stored results of the same computation (same frame, plugins, versions, parameters and
    calibration) are reused, not recomputed; other plugins, parameters or calibrations add
    results beside the old ones. An unknown plugin, stage or calibration is refused before
    any work. If an acquisition fails, the others are still processed and each failure is
    listed; the exit code is the failures' (3 for an unknown acquisition, 2 for a frame that
    does not fit its calibration, ...) when they agree, else 1.

    Runs that a killed process left "running" are marked interrupted when their acquisition
    is processed again (and see `rasterserver runs reap`).
    """
    chain = parse_stage_options(stage or [])
    wanted = parse_calibration(calibration)
    targets = list(until or DEFAULT_TARGETS)
    for target in targets:
        # a misspelt plugin or stage is the request's fault, not each acquisition's: refuse
        # it once (exit 3 or 2) before any work
        resolve_chain(chain, until=target)
    with open_archive(ctx) as archive:
        if wanted is not None:
            archive.calibration(*wanted)  # an unknown station or version: exit 3, before work
        pipeline = Pipeline(archive)
        selected = list(uids or [])
        if all_unprocessed:
            selected += pipeline.unprocessed(patient=patient)
        elif patient is not None:
            selected += [
                a.uid for a in reversed(archive.acquisitions(patient=patient, limit=1_000_000))
            ]
        if not selected:
            if uids or patient or all_unprocessed:
                typer.echo("nothing to process", err=True)
                return
            raise InputError("name acquisitions, or use --patient or --all-unprocessed")
        selected = list(dict.fromkeys(selected))  # each once, in the order given
        with progress_bar("processing") as progress:
            outcomes = process_many(
                archive,
                selected,
                chain=chain,
                calibration=wanted,
                until=targets,
                dask=dask,
                progress=progress,
            )
    for outcome in outcomes:
        if as_json:
            typer.echo(json.dumps(outcome.to_dict()))
        elif outcome.status == "done":
            note = f"; {outcome.reason}" if outcome.reason else ""
            typer.echo(
                f"{outcome.uid}\tdone\t{outcome.computed} computed, {outcome.reused} reused{note}"
            )
        else:
            typer.echo(f"{outcome.uid}\tfailed\t{outcome.error}")
    failed = [o for o in outcomes if o.status == "failed"]
    if failed:
        raise ProcessingFailedError(
            f"{len(failed)} of {len(outcomes)} acquisition(s) failed, see above",
            exit_code=ProcessingFailedError.code_of(failed),
        )


def register(app: typer.Typer) -> None:
    """Add the ``process`` command to ``app``."""
    app.command("process")(process)
