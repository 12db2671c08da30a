"""rasterserver: a plugin-based archive and clinical data server for video rasterstereography."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("rasterserver")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
