"""The audit trail's group commit, on a real catalogue (SQLite and PostgreSQL)."""

from __future__ import annotations

import threading
from collections.abc import Sequence

import pytest
from sqlalchemy import func, select

from rasterserver.archive import Archive
from rasterserver.catalog.auth_models import AuditEvent, AuditEventPatient
from rasterserver.config import Settings
from rasterserver.services.audit import AuditNote, AuditRecord, audit_record, insert_records
from rasterserver.services.audit_writer import AuditWriter
from rasterserver.services.auth import Principal


@pytest.fixture
def archive(settings: Settings) -> Archive:
    with Archive.create(settings) as a:
        yield a


def _rows(patient_ids: Sequence[int], *, action_ok: bool = True) -> AuditRecord:
    note = AuditNote(principal=Principal(1, "reader", "clinician", "user"),
                     patient_ids=set(patient_ids))
    record = audit_record(note, method="GET", route="/acquisitions",
                          route_name="list_acquisitions", status=200, client="127.0.0.1")
    if not action_ok:  # refused by the table's CHECK constraint, as a corrupt note would be
        record = AuditRecord(record.event | {"action": "X"}, record.patient_ids)
    return record


def _count(archive: Archive) -> int:
    with archive.session() as s:
        return s.scalar(select(func.count()).select_from(AuditEvent))


class _Counting:
    """The real insert, counting its transactions; the first one waits for a signal so that
    the other requests queue up behind it, as they do under load."""

    def __init__(self, archive: Archive) -> None:
        self.archive = archive
        self.calls: list[int] = []
        self.release = threading.Event()
        self.entered = threading.Event()

    def __call__(self, records: list[AuditRecord]) -> None:
        if not self.calls:
            self.entered.set()
            self.release.wait(10)
        self.calls.append(len(records))
        insert_records(self.archive, records)


def test_requests_waiting_together_share_one_commit(archive: Archive) -> None:
    archive.add_patient("P-1")
    insert = _Counting(archive)
    writer = AuditWriter(insert)
    try:
        first = writer.submit(_rows([]))
        assert insert.entered.wait(10)
        waiting = [writer.submit(_rows([])) for _ in range(30)]
        insert.release.set()
        for f in [first, *waiting]:
            assert f.result(timeout=30) is None
    finally:
        writer.close()
    # the first commit alone, then the 30 that queued behind it in one transaction
    assert insert.calls == [1, 30]
    assert _count(archive) == 31


def test_a_refused_request_fails_alone(archive: Archive) -> None:
    insert = _Counting(archive)
    writer = AuditWriter(insert)
    try:
        first = writer.submit(_rows([]))
        assert insert.entered.wait(10)
        good = [writer.submit(_rows([])) for _ in range(5)]
        bad = writer.submit(_rows([], action_ok=False))
        more = writer.submit(_rows([]))
        insert.release.set()
        first.result(timeout=30)
        for f in [*good, more]:
            assert f.result(timeout=30) is None
        with pytest.raises(Exception, match="action"):
            bad.result(timeout=30)
    finally:
        writer.close()
    assert _count(archive) == 7  # nothing of the refused request, everything of the others


def test_close_commits_what_is_queued_and_then_refuses(archive: Archive) -> None:
    insert = _Counting(archive)
    writer = AuditWriter(insert)
    futures = [writer.submit(_rows([])) for _ in range(10)]
    insert.release.set()
    writer.close()
    assert all(f.done() and f.exception() is None for f in futures)
    assert _count(archive) == 10
    with pytest.raises(RuntimeError, match="closed"):
        writer.submit(_rows([]))
    writer.close()  # twice is harmless


def test_a_list_writes_one_event_linked_to_each_patient(archive: Archive) -> None:
    ids = [archive.add_patient(f"P-{i}").id for i in range(3)]
    writer = AuditWriter(lambda records: insert_records(archive, records))
    try:
        writer.write(_rows(ids))
        writer.write(_rows(ids[:1]))
    finally:
        writer.close()
    with archive.session() as s:
        events = list(s.scalars(select(AuditEvent.id).order_by(AuditEvent.id)))
        links = sorted(s.execute(select(AuditEventPatient.event_id,
                                        AuditEventPatient.patient_id)).all())
    assert len(events) == 2
    assert links == sorted([(events[0], i) for i in ids] + [(events[1], ids[0])])


def test_one_batch_links_each_event_to_its_own_patients(archive: Archive) -> None:
    """Several requests in one transaction, after events written by an earlier one: each
    event's links name exactly the patients of its own request."""
    ids = [archive.add_patient(f"P-{i}").id for i in range(6)]
    insert_records(archive, [_rows(ids[:2])])
    wanted = [ids[1:4], [], ids[5:], ids, ids[2:3]]
    records = [_rows(patients) for patients in wanted]
    insert_records(archive, records)
    with archive.session() as s:
        by_request = dict(s.execute(select(AuditEvent.request_id, AuditEvent.id)).all())
        links = s.execute(select(AuditEventPatient.event_id, AuditEventPatient.patient_id)).all()
    touched: dict[int, set[int]] = {}
    for event_id, patient_id in links:
        touched.setdefault(event_id, set()).add(patient_id)
    for record, patients in zip(records, wanted, strict=True):
        assert touched.get(by_request[record.event["request_id"]], set()) == set(patients)


def test_request_ids_are_unique_time_ordered_and_per_process() -> None:
    import os

    from rasterserver.services.audit import new_request_id

    ids = [new_request_id() for _ in range(10_000)]
    assert len(set(ids)) == len(ids)
    assert all(len(i) == 32 and int(i, 16) >= 0 for i in ids)
    assert ids == sorted(ids)  # time first, then the count
    read, write = os.pipe()
    child = os.fork()
    if child == 0:  # a forked worker draws its own process bits
        os.write(write, new_request_id().encode())
        os._exit(0)
    os.waitpid(child, 0)
    theirs = os.read(read, 64).decode()
    os.close(read)
    os.close(write)
    assert theirs[16:24] != ids[-1][16:24]
