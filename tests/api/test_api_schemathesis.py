"""Schemathesis over the published OpenAPI document, against a real uvicorn server.

For every operation of ``/openapi.json`` (read from the live server), schemathesis generates
requests, valid and invalid by the schema, and sends them over loopback with the token of
each role (admin, clinician, researcher, station), on both catalogue backends (SQLite,
PostgreSQL). Every response must:

* not be a server error (``not_a_server_error``);
* have a status code the document lists for the operation (``status_code_conformance``);
* have a ``Content-Type`` the document lists for it (``content_type_conformance``);
* have a body that conforms to the documented schema (``response_schema_conformance``).

Phases: schemathesis' coverage phase (boundary and wrong-typed values of every parameter and
field) for the operations the role may call; for those the role table refuses (a 403 before
the input is looked at) only the fuzzing phase. Bounded and repeatable: a fixed seed,
``derandomize=True``, no example database, no deadline, ``MAX_EXAMPLES`` fuzzed examples per
operation; the whole file takes about a minute.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Any

import pytest
import schemathesis
from api_helpers import ROLES, LiveServer
from hypothesis import HealthCheck, settings
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_schema_conformance,
    status_code_conformance,
)

from rasterserver.api.roles import PUBLIC, RULES, allowed

SEED = 20250301
MAX_EXAMPLES = 5
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance,
          response_schema_conformance]


@pytest.fixture(params=ROLES)
def role(request: pytest.FixtureRequest) -> str:
    """The role whose token signs the requests of the run."""
    return request.param


def _route_name(path: str, method: str, operation: dict[str, Any]) -> str:
    """The route name behind an operation (FastAPI's operationId: name, path, method)."""
    for name in (*RULES, *PUBLIC):
        if operation.get("operationId") == re.sub(r"\W", "_", name + path) + "_" + method:
            return name
    raise AssertionError(f"{method.upper()} {path} has no rule in rasterserver.api.roles")


def _refused_operation_ids(document: dict[str, Any], role: str) -> list[str]:
    """operationIds of the operations the role table refuses to ``role``."""
    return [operation["operationId"]
            for path, item in document["paths"].items()
            for method, operation in item.items()
            if (name := _route_name(path, method, operation)) not in PUBLIC
            and not allowed(name, role)]


@pytest.fixture
def api_schema(live: LiveServer, role: str,
               request: pytest.FixtureRequest) -> schemathesis.BaseSchema:
    """The live server's own OpenAPI document, with the run's seed and phases for ``role``."""
    # schemathesis 4.32's lazy loader reads ``node._nodeid``, which pytest 9.2 no longer has
    if not hasattr(request.node, "_nodeid"):
        request.node._nodeid = request.node.nodeid
    with live.client() as client:
        document = client.get("/openapi.json").raise_for_status().json()
    options: dict[str, Any] = {"seed": SEED}
    if refused := _refused_operation_ids(document, role):
        options["operations"] = [{"include-operation-id": refused,
                                  "phases": {"coverage": {"enabled": False}}}]
    schema = schemathesis.openapi.from_dict(document,
                                            config=schemathesis.Config.from_dict(options))
    schema.config.update(base_url=live.url, request_timeout=60)
    return schema


@pytest.fixture
def answers(role: str) -> Iterator[dict[str, set[int]]]:
    """Status codes seen per operation; afterwards: the role's token was used and let in."""
    seen: dict[str, set[int]] = {}
    yield seen
    # schemathesis also sends no or broken tokens (401), and a body that cannot be parsed is
    # refused before the token is looked at (400, 422): only a 403 proves the token was
    # accepted, and a 2xx of a protected operation that the role got somewhere
    codes = {code for label, found in seen.items() if label != "GET /health" for code in found}
    assert 403 in codes, f"the {role} token was never accepted: {seen}"
    if any(allowed(name, role) for name in RULES if name.startswith("list_")):
        assert any(200 <= code < 300 for code in codes), f"{role} never succeeded: {seen}"


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
@settings(max_examples=MAX_EXAMPLES, derandomize=True, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
def test_every_response_conforms_to_the_openapi_document(
    case: schemathesis.Case, live: LiveServer, role: str, answers: dict[str, set[int]]
) -> None:
    response = case.call_and_validate(
        base_url=live.url, checks=CHECKS,
        headers={"Authorization": f"Bearer {live.tokens[role]}"})
    answers.setdefault(case.operation.label, set()).add(response.status_code)


pytestmark = pytest.mark.timeout(300)
