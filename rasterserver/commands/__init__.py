"""CLI command groups, one module each; every module exposes ``register(app)``.

The CLI builds only the command being run: :data:`COMMANDS` names each top-level command,
the module that registers it and the one-line help ``rasterserver --help`` shows for it, so
listing the commands imports none of the command modules (``rasterserver.cli.LazyGroup``).
Add a command: register it in its module and add its row here, in the order ``--help``
lists it (``tests/commands/test_cli_imports.py`` checks that the table and the modules agree).

A command module is imported when one of its commands runs or shows its own help, and then
Typer builds that module's options only. At module level a command module still imports only
Typer and light modules (errors, config, times): the archive, the pipeline, NumPy, OpenCV,
SciPy, open3d, Dask, the simulator and the HTTP API are imported inside the command
functions that use them, so that ``list --help`` and ``verify --help`` stay light too.
``tests/commands/test_cli_imports.py`` checks what ``--help``, ``list`` and ``verify`` load.
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import NamedTuple


class CommandEntry(NamedTuple):
    """Where a top-level command lives and what ``rasterserver --help`` says of it."""

    module: str
    """The module under :mod:`rasterserver.commands` whose ``register(app)`` adds it."""
    help: str
    """The first paragraph of the command's help, as the command list shows it."""


#: Every top-level command in the order ``--help`` lists it (commands, then groups).
COMMANDS: dict[str, CommandEntry] = {
    "demo": CommandEntry(
        "demo",
        "Run the main job on a simulated patient: render a progressing scoliosis over several "
        "visits, ingest the frames, process them through the stage plugins (mesh and "
        "back-shape analysis), export one mesh and one report page per visit (to "
        "<archive>/exports), verify the archive, and end with the key parameters of every "
        "visit side by side.",
    ),
    "ingest": CommandEntry(
        "ingest",
        "Validate frames and store them as one acquisition (write-once HDF5 + catalogue row).",
    ),
    "list": CommandEntry("listing", "List acquisitions, newest first."),
    "verify": CommandEntry(
        "verify",
        "Re-hash every raw frame and stored result; report missing, corrupt, orphaned and "
        "leftover files.",
    ),
    "plugins": CommandEntry(
        "plugins",
        "List every installed stage plugin: name, stage kind, algorithm version, input and "
        "output record kinds, the package (name and version) that provides it, and its status.",
    ),
    "reconstruct": CommandEntry(
        "reconstruct",
        "Reconstruct the 3-D surface points of one frame and write them as a PLY point cloud.",
    ),
    "analyse": CommandEntry(
        "analyse", "Analyse the shape of a back in camera frames, without an archive."
    ),
    "show": CommandEntry(
        "analyse",
        "Show the back-shape analysis of an archived acquisition: landmarks and parameters.",
    ),
    "compare": CommandEntry(
        "compare",
        "Compare visits of one patient: registration, distance maps, trends, a report.",
    ),
    "process": CommandEntry(
        "process", "Process acquisitions: every stage's result is stored with its provenance."
    ),
    "diff": CommandEntry(
        "diff",
        "Compare the stored results of two chains: which acquisitions changed, and how.",
    ),
    "reprocess": CommandEntry(
        "diff", "Process the selection with a new chain, then report what it changed."
    ),
    "prune": CommandEntry(
        "prune", "Remove derived results that no kept chain needs; a dry run unless --apply."
    ),
    "stats": CommandEntry(
        "prune",
        "Show the archive's size by kind of file, its acquisitions and results, the stored "
        "results per chain (plugins, versions and parameters hashes), and what prune would "
        "free.",
    ),
    "export": CommandEntry(
        "export", "Export the newest stored mesh or point cloud of an acquisition."
    ),
    "serve": CommandEntry(
        "serve",
        "Serve the HTTP API (OpenAPI at /docs); every route but /health needs a bearer token.",
    ),
    "calibrate": CommandEntry(
        "calibrate",
        "Calibrate camera and projector from the control-point frames and store the result "
        "as the station's next calibration version.",
    ),
    "export-calibration": CommandEntry(
        "calibrate",
        "Write a stored calibration as its calibration JSON (rasterserver.calibration/1).",
    ),
    "db": CommandEntry("db", "Create or migrate the catalogue's SQL schema (Alembic migrations)."),
    "patient": CommandEntry("patients", "Register and list patients."),
    "station": CommandEntry(
        "stations", "Register stations (camera + projector set-ups), rasters and calibrations."
    ),
    "simulate": CommandEntry(
        "simulate",
        "Simulate rasterstereographs: render a human back or the control-point calibration "
        "body as the station's camera sees it under the projector's line raster, with exact "
        "ground truth (surface points, line numbers, line rows per column, landmarks).",
    ),
    "jobs": CommandEntry(
        "jobs",
        "Processing jobs: every `rasterserver process` and every POST /jobs is a job kept in "
        "the catalogue, with its selection, chain, counts and times. A job can be paused, "
        "cancelled, and resumed by any process, also after the process running it was killed.",
    ),
    "runs": CommandEntry(
        "runs",
        "Pipeline runs: list an acquisition's runs; mark runs whose process was killed (out "
        "of memory, kill -9, power cut) as interrupted instead of running for ever.",
    ),
    "user": CommandEntry("tokens", "API accounts: people and service accounts (stations)."),
    "token": CommandEntry(
        "tokens", "API bearer tokens: shown once when created, stored as SHA-256."
    ),
    "audit": CommandEntry("tokens", "The audit trail of the HTTP API."),
    "keys": CommandEntry("tokens", "The researchers' pseudonym key (kept outside the catalogue)."),
}


def command_module(name: str) -> ModuleType:
    """Import the module that registers the top-level command ``name``.

    Parameters
    ----------
    name : str
        A key of :data:`COMMANDS`.

    Returns
    -------
    ModuleType
        The module; its ``register(app)`` adds ``name`` (and its siblings) to a Typer app.
    """
    return importlib.import_module(f"{__name__}.{COMMANDS[name].module}")


def command_modules() -> list[ModuleType]:
    """Every command module, each once, in the order of :data:`COMMANDS` (imports them all)."""
    names = dict.fromkeys(entry.module for entry in COMMANDS.values())
    return [importlib.import_module(f"{__name__}.{module}") for module in names]
