"""Property-based requests over the whole published OpenAPI: no input gives a 500.

Hypothesis generates, for every operation of the OpenAPI document, path values, query
parameters (right and wrong types), JSON bodies shaped by the request schema (and random
ones) and multipart uploads of random bytes, sent with every role's token to a live server.
Bounded: a fixed number of examples and a wall-clock budget well under 60 s.
(test_api_schemathesis.py runs schemathesis over the same document with its response
checks; these hand-written strategies add random multipart uploads and wilder values.)
"""

from __future__ import annotations

import time
from typing import Any
from urllib.parse import quote

import pytest
from api_helpers import PATIENT_ID, ROLES, LiveServer, frame, npy_bytes
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

BUDGET_S = 40.0

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**70), 2**70),
    st.floats(allow_nan=False, allow_infinity=False), st.text(max_size=30),
    st.sampled_from(["", "0", "-1", "2025-03-01", "2025-03-01T10:00:00Z", "9999-12-31",
                     "0001-01-01T00:00:00", "clinic-1", PATIENT_ID, "mesh", "\x00", "../..",
                     "ply", "fhir", "raster", "patient", "x" * 300]),
)
json_values = st.recursive(scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)),
    max_leaves=12)


def _schema_body(document: dict[str, Any], operation: dict[str, Any]) -> st.SearchStrategy:
    content = operation.get("requestBody", {}).get("content", {})
    schema = content.get("application/json", {}).get("schema")
    if schema is None:
        return st.none()
    if "$ref" in schema:
        schema = document["components"]["schemas"][schema["$ref"].split("/")[-1]]
    names = list(schema.get("properties", {}))
    shaped = st.fixed_dictionaries({}, optional={n: json_values for n in names})
    return st.one_of(shaped, json_values)


def _multipart() -> st.SearchStrategy:
    good = npy_bytes(frame())
    files = st.lists(st.tuples(st.sampled_from(["a.npy", "b.png", "c.tif", "d.raw", "", "e"]),
                               st.one_of(st.binary(max_size=200), st.just(good))),
                     min_size=0, max_size=3)
    fields = st.dictionaries(
        st.sampled_from(["patient", "kind", "station", "calibration_version", "visit_date",
                         "acquired_at", "operator", "notes", "shape", "dtype",
                         "convert_color", "roles"]),
        scalars.map(lambda v: "" if v is None else str(v)), max_size=6)
    return st.tuples(files, fields)


def _request(document: dict[str, Any]) -> st.SearchStrategy:
    operations = [(path, method, op) for path, item in document["paths"].items()
                  for method, op in item.items()]

    @st.composite
    def build(draw: st.DrawFn) -> dict[str, Any]:
        path, method, op = draw(st.sampled_from(operations))
        url = path
        query: dict[str, str] = {}
        for param in op.get("parameters", []):
            value = draw(scalars)
            if param["in"] == "path":
                url = url.replace("{" + param["name"] + "}",
                                  quote(str(value if value is not None else ""), safe=""))
            elif value is not None:
                query[param["name"]] = str(value)
        request: dict[str, Any] = {"method": method.upper(), "url": url, "params": query,
                                   "role": draw(st.sampled_from(ROLES))}
        if "multipart/form-data" in op.get("requestBody", {}).get("content", {}):
            files, fields = draw(_multipart())
            request["files"] = [("files", f) for f in files] or None
            request["data"] = fields
        elif method == "post":
            request["json"] = draw(_schema_body(document, op))
        return request

    return build()


def test_no_request_from_the_openapi_document_gives_a_500(live_sqlite: LiveServer) -> None:
    live = live_sqlite
    clients = {role: live.client(role) for role in ROLES}
    document = clients["admin"].get("/openapi.json").json()
    started = time.monotonic()
    seen: list[tuple[str, str, int]] = []

    @settings(max_examples=400, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(_request(document))
    def check(request: dict[str, Any]) -> None:
        if time.monotonic() - started > BUDGET_S:
            return
        client = clients[request.pop("role")]
        method, url = request.pop("method"), request.pop("url")
        response = client.request(method, url, **{k: v for k, v in request.items()
                                                  if v is not None})
        seen.append((method, url, response.status_code))
        assert response.status_code < 500, (method, url, request, response.text)
        if response.status_code >= 400:  # every refusal explains itself in JSON
            assert response.headers["content-type"] == "application/json", response.text
            assert "detail" in response.json()

    try:
        check()
    finally:
        for client in clients.values():
            client.close()
    assert time.monotonic() - started < 60
    assert len({u for _m, u, _s in seen}) > 50, "the walk reached few distinct requests"
    assert any(s < 300 for *_x, s in seen), "nothing ever succeeded: the generator is too wild"


pytestmark = pytest.mark.timeout(120)
