"""No true date reaches a researcher: every route of the OpenAPI document, walked as a
researcher on a processed archive (two visits of one patient, processed through the mesh and
the analysis), on a live server (SQLite and PostgreSQL).

Every date-like text in every JSON, CSV or other text answer (values and keys, also inside
longer strings) is checked against the true times the catalogue stores (read from every
date and time column of every table, so new columns are covered too):

* it equals no true time of a patient's data (acquisitions, visits, results, runs, jobs,
  the patient's record, the audit trail), and no true date of them;
* shifted back by the patient's offset, it is one of those true times (so it is the true
  time shifted, and every interval between two of them is the true interval).

Times of stations, calibrations and rasters are no patient's data, but they are withheld
from researchers too (the period a calibration applied brackets the true dates of the
acquisitions made with it), so the walk accepts no unshifted time of any kind.

Routes come from the server's ``/openapi.json``, so a route added later is walked too; one
with a path parameter the walk does not know fails the test until the walk is told what to
put there. Images and binary files (PNG, PDF, NPY, PLY, STL) are not read: the report's
shifted date is drawn into its pixels (tests/api/test_api_analysis.py checks the header it
is drawn from).
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import re
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
from api_helpers import PATIENT_ID, LiveServer, npy_bytes, run_job
from backshape_truth import simulated
from sqlalchemy import Date, DateTime, select
from test_api_analysis import _calibrate

from rasterserver.api.roles import RESEARCHER, RULES
from rasterserver.catalog import auth_models as _auth_models  # noqa: F401  (its tables)
from rasterserver.catalog.models import Base
from rasterserver.services.pseudonyms import Pseudonymiser

# a fixed key, so that the patient's shift is known and not zero (a zero shift would make
# every check below pass or fail by chance)
KEY_HEX = "5e" * 32
SHIFT_DAYS = 201
FIRST, SECOND = "2024-03-01T10:15:00+01:00", "2025-03-11T10:15:00+01:00"
# rows that describe no patient: their true times may be shown to anyone
NOT_PATIENT_DATA = frozenset({"station", "calibration", "raster", "api_account", "api_token"})

DATE_LIKE = re.compile(
    r"(?<!\d)(\d{4}-\d{2}-\d{2})(?:[T ](\d{2}:\d{2})(:\d{2})?(\.\d{1,6})?(Z|[+-]\d{2}:?\d{2})?)?"
    r"(?!\d)"
)


@pytest.fixture(scope="module")
def two_backs() -> tuple[np.ndarray, np.ndarray]:
    """One simulated back rendered twice with independent noise (seconds: once)."""
    return simulated("moderate", seed=1)[0], simulated("moderate", seed=2)[0]


def _upload(live: LiveServer, pixels: np.ndarray, when: str) -> str:
    with live.client("station") as cam:
        response = cam.post(
            "/acquisitions",
            files=[("files", ("back.npy", npy_bytes(pixels)))],
            data={"patient": PATIENT_ID, "station": "clinic-1", "acquired_at": when,
                  "operator": "nurse A", "notes": "seen on 2025-03-11"},
        )
        assert response.status_code == 201, response.text
        return response.json()["uid"]


def _utc(value: dt.datetime) -> dt.datetime:
    return value if value.tzinfo else value.replace(tzinfo=dt.UTC)


def true_times(live: LiveServer) -> tuple[set[Any], set[Any]]:
    """Every date and time the catalogue stores: (of patients' data, of anything else)."""
    patient: set[Any] = set()
    other: set[Any] = set()
    with live.archive() as archive, archive.engine.connect() as conn:
        for table in Base.metadata.sorted_tables:
            columns = [c for c in table.columns if isinstance(c.type, Date | DateTime)
                       or isinstance(getattr(c.type, "impl", None), Date | DateTime)]
            if not columns:
                continue
            into = other if table.name in NOT_PATIENT_DATA else patient
            for row in conn.execute(select(*columns)):
                for value in row:
                    if isinstance(value, dt.datetime):
                        into.add(_utc(value))
                    elif isinstance(value, dt.date):
                        into.add(value)
    return patient, other


def date_texts(value: Any) -> Iterator[str]:
    """Every date-like text in a JSON value, keys included."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from date_texts(key)
            yield from date_texts(item)
    elif isinstance(value, list):
        for item in value:
            yield from date_texts(item)
    elif isinstance(value, str):
        yield from (m.group(0) for m in DATE_LIKE.finditer(value))


def _truncate(when: dt.datetime, precision: str) -> dt.datetime:
    if precision == "minute":
        return when.replace(second=0, microsecond=0)
    if precision == "second":
        return when.replace(microsecond=0)
    return when


class Checker:
    """Judges date-like texts against the true times; collects what it saw and refused."""

    def __init__(self, patient: set[Any], other: set[Any], shift: dt.timedelta) -> None:
        self.shift = shift
        self.patient_times = {v for v in patient if isinstance(v, dt.datetime)}
        self.patient_dates = ({v for v in patient if not isinstance(v, dt.datetime)}
                              | {v.date() for v in self.patient_times})
        self.other_times = {v for v in other if isinstance(v, dt.datetime)}
        self.other_dates = ({v for v in other if not isinstance(v, dt.datetime)}
                            | {v.date() for v in self.other_times})
        self.checked = 0
        self.problems: list[str] = []

    def check(self, text: str, where: str) -> None:
        match = DATE_LIKE.fullmatch(text)
        assert match is not None, text
        day, clock, seconds, fraction, zone = match.groups()
        self.checked += 1
        if clock is None:
            self._check_date(dt.date.fromisoformat(day), text, where)
            return
        precision = "micro" if fraction else ("second" if seconds else "minute")
        iso = f"{day}T{clock}{seconds or ''}{fraction or ''}{zone or 'Z'}"
        when = _utc(dt.datetime.fromisoformat(iso.replace(" ", "T")))
        patient = {_truncate(t, precision) for t in self.patient_times}
        other = {_truncate(t, precision) for t in self.other_times}
        if when in patient:
            self.problems.append(f"{where}: {text} is a true time of a patient's data")
        elif when - self.shift not in patient and when not in other:
            self.problems.append(f"{where}: {text} is neither a shifted time of the patient's "
                                 "data nor the time of something else")

    def _check_date(self, day: dt.date, text: str, where: str) -> None:
        if day in self.patient_dates:
            self.problems.append(f"{where}: {text} is a true date of a patient's data")
        elif day - self.shift not in self.patient_dates and day not in self.other_dates:
            self.problems.append(f"{where}: {text} is neither a shifted date nor another date")


def _values(path: str, uids: list[str], pseudonym: str, stages: list[str],
            job_id: str) -> list[dict[str, str]]:
    """The path parameters to try for ``path``: every combination the archive offers."""
    options = {"uid": uids, "uid_a": uids[:1], "uid_b": uids[1:], "patient": [pseudonym],
               "index": ["0"], "stage": stages, "station": ["clinic-1"], "version": ["1"],
               "name": ["default"], "job_id": [job_id]}
    names = re.findall(r"{([^}]+)}", path)
    unknown = [n for n in names if n not in options]
    assert not unknown, f"{path}: the walk does not know what to put in {unknown}; add it"
    combos: list[dict[str, str]] = [{}]
    for name in names:
        combos = [c | {name: v} for c in combos for v in options[name]]
    return combos


def _variants(operation: dict[str, Any]) -> list[dict[str, str]]:
    """Query strings to try: none, and each value of an enumerated ``format``."""
    variants: list[dict[str, str]] = [{}]
    for parameter in operation.get("parameters", []):
        schema = parameter.get("schema", {})
        enum = schema.get("enum") or next((s.get("enum") for s in schema.get("anyOf", [])
                                           if s.get("enum")), None)
        if parameter.get("in") == "query" and parameter["name"] == "format" and enum:
            variants += [{"format": value} for value in enum]
    return variants


def _texts_of(response: httpx.Response) -> Iterator[str]:
    kind = response.headers.get("content-type", "")
    if "json" in kind:
        yield from date_texts(response.json())
    elif kind.startswith("text/"):
        if "csv" in kind:
            for row in csv.reader(io.StringIO(response.text)):
                for cell in row:
                    yield from date_texts(cell)
        else:
            yield from date_texts(response.text)


def test_a_researcher_sees_no_true_date_on_any_route(start_server, settings, monkeypatch,
                                                     two_backs) -> None:
    monkeypatch.setenv("RASTERSERVER_PSEUDONYM_KEY", KEY_HEX)
    live = start_server(settings)
    _calibrate(live)
    uids = [_upload(live, back, when) for back, when in zip(two_backs, (FIRST, SECOND),
                                                             strict=True)]
    with live.client("clinician") as c:
        job = run_job(c, uids)
        stages = sorted({r["stage"] for r in c.get(f"/acquisitions/{uids[0]}/results").json()})
    assert {"mesh", "analysis"} <= set(stages)
    with live.archive() as archive:
        pseudonyms = Pseudonymiser(archive)
        assert pseudonyms.shift_days(PATIENT_ID) == SHIFT_DAYS
        pseudonym = pseudonyms.pseudonym(PATIENT_ID)
    seen: list[tuple[str, str]] = []  # (date-like text, where), judged after the walk

    answered: dict[str, int] = {}
    with live.client("researcher") as r:
        document = r.get("/openapi.json").json()
        for path, item in document["paths"].items():
            for method, operation in item.items():
                for values in _values(path, uids, pseudonym, stages, job["id"]):
                    concrete = path.format(**values)
                    for query in _variants(operation):
                        kwargs: dict[str, Any] = {"params": query}
                        if method in ("post", "put", "patch"):
                            kwargs["json"] = {}
                        response = r.request(method.upper(), concrete, **kwargs)
                        where = f"{method.upper()} {path} {values} {query}"
                        assert response.status_code < 500, f"{where}: {response.text[:300]}"
                        if response.status_code == 200:
                            answered[f"{method} {path}"] = answered.get(f"{method} {path}",
                                                                        0) + 1
                        seen.extend((text, where) for text in _texts_of(response))

    # the true times as stored after the walk: a read may store something too (a
    # comparison is stored when first asked for), and its time must be shifted as well
    patient_times, other_times = true_times(live)
    assert other_times  # the station, its calibration, the raster: none may be shown either
    checker = Checker(patient_times | other_times, set(), dt.timedelta(days=SHIFT_DAYS))
    for text, where in seen:
        checker.check(text, where)
    assert checker.problems == [], "\n".join(checker.problems)
    # the walk saw the data: every route a researcher may read answered at least once...
    readable = {f"{m} {p}" for p, item in document["paths"].items() for m, op in item.items()
                if m == "get" and RESEARCHER in RULES.get(_route_name(op), frozenset())}
    assert readable and readable <= set(answered), sorted(readable - set(answered))
    # ... and many dates were judged (acquisitions, visits, results, runs, the analysis'
    # provenance, the trends)
    assert checker.checked > 50, checker.checked


def _route_name(operation: dict[str, Any]) -> str:
    """The route's name (FastAPI's operationId is ``<name>_<path>_<method>``)."""
    operation_id = operation.get("operationId", "")
    return next((n for n in sorted(RULES, key=len, reverse=True)
                 if operation_id.startswith(n + "_")), operation_id)


def test_the_checker_catches_true_and_unshifted_times() -> None:
    true = dt.datetime(2025, 3, 11, 9, 15, 0, 123456, tzinfo=dt.UTC)
    station = dt.datetime(2026, 1, 1, 8, 0, tzinfo=dt.UTC)
    checker = Checker({true, dt.date(2025, 3, 11)}, {station}, dt.timedelta(days=3))
    checker.check("2025-03-11T09:15:00.123456Z", "true time")
    checker.check("2025-03-14T09:15:00.123456+00:00", "shifted")
    checker.check("2025-03-14 09:15", "shifted, minutes")
    checker.check("2025-03-12T09:15:00.123456Z", "wrong shift")
    checker.check("2025-03-11", "true date")
    checker.check("2025-03-14", "shifted date")
    checker.check("2026-01-01T08:00:00Z", "a station")
    assert [p.split(":")[0] for p in checker.problems] == ["true time", "wrong shift",
                                                          "true date"]
    assert list(date_texts({"2025-03-11": ["acquired 2025-03-14 09:15 UTC", 20250311]})) == [
        "2025-03-11", "2025-03-14 09:15"]
