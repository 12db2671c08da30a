"""Every route with every role, on a live server (SQLite and PostgreSQL): allowed -> neither
401 nor 403, refused -> 403, no token -> 401. And every route is in the OpenAPI document."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from api_helpers import PATIENT_ID, ROLES, LiveServer, frame, npy_bytes
from fastapi.routing import APIRoute

from rasterserver.api.app import create_app
from rasterserver.api.roles import PUBLIC, RULES
from rasterserver.archive import Archive
from rasterserver.config import Settings, sqlite_url


def iter_routes(routes: list[Any]) -> Iterator[Any]:
    """Every route of the app, descending into included routers."""
    for route in routes:
        inner = getattr(route, "original_router", None)
        if inner is not None:
            yield from iter_routes(inner.routes)
        else:
            yield route


@pytest.fixture(scope="module")
def app_routes(tmp_path_factory: pytest.TempPathFactory) -> list[Any]:
    root = tmp_path_factory.mktemp("routes") / "archive"
    settings = Settings(archive=root, database_url=sqlite_url(root))
    Archive.create(settings).close()
    app = create_app(settings)
    routes = list(iter_routes(app.routes))
    app.state.openapi_doc = app.openapi()
    routes.append(app)  # the last item carries the document
    return routes


def test_every_route_has_a_rule_and_every_rule_a_route(app_routes: list[Any]) -> None:
    names = {r.name for r in app_routes[:-1] if isinstance(r, APIRoute)}
    assert len(names) == sum(isinstance(r, APIRoute) for r in app_routes[:-1]), "names unique"
    assert names - PUBLIC == set(RULES), "a route without a rule is refused to everyone"
    for name, roles in RULES.items():
        assert roles <= set(ROLES), name


def test_every_route_is_in_openapi(app_routes: list[Any]) -> None:
    document = app_routes[-1].state.openapi_doc
    checked = 0
    for route in app_routes[:-1]:
        if not getattr(route, "include_in_schema", False):
            continue
        path = route.path_format  # as OpenAPI writes it: /patients/{patient}, no converter
        for method in route.methods - {"HEAD"}:
            assert method.lower() in document["paths"][path], (method, path)
            checked += 1
        if route.name not in PUBLIC:
            operation = document["paths"][path][sorted(route.methods)[0].lower()]
            assert operation.get("security"), f"{path} must declare the bearer token"
    assert checked == len(RULES) + 1  # + /health


def _sample_path(path: str, uid: str) -> str:
    values = {"uid": uid, "index": "0", "patient": PATIENT_ID, "station": "clinic-1",
              "version": "1", "name": "default", "stage": "mesh", "job_id": "0" * 32,
              "uid_a": uid, "uid_b": uid}
    for key, value in values.items():
        path = path.replace("{" + key + "}", value)
    assert "{" not in path, path
    return path


def test_every_route_with_every_role(live: LiveServer, app_routes: list[Any]) -> None:
    with live.client("clinician") as c:
        uid = c.post("/acquisitions", files=[("files", ("a.npy", npy_bytes(frame())))],
                     data={"patient": PATIENT_ID}).json()["uid"]
    clients = {role: live.client(role) for role in ROLES} | {None: live.client()}
    walked = 0
    try:
        for route in app_routes[:-1]:
            if not isinstance(route, APIRoute):
                continue
            path = _sample_path(route.path_format, uid)
            for method in sorted(route.methods):
                for role, client in clients.items():
                    kwargs = {"json": {}} if method == "POST" and route.name != \
                        "upload_acquisition" else {}
                    status = client.request(method, path, **kwargs).status_code
                    where = f"{method} {route.path} as {role}: {status}"
                    if route.name in PUBLIC:
                        assert status not in (401, 403), where
                    elif role is None:
                        assert status == 401, where
                    elif role in RULES[route.name]:
                        assert status not in (401, 403), where
                        assert status < 500, where
                    else:
                        assert status == 403, where
                    walked += 1
    finally:
        for client in clients.values():
            client.close()
    assert walked >= 5 * len(RULES)
