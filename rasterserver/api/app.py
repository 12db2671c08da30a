"""The FastAPI application factory and the services it holds.

:func:`create_app` builds the app for one archive. The routers reach the services through
``request.app.state.services``: the same :class:`~rasterserver.archive.Archive` and
:class:`~rasterserver.pipeline.Pipeline` the CLI uses, the services of
:mod:`rasterserver.services` (jobs, pseudonyms, the audit trail, tokens), and metrics.

Settings (environment, or :class:`ApiSettings` arguments):

``RASTERSERVER_MAX_UPLOAD_BYTES``
    Largest request body (default 256 MiB); bigger ones get 413.
``RASTERSERVER_REQUEST_TIMEOUT``
    Seconds a request may take (default 120); then 504.
``RASTERSERVER_API_THREADS``
    Threads serving requests per worker process (default 16).
``RASTERSERVER_KEEPALIVE_SECONDS``
    Seconds a keep-alive connection is used before the server closes it (default 5; 0:
    never), so that long-lived clients spread evenly over the worker processes.
``RASTERSERVER_PSEUDONYM_KEY``, ``RASTERSERVER_PSEUDONYM_KEY_FILE``
    The key of the researchers' pseudonyms, as hex or in a file (default
    ``<archive>/config/pseudonym.key``, made once), never in the catalogue: see
    :mod:`rasterserver.pseudonym_key`.
"""

from __future__ import annotations

import functools
import gc
import logging
import os
import threading
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any, TypeVar

import anyio
from fastapi import FastAPI

from rasterserver import __version__
from rasterserver.api.audit import RequestMiddleware
from rasterserver.api.errors import LimitsMiddleware, install_handlers
from rasterserver.api.gate import AuthGate
from rasterserver.api.metrics import Metrics
from rasterserver.api.roles import RESEARCHER
from rasterserver.archive import Archive
from rasterserver.config import Settings
from rasterserver.pipeline import Pipeline
from rasterserver.services.audit import audit_writer
from rasterserver.services.audit_index import AuditIndexer
from rasterserver.services.auth import has_role
from rasterserver.services.jobs import JobRunner
from rasterserver.services.pseudonyms import Pseudonymiser
from rasterserver.services.token_cache import token_cache_for

T = TypeVar("T")


@dataclass(frozen=True)
class ApiSettings:
    """Limits of the HTTP API.

    Attributes
    ----------
    max_upload_bytes : int
        Largest request body accepted.
    request_timeout_s : float
        Longest a request may take.
    job_workers : int
        Threads running processing jobs in this process.
    threads : int
        Threads serving requests in this process. Python runs one at a time; more only
        queue for the interpreter and hold catalogue connections, so a few are enough to
        overlap waits on disk and database.
    keepalive_s : float
        Seconds a keep-alive connection is used before it is closed (0: never); see
        :class:`~rasterserver.api.errors.LimitsMiddleware`.
    """

    max_upload_bytes: int = 256 * 1024 * 1024
    request_timeout_s: float = 120.0
    job_workers: int = 1
    threads: int = 16
    keepalive_s: float = 5.0

    @classmethod
    def from_env(cls) -> ApiSettings:
        """Read the limits from the environment, with the defaults above."""
        return cls(
            max_upload_bytes=int(os.environ.get("RASTERSERVER_MAX_UPLOAD_BYTES",
                                                cls.max_upload_bytes)),
            request_timeout_s=float(os.environ.get("RASTERSERVER_REQUEST_TIMEOUT",
                                                   cls.request_timeout_s)),
            job_workers=int(os.environ.get("RASTERSERVER_JOB_WORKERS", cls.job_workers)),
            threads=int(os.environ.get("RASTERSERVER_API_THREADS", cls.threads)),
            keepalive_s=float(os.environ.get("RASTERSERVER_KEEPALIVE_SECONDS",
                                             cls.keepalive_s)),
        )


