"""JSON error bodies for every refusal, and the request limits (size, time).

Every error response is ``{"detail": ..., "error": <type>, "status": <code>}``: the service's
:class:`~rasterserver.errors.RasterServerError` subclasses keep their ``http_status`` (422 bad
input, 404, 409, 500 integrity), FastAPI's validation errors stay 422 with the per-field list,
and anything unexpected is a 500 whose body says nothing about the data.

The OpenAPI document says so too (:func:`document_errors`): every protected operation lists
401, 403 and 404, every POST 409, every operation with a body 400 and 413, all with the
:class:`~rasterserver.api.schemas.ErrorOut` body, which also replaces FastAPI's
``HTTPValidationError`` for 422 (a service's 422 carries a sentence, not a field list).

A method a path does not take is answered 405 with ``Allow`` naming every method of the
path (Starlette named those of its first route only: ``GET`` for ``/patients``, which also
takes POST), and ``OPTIONS`` is answered 204 with that header, without a token.
"""

from __future__ import annotations

import json
import logging
import time
import traceback
from collections.abc import Callable, Iterator
from typing import Any

import anyio
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from sqlalchemy.exc import DataError, OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from rasterserver.api.schemas import ErrorOut
from rasterserver.errors import RasterServerError

log = logging.getLogger(__name__)


def traceback_without_values(exc: BaseException) -> str:
    """Where an exception came from, without its message.

    Messages of database errors quote the statement's parameters, which may be a patient's
    identifier or name; the log gets the frames only.
    """
    return "".join(traceback.format_tb(exc.__traceback__))


#: The body of a 500 the service raised on purpose (e.g. a damaged archive file).
SERVER_FAULT = ("stored data needed for this request is damaged or missing; the server log "
                "says which (run `rasterserver verify`)")


def scrub_paths(text: str, root: object) -> str:
    """``text`` with the archive folder ``root`` written as ``<archive>``: messages kept for
    clients (a pipeline run's or job's error) must not show where the archive lives."""
    where = str(root)
    return text.replace(where, "<archive>") if where and where != "." else text


_HTTP_KINDS = {400: "BadRequest", 401: "Unauthorized", 403: "Forbidden", 404: "NotFound",
               405: "MethodNotAllowed", 413: "PayloadTooLarge"}


def error_body(status: int, detail: object, kind: str) -> dict[str, object]:
    """The JSON body of an error response."""
    return {"detail": detail, "error": kind, "status": status}


async def send_error(send: Send, status: int, detail: str, kind: str, *,
                     close: bool = False) -> None:
    """Answer on a raw ASGI ``send`` with the JSON error body: for the middlewares, which
    answer outside FastAPI's exception handlers. ``close`` ends the connection too."""
    body = json.dumps(error_body(status, detail, kind)).encode()
    headers = [(b"content-type", b"application/json"),
               (b"content-length", str(len(body)).encode())]
    if close:
        headers.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


_ERROR_DOCS = {
    400: "The body could not be parsed (e.g. not UTF-8), or a bad Content-Length",
    401: "No or invalid token",
    403: "The role may not use this route",
    404: "Something the request names does not exist",
    409: "Conflicts with what is stored (e.g. exists already)",
    413: "Request body too large",
    422: "A parameter or field was refused",
    503: "The catalogue or the audit trail is unavailable; nothing was done or returned. "
         "Retry (see Retry-After)",
}


def document_errors(document: dict[str, Any]) -> dict[str, Any]:
    """Add the error responses the handlers give to every operation of an OpenAPI document.

    In place; returns ``document``. Descriptions a route gives itself are kept.
    """
    schemas = document.setdefault("components", {}).setdefault("schemas", {})
    error_schema = ErrorOut.model_json_schema(ref_template="#/components/schemas/{model}")
    schemas.update(error_schema.pop("$defs", {}))
    schemas["ErrorOut"] = error_schema
    content = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorOut"}}}
    for item in document.get("paths", {}).values():
        for method, operation in item.items():
            responses = operation.setdefault("responses", {})
            codes = ({"422"} & set(responses)) | {"503"}
            if operation.get("security"):
                codes |= {"401", "403", "404"}
            if method == "post":
                codes.add("409")
            if "requestBody" in operation:
                codes |= {"400", "413"}
            for code in codes:
                response = responses.setdefault(code, {"description": _ERROR_DOCS[int(code)]})
                response["content"] = content
    return document


def _openapi_with_errors(app: FastAPI) -> Callable[[], dict[str, Any]]:
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = document_errors(build())
        return app.openapi_schema

    return openapi


def allowed_methods(app: FastAPI, scope: Scope) -> list[str]:
    """The methods the app answers on the path of ``scope``, for an ``Allow`` header: those
    of every route with that path, and OPTIONS (answered here, without a token)."""
    methods = {"OPTIONS"}
    for route in all_routes(app.router.routes):
        match, _ = route.matches(scope)
        if match is not Match.NONE:
            methods |= set(getattr(route, "methods", None) or ())
    return sorted(methods)


def all_routes(routes: list[Any]) -> Iterator[Any]:
    """Every route, descending into the routers FastAPI includes (ours have no prefix)."""
    for route in routes:
        inner = getattr(route, "original_router", None)
        if inner is not None:
            yield from all_routes(inner.routes)
        else:
            yield route


