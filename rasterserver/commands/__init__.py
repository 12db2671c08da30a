"""CLI command groups, one module each; every module exposes ``register(app)``.

Add a module here to add commands: the CLI imports this list and nothing else.

Every command module is imported at every start (``--help`` lists them all), so at module level
a command module imports only Typer and light modules (errors, config, times); the archive,
the pipeline, NumPy, OpenCV, SciPy, open3d, Dask, the simulator and the HTTP API are imported
inside the command functions that use them. Names needed in a command's signature (an enum of
choices) live in a light module of their own, as :mod:`rasterserver.export_choices` does.
``tests/commands/test_cli_imports.py`` checks what ``--help``, ``list`` and ``verify`` load.
"""

from __future__ import annotations

from types import ModuleType

from rasterserver.commands import (
    analyse,
    calibrate,
    compare,
    db,
    demo,
    diff,
    export,
    ingest,
    jobs,
    listing,
    patients,
    plugins,
    process,
    prune,
    reconstruct,
    runs,
    serve,
    simulate,
    stations,
    tokens,
    verify,
)

COMMAND_MODULES: list[ModuleType] = [
    demo,
    db,
    patients,
    stations,
    ingest,
    listing,
    verify,
    plugins,
    simulate,
    reconstruct,
    analyse,
    compare,
    process,
    jobs,
    diff,
    prune,
    runs,
    export,
    serve,
    tokens,
    calibrate,
]
