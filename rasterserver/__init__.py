"""rasterserver: a plugin-based archive and clinical data server for video rasterstereography."""

from __future__ import annotations

__all__ = ["__version__"]


def __getattr__(name: str) -> str:
    """Read ``__version__`` from the installed metadata on first use (PEP 562).

    :mod:`importlib.metadata` and the scan of the installed distributions cost every command
    a noticeable part of its start; only ``--version``, the HTTP API and stored provenance
    need the version.
    """
    if name != "__version__":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        found = version("rasterserver")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
        found = "0.0.0+unknown"
    globals()["__version__"] = found  # later reads find it without this function
    return found