def install_handlers(app: FastAPI) -> None:
    """Register the exception handlers that turn every error into a JSON body, and document
    their responses in the app's OpenAPI document."""
    app.openapi = _openapi_with_errors(app)  # type: ignore[method-assign]

    @app.exception_handler(RasterServerError)
    async def _service_error(_request: Request, exc: RasterServerError) -> JSONResponse:
        if exc.http_status >= 500:
            # A damaged or missing archive file: its message names the file (the archive's
            # layout, and in h5py's words its absolute path), which is the operator's
            # business, not the client's. The log keeps it (uids and paths, no patient data).
            log.error("%s while handling a request: %s", type(exc).__name__, exc)
            return JSONResponse(error_body(exc.http_status, SERVER_FAULT, type(exc).__name__),
                                status_code=exc.http_status)
        return JSONResponse(error_body(exc.http_status, str(exc), type(exc).__name__),
                            status_code=exc.http_status)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException) -> Response:
        headers = exc.headers
        if exc.status_code == 405:
            # Starlette names the methods of the first route with this path only: "GET" for
            # /patients, which also takes POST
            allow = ", ".join(allowed_methods(request.app, request.scope))
            if request.method == "OPTIONS":
                return Response(status_code=204, headers={"Allow": allow})
            headers = {**(headers or {}), "Allow": allow}
        kind = _HTTP_KINDS.get(exc.status_code, "HTTPError")
        return JSONResponse(error_body(exc.status_code, exc.detail, kind),
                            status_code=exc.status_code, headers=headers)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
        # the offending input is echoed back to the client only, never logged
        errors = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", ""),
                   "type": e.get("type", "")} for e in exc.errors()]
        return JSONResponse(error_body(422, errors, "ValidationError"), status_code=422)

    @app.exception_handler(DataError)
    async def _unstorable(_request: Request, _exc: DataError) -> JSONResponse:
        # e.g. a NUL character PostgreSQL cannot store in text: bad input, not a server fault
        return JSONResponse(error_body(422, "a value cannot be stored (bad characters or "
                                       "out of range)", "InputError"), status_code=422)

    @app.exception_handler(OperationalError)
    async def _catalogue_unavailable(_request: Request, exc: OperationalError) -> JSONResponse:
        # the database is down, restarting or unreachable, or a pooled connection went stale
        # (the pool then replaces them): worth a retry, unlike a 500
        log.error("catalogue unavailable: %s%s", type(exc.orig).__name__,
                  " (connection invalidated)" if exc.connection_invalidated else "")
        return JSONResponse(error_body(503, "the catalogue is unavailable; retry shortly",
                                       "CatalogueUnavailable"),
                            status_code=503, headers={"Retry-After": "1"})

    @app.exception_handler(Exception)
    async def _unexpected(_request: Request, exc: Exception) -> JSONResponse:
        log.error("unexpected %s while handling a request\n%s", type(exc).__name__,
                  traceback_without_values(exc))
        return JSONResponse(error_body(500, "internal error", "InternalError"), status_code=500)


class _TooLarge(StarletteHTTPException):
    """Raised while reading a body that outgrows the limit.

    An HTTPException so that FastAPI's body parser passes it on as a 413 instead of turning
    it into a generic 400.
    """


class LimitsMiddleware:
    """Refuse bodies over ``max_body_bytes`` (413) and requests over ``timeout_s`` (504);
    close a keep-alive connection after ``keepalive_s`` seconds of use.

    The size is checked on ``Content-Length`` before anything is read, and again while the
    body streams in, so a chunked upload cannot get around it.

    The connection limit is nginx's ``keepalive_time``, for the balance between worker
    processes: they share one listening socket, and a client's connection stays with
    whichever worker accepted it. Fifty clients connecting at once were split between two
    workers as unevenly as 41 to 9, for as long as they stayed connected; the busier
    worker's clients waited about twice as long while the other worker sat partly idle.
    A connection older than the limit gets ``Connection: close`` on its next response and
    the client reconnects, to either worker, so an uneven split lasts seconds, not the
    client's lifetime. (It does not make the split even: which worker accepts is still
    chance.)
    """

    def __init__(self, app: ASGIApp, *, max_body_bytes: int, timeout_s: float,
                 keepalive_s: float = 0.0) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.timeout_s = timeout_s
        self.keepalive_s = keepalive_s
        # when each open connection was first seen, by the client's (address, port)
        self._opened: dict[tuple[str, int], float] = {}

    def _closes(self, scope: Scope) -> bool:
        """Whether the response to this request should close its connection."""
        client = scope.get("client")
        if not self.keepalive_s or client is None:
            return False
        key = (client[0], client[1])
        now = time.monotonic()
        opened = self._opened.get(key)
        if opened is None:
            if len(self._opened) > 100_000:  # connections that closed on their own
                self._opened.clear()
            self._opened[key] = now
            return False
        if now - opened >= self.keepalive_s:
            del self._opened[key]
            return True
        return False

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def send_tracked(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                if self._closes(scope):
                    message["headers"] = [*message.get("headers", []),
                                          (b"connection", b"close")]
            await send(message)

        async def refuse(status: int, detail: str, kind: str) -> None:
            await send_error(send, status, detail, kind, close=True)

        too_big = f"request body over {self.max_body_bytes} bytes"
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    length = int(value)
                except ValueError:
                    await refuse(400, "bad Content-Length", "BadRequest")
                    return
                if length > self.max_body_bytes:
                    await refuse(413, too_big, "PayloadTooLarge")
                    return
        received = 0

        async def receive_limited() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_body_bytes:
                    raise _TooLarge(413, too_big)
            return message

        try:
            with anyio.fail_after(self.timeout_s):
                await self.app(scope, receive_limited, send_tracked)
        except TimeoutError:
            if not started:
                await refuse(504, f"request took longer than {self.timeout_s:g} s", "Timeout")
        except _TooLarge:
            if not started:
                await refuse(413, too_big, "PayloadTooLarge")
