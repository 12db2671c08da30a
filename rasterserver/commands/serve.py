"""``rasterserver serve``: run the HTTP API on uvicorn."""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Annotated, Any

import typer

from rasterserver.commands.common import settings
from rasterserver.errors import InputError, UnavailableError

# read by prometheus_client in each worker (rasterserver.api.metrics)
MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"


def serve(
    ctx: typer.Context,
    host: Annotated[
        str, typer.Option(envvar="RASTERSERVER_HOST", help="Interface to listen on.")
    ] = "127.0.0.1",
    port: Annotated[int, typer.Option(envvar="RASTERSERVER_PORT", help="TCP port.")] = 8000,
    workers: Annotated[
        int, typer.Option(envvar="RASTERSERVER_WORKERS", help="Worker processes.")
    ] = 1,
    log_level: Annotated[str, typer.Option(help="uvicorn log level.")] = "info",
    keep_alive: Annotated[
        int,
        typer.Option(
            help="Seconds an idle keep-alive connection stays open. Longer than uvicorn's 5 s "
            "default, so busy clients rarely reuse a connection the server is closing."
        ),
    ] = 30,
) -> None:
    """Serve the HTTP API (OpenAPI at /docs); every route but /health needs a bearer token.

    Create the first admin account and its token with `rasterserver user add` and
    `rasterserver token create`. Uvicorn's own access log is off: it would print request
    paths, which can carry patient identifiers; rasterserver logs route templates instead.
    With several workers, /metrics sums the counts of all of them through a private
    directory (PROMETHEUS_MULTIPROC_DIR), made at start and removed at exit; those left by
    servers that were killed are removed at the next start.

    A new archive on the embedded SQLite catalogue is set up at the first start; a
    PostgreSQL catalogue must be created with `rasterserver db upgrade` first.
    """
    import uvicorn
    from uvicorn.config import LOG_LEVELS

    if not 1 <= port <= 65535:
        raise InputError(f"--port must lie in [1, 65535], got {port}")
    if workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    if keep_alive < 1:
        raise InputError(f"--keep-alive must be at least 1 second, got {keep_alive}")
    if log_level not in LOG_LEVELS:
        raise InputError(f"--log-level must be one of {', '.join(LOG_LEVELS)}, got {log_level!r}")

    from rasterserver.api.app import create_app
    from rasterserver.api.metrics_dir import make_metrics_dir
    from rasterserver.archive import Archive
    from rasterserver.catalog import migrate
    from rasterserver.catalog.database import make_engine

    resolved = settings(ctx)
    engine = make_engine(resolved.database_url)
    try:
        if migrate.create_embedded(engine):
            typer.echo(f"created the catalogue {resolved.database_url}", err=True)
    finally:
        engine.dispose()
    # refuse to start on an old schema, with the message that says what to run
    Archive(resolved).close()
    common: dict[str, Any] = {  # keyword arguments of uvicorn.run
        "host": host,
        "port": port,
        "access_log": False,
        "log_level": log_level,
        "proxy_headers": False,
        "timeout_keep_alive": keep_alive,
    }
    if workers <= 1:
        with _startup_failure(host, port):
            uvicorn.run(create_app(resolved), **common)
        return
    # worker processes build their own app from the environment
    os.environ["RASTERSERVER_ARCHIVE"] = str(resolved.archive)
    os.environ["RASTERSERVER_DATABASE_URL"] = resolved.database_url
    # A fresh private directory for prometheus_client's multiprocess mode: it must be empty
    # at start (stale files from an earlier run would be summed in), so a value already in
    # the environment is replaced. Set here, before uvicorn spawns the workers, which
    # inherit it and import prometheus_client afresh.
    multiproc_dir = str(make_metrics_dir())
    previous = os.environ.get(MULTIPROC_ENV)
    os.environ[MULTIPROC_ENV] = multiproc_dir
    try:
        with _startup_failure(host, port):
            uvicorn.run(
                "rasterserver.api.app:app_from_env", factory=True, workers=workers, **common
            )
    finally:
        if previous is None:
            os.environ.pop(MULTIPROC_ENV, None)
        else:
            os.environ[MULTIPROC_ENV] = previous
        shutil.rmtree(multiproc_dir, ignore_errors=True)


@contextmanager
def _startup_failure(host: str, port: int) -> Iterator[None]:
    """Turn uvicorn's exit on a failed start (3: address in use, an unknown host) into exit 8
    with a sentence; uvicorn has logged its reason above."""
    try:
        yield
    except SystemExit as exc:
        if exc.code in (0, None):
            raise
        raise UnavailableError(
            f"the server could not start on {host}:{port} (uvicorn's reason above)"
        ) from None


def register(app: typer.Typer) -> None:
    """Add the ``serve`` command to ``app``."""
    app.command("serve")(serve)
