"""CLI command groups, one module each; every module exposes ``register(app)``.

Add a module here to add commands: the CLI imports this list and nothing else.
"""

from __future__ import annotations

from types import ModuleType

COMMAND_MODULES: list[ModuleType] = []
