"""A JSON document's text and file, for the types that say themselves as one (``to_dict``).

One place for the two small steps :class:`~rasterserver.raster.Raster` and
:class:`~rasterserver.optics.Station` wrote alike; reading them back goes through the checks
of :mod:`rasterserver.documents`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


class JsonDocument:
    """Mixin: :meth:`to_json` and :meth:`save` from the class's ``to_dict()``."""

    def to_dict(self) -> dict[str, Any]:  # pragma: no cover - each class has its own
        raise NotImplementedError

    def to_json(self, *, indent: int | None = 2) -> str:
        """Serialise to the document's JSON text."""
        return json.dumps(self.to_dict(), indent=indent)

    def save(self, path: str | Path) -> Path:
        """Write the document's JSON (and a final newline) to ``path``; returns the path."""
        path = Path(path)
        path.write_text(self.to_json() + "\n", encoding="utf-8")
        return path
