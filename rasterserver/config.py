"""Where the archive and the catalogue live, read from the environment.

One machine and a clinic run the same code; only these settings change:

``RASTERSERVER_ARCHIVE``
    Folder of the archive (raw HDF5 files, derived results and, by default, the SQLite
    catalogue). Default: ``./archive``.
``RASTERSERVER_DATABASE_URL``
    SQLAlchemy URL of the catalogue. Default: ``sqlite:///<archive>/catalog.sqlite``.
    PostgreSQL: ``postgresql+psycopg://user@host:5432/dbname``.
``RASTERSERVER_DASK_SCHEDULER``
    Address of a Dask scheduler for reprocessing jobs; empty means a local cluster.
``RASTERSERVER_MAX_FRAME_BYTES``
    Largest frame accepted at ingest, in bytes (default 256 MiB).
``RASTERSERVER_GROUP_ACCESS``
    ``1``: the archive's files and folders are readable by the owner's group (0640/0750)
    instead of owner-only (0600/0700); see :mod:`rasterserver.store.modes`.
``RASTERSERVER_PSEUDONYM_KEY``, ``RASTERSERVER_PSEUDONYM_KEY_FILE``
    The researchers' pseudonym key, never in the catalogue: :mod:`rasterserver.pseudonym_key`.
``RASTERSERVER_TOKEN_DAYS``
    Lifetime of a new API token in days (default 90).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

DEFAULT_MAX_FRAME_BYTES = 256 * 1024 * 1024


@dataclass(frozen=True)
class Settings:
    """Resolved settings of one rasterserver process.

    Attributes
    ----------
    archive : Path
        Root folder of the archive.
    database_url : str
        SQLAlchemy URL of the catalogue.
    dask_scheduler : str or None
        Address of a Dask scheduler, or None for a local cluster.
    max_frame_bytes : int
        Largest frame accepted at ingest.
    """

    archive: Path
    database_url: str
    dask_scheduler: str | None = None
    max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES

    @classmethod
    def from_env(
        cls, archive: Path | str | None = None, database_url: str | None = None
    ) -> Settings:
        """Build settings from explicit values, falling back to the environment.

        Parameters
        ----------
        archive : Path or str, optional
            Archive folder; overrides ``RASTERSERVER_ARCHIVE``.
        database_url : str, optional
            Catalogue URL; overrides ``RASTERSERVER_DATABASE_URL``.

        Returns
        -------
        Settings
        """
        root = Path(archive or os.environ.get("RASTERSERVER_ARCHIVE") or "archive").resolve()
        url = database_url or os.environ.get("RASTERSERVER_DATABASE_URL") or sqlite_url(root)
        scheduler = os.environ.get("RASTERSERVER_DASK_SCHEDULER") or None
        max_bytes = int(os.environ.get("RASTERSERVER_MAX_FRAME_BYTES", DEFAULT_MAX_FRAME_BYTES))
        return cls(archive=root, database_url=url, dask_scheduler=scheduler,
                   max_frame_bytes=max_bytes)


def sqlite_url(archive: Path) -> str:
    """Return the URL of the embedded SQLite catalogue inside ``archive``."""
    return f"sqlite:///{archive / 'catalog.sqlite'}"
