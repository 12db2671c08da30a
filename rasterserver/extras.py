"""Optional extras: which ``pip install 'rasterserver[EXTRA]'`` a missing package belongs to.

The archive, the pipeline, the calibration, the comparison and the simulator need only the
core dependencies. Two parts can be left out, as pydicom leaves out its image handlers:

``server``
    ``rasterserver serve`` and the HTTP API: FastAPI, uvicorn, python-multipart, orjson,
    prometheus-client.
``dask``
    Processing on a Dask cluster (``--dask``, ``--scheduler``): dask.distributed.

A command that needs an extra that is not installed exits with code 8 (unavailable) and a
sentence naming the extra, instead of a traceback (:func:`missing_extra`, called by the CLI
on an error it does not otherwise know). The simulator has no extra: everything it imports
(NumPy, SciPy, OpenCV, open3d, h5py) the pipeline needs too.
"""

from __future__ import annotations

from rasterserver.errors import UnavailableError

__all__ = ["EXTRAS", "MissingExtraError", "missing_extra"]

#: Top-level import name → (extra, what it is for). Kept in step with pyproject.toml's
#: [project.optional-dependencies] (tests/test_extras.py checks it).
EXTRAS: dict[str, tuple[str, str]] = {
    "fastapi": ("server", "the HTTP API"),
    "starlette": ("server", "the HTTP API"),
    "uvicorn": ("server", "the HTTP server"),
    "multipart": ("server", "uploads to the HTTP API"),
    "python_multipart": ("server", "uploads to the HTTP API"),
    "orjson": ("server", "the HTTP API"),
    "prometheus_client": ("server", "the HTTP API's metrics"),
    "dask": ("dask", "processing on Dask"),
    "distributed": ("dask", "processing on Dask"),
}


class MissingExtraError(UnavailableError):
    """A package of an optional extra is not installed; the message says which extra."""

    def __init__(self, module: str, extra: str, purpose: str) -> None:
        hint = " (or run without Dask: --no-dask)" if extra == "dask" else ""
        super().__init__(
            f"{purpose} needs the package {module!r}, which is not installed: install the "
            f"{extra!r} extra, pip install 'rasterserver[{extra}]'{hint}"
        )
        self.module = module
        self.extra = extra


def missing_extra(exc: BaseException) -> MissingExtraError | None:
    """The :class:`MissingExtraError` that ``exc`` stands for, or None.

    Parameters
    ----------
    exc : BaseException
        Any error; a :class:`ModuleNotFoundError` of a package of an extra (itself or as the
        ``__cause__`` of ``exc``) is recognised.

    Returns
    -------
    MissingExtraError or None
    """
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, ModuleNotFoundError) and seen.name:
            top = seen.name.split(".", 1)[0]
            if top in EXTRAS:
                extra, purpose = EXTRAS[top]
                return MissingExtraError(top, extra, purpose)
        seen = seen.__cause__
    return None
