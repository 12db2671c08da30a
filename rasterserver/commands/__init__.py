"""CLI command groups, one module each; every module exposes ``register(app)``.

Add a module here to add commands: the CLI imports this list and nothing else.
"""

from __future__ import annotations

from types import ModuleType

from rasterserver.commands import (
    analyse,
    calibrate,
    compare,
    db,
    demo,
    export,
    ingest,
    jobs,
    listing,
    patients,
    plugins,
    process,
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
    runs,
    export,
    serve,
    tokens,
    calibrate,
]