class Services:
    """What the routers call: the archive and its catalogue, its pipeline, jobs, pseudonyms,
    metrics, the audit trail's writer and indexer, and the token cache."""

    def __init__(self, settings: Settings, api: ApiSettings) -> None:
        self.settings = settings
        self.api = api
        # a connection for each request thread, the job threads, the audit writer and indexer
        self.archive = Archive(settings, connections=api.threads + api.job_workers + 2)
        #: The database handle of the services that need no more (auth, audit, listings)
        self.catalog = self.archive.catalog
        self.pipeline = Pipeline(self.archive)
        self.jobs = JobRunner(self.archive, workers=api.job_workers)
        self.pseudonyms = Pseudonymiser(self.archive)
        self.metrics = Metrics()
        self.audit = audit_writer(self.catalog)
        self.audit_index = AuditIndexer(self.catalog)
        self.token_cache = token_cache_for(self.catalog.engine)  # None on SQLite
        # SQLite answers in-process, PostgreSQL over a socket: see read()
        self.reads_inline = self.archive.engine.dialect.name == "sqlite"

    async def read(self, fn: Callable[..., T], /, *args: Any, **kwargs: Any) -> T:
        """Run ``fn(*args, **kwargs)``, a short catalogue read, for a coroutine.

        On SQLite it runs right here on the event loop: the query is in-process and well
        under a millisecond, and handing it to a thread and back cost more than that. On
        PostgreSQL it runs in a thread: the event loop would otherwise stand idle for each
        round trip to the database server, and under load the workers waited on those with
        half their CPU unused.
        """
        if self.reads_inline:
            return fn(*args, **kwargs)
        return await anyio.to_thread.run_sync(functools.partial(fn, *args, **kwargs))

    def has_researchers(self) -> bool:
        """Whether any account has the researcher role (whose requests use pseudonyms)."""
        return has_role(self.catalog, RESEARCHER)

    def warm_pseudonyms(self) -> None:
        """Fill the pseudonym table; a failure only means the first look-up will do it."""
        try:
            self.pseudonyms.warm()
        except Exception as exc:  # best effort, in a background thread
            logging.getLogger(__name__).warning("pseudonym table not prepared: %s",
                                                type(exc).__name__)

    def close(self) -> None:
        """Stop the job threads, commit queued audit rows, stop the indexer and the token
        cache, release the catalogue."""
        self.jobs.close()
        self.audit.close()
        self.audit_index.close()
        if self.token_cache is not None:
            self.token_cache.close()
        self.archive.close()


def _drop_record(_record: logging.LogRecord) -> bool:
    return False


def silence_uvicorn_access_log() -> None:
    """Drop uvicorn's access log records: they carry the concrete path and query, which can
    name a patient. A filter, not just ``access_log=False``: logging set-ups elsewhere (a
    ``dictConfig`` touching ``uvicorn``) re-enable propagation, but leave filters alone.
    """
    access = logging.getLogger("uvicorn.access")
    if _drop_record not in access.filters:
        access.addFilter(_drop_record)


def create_app(settings: Settings, api: ApiSettings | None = None) -> FastAPI:
    """Build the HTTP API of the archive described by ``settings``.

    Parameters
    ----------
    settings : Settings
        Archive folder and catalogue URL; the catalogue must be migrated.
    api : ApiSettings, optional
        Limits; by default from the environment.

    Returns
    -------
    fastapi.FastAPI
    """
    from rasterserver.api.routers import ROUTERS

    silence_uvicorn_access_log()
    api = api or ApiSettings.from_env()
    services = Services(settings, api)

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        # Everything imported and built so far (numpy, h5py, open3d, cv2, the app itself:
        # ~170,000 objects) lives as long as the process. Left in the collector, every
        # full collection walks it: about 0.1 s with the server frozen, which was the whole
        # of the tail latency under load. Frozen objects are skipped by the collector.
        gc.collect()
        gc.freeze()
        anyio.to_thread.current_default_thread_limiter().total_tokens = api.threads
        if services.has_researchers():
            threading.Thread(target=services.warm_pseudonyms, name="pseudonyms",
                             daemon=True).start()
        try:
            yield
        finally:
            services.close()

    app = FastAPI(
        title="rasterserver",
        version=__version__,
        summary="Archive and clinical data server for video rasterstereography.",
        description=(
            "Bearer tokens (`rasterserver token create`) on every route but `/health`. "
            "Roles: admin, clinician, station (upload only), researcher (pseudonymised, "
            "read-only). Every access to patient data is audited."
        ),
        lifespan=lifespan,
    )
    app.state.services = services
    install_handlers(app)
    for router in ROUTERS:
        app.include_router(router)
    # innermost first: the gate refuses a request without a valid token (or role) before
    # its body is read, inside the audit middleware, which records the refusal
    app.add_middleware(AuthGate, services=services, routes=app.router.routes)
    # the limits wrap the audit, so a refused upload is still answered
    app.add_middleware(RequestMiddleware, services=services)
    app.add_middleware(LimitsMiddleware, max_body_bytes=api.max_upload_bytes,
                       timeout_s=api.request_timeout_s,
                       keepalive_s=api.keepalive_s)
    return app


def app_from_env() -> FastAPI:
    """Uvicorn factory for ``--workers`` > 1: settings from the environment."""
    return create_app(Settings.from_env())
