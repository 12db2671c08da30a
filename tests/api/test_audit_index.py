"""The audit trail's index by patient, on a real catalogue (SQLite and PostgreSQL)."""

from __future__ import annotations

import datetime as dt
import random
import threading
import time
from pathlib import Path

import pytest
from sqlalchemy import func, select, text, update

from rasterserver.archive import Archive
from rasterserver.catalog.auth_models import AuditIndexMark, AuditPatientIndex
from rasterserver.config import Settings
from rasterserver.services import audit_index
from rasterserver.services.audit import AuditNote, AuditRecord, audit_record, insert_records
from rasterserver.services.audit_index import AuditIndexer, index_patient_links
from rasterserver.services.audit_trail import audit_events
from rasterserver.services.auth import Principal

PATIENTS = [f"P-{n}" for n in range(12)]


@pytest.fixture
def archive(settings: Settings) -> Archive:
    with Archive.create(settings) as a:
        for identifier in PATIENTS:
            a.add_patient(identifier)
        yield a


def _ids(archive: Archive) -> dict[str, int]:
    with archive.engine.connect() as conn:
        return dict(conn.execute(text("SELECT identifier, id FROM patient")).all())


def _record(patient_ids: set[int]) -> AuditRecord:
    note = AuditNote(principal=Principal(1, "dr", "clinician", "user"), patient_ids=patient_ids)
    return audit_record(note, method="GET", route="/acquisitions",
                        route_name="list_acquisitions", status=200, client="")


def _record_many(archive: Archive, n: int, seed: int) -> dict[str, list[int]]:
    """Record ``n`` requests touching random patients; return, per patient, the events that
    touched it, read back independently of the index (the ground truth)."""
    rng = random.Random(seed)
    ids = _ids(archive)
    for start in range(0, n, 7):  # several requests per commit, as the writer does
        insert_records(archive, [
            _record(set(rng.sample(sorted(ids.values()), rng.randint(0, 5))))
            for _ in range(min(7, n - start))
        ])
    truth: dict[str, list[int]] = {identifier: [] for identifier in ids}
    by_id = {v: k for k, v in ids.items()}
    with archive.engine.connect() as conn:
        for event_id, patient_id in conn.execute(text(
                "SELECT event_id, patient_id FROM audit_event_patient ORDER BY event_id")):
            truth[by_id[patient_id]].append(event_id)
    return truth


def _found(archive: Archive) -> dict[str, list[int]]:
    return {p: [e.id for e, _ in audit_events(archive, patient=p, limit=10_000)]
            for p in PATIENTS}


def _mark(archive: Archive) -> tuple[int, dt.datetime | None]:
    with archive.engine.connect() as conn:
        return tuple(conn.execute(select(AuditIndexMark.indexed_through,
                                         AuditIndexMark.lease_until)).one())


def _indexed(archive: Archive) -> int:
    with archive.engine.connect() as conn:
        return conn.execute(select(func.count()).select_from(AuditPatientIndex)).scalar()


def test_queries_by_patient_are_complete_before_during_and_after_indexing(
        archive: Archive) -> None:
    truth = _record_many(archive, 60, seed=1)
    assert sum(map(len, truth.values())) > 50
    assert _mark(archive) == (0, None) and _indexed(archive) == 0
    assert _found(archive) == truth  # nothing indexed yet: all from the links

    # part of the way (the run stops at the mark plus max_events), in small transactions
    added = index_patient_links(archive, max_events=25, chunk=4)
    assert 0 < added < sum(map(len, truth.values()))
    assert _mark(archive) == (25, None)
    assert _found(archive) == truth

    more = _record_many(archive, 20, seed=2)  # recorded meanwhile
    assert index_patient_links(archive, chunk=4) > 0
    assert _mark(archive)[0] == 80
    assert _indexed(archive) == sum(map(len, more.values()))
    assert _found(archive) == more
    assert index_patient_links(archive) == 0  # nothing new


def test_a_run_that_fails_half_way_leaves_nothing_to_repair(
        archive: Archive, monkeypatch: pytest.MonkeyPatch) -> None:
    truth = _record_many(archive, 40, seed=3)
    real_finish = audit_index._finish

    def fail(conn: object, through: int) -> None:  # the last transaction breaks
        raise OSError("disk gone")

    monkeypatch.setattr(audit_index, "_finish", fail)
    with pytest.raises(OSError):
        index_patient_links(archive, chunk=5)
    # the mark has not moved, the lease was given back; on SQLite the earlier chunks are
    # in (PostgreSQL indexes a run in one transaction)
    sqlite = archive.engine.dialect.name == "sqlite"
    assert sqlite <= _indexed(archive) < sum(map(len, truth.values()))
    assert _mark(archive) == (0, None)
    assert _found(archive) == truth

    monkeypatch.setattr(audit_index, "_finish", real_finish)
    index_patient_links(archive, chunk=5)  # redoes the run; the links already in are skipped
    assert _indexed(archive) == sum(map(len, truth.values()))
    assert _mark(archive)[0] == 40
    assert _found(archive) == truth


def test_one_indexer_at_a_time_and_an_expired_lease_is_taken_over(archive: Archive) -> None:
    _record_many(archive, 10, seed=4)
    later = dt.datetime.now(dt.UTC) + dt.timedelta(minutes=5)
    with archive.engine.begin() as conn:
        conn.execute(update(AuditIndexMark).values(lease_until=later))
    assert index_patient_links(archive) == 0
    assert _mark(archive)[0] == 0
    with archive.engine.begin() as conn:  # the holder died a while ago
        conn.execute(update(AuditIndexMark).values(
            lease_until=dt.datetime.now(dt.UTC) - dt.timedelta(seconds=1)))
    assert index_patient_links(archive) > 0
    assert _mark(archive) == (10, None)


def test_the_index_is_append_only(archive: Archive) -> None:
    _record_many(archive, 10, seed=5)
    index_patient_links(archive)
    assert _indexed(archive) > 0
    for statement in ("DELETE FROM audit_patient_index",
                      "UPDATE audit_patient_index SET event_id = event_id + 1000"):
        with pytest.raises(Exception, match="append-only"), archive.engine.begin() as conn:
            conn.execute(text(statement))


def test_events_without_patients_move_the_mark(archive: Archive) -> None:
    insert_records(archive, [_record(set()) for _ in range(3)])
    assert index_patient_links(archive) == 0
    assert _mark(archive) == (3, None)


def test_the_indexer_thread_runs_and_stops(archive: Archive) -> None:
    truth = _record_many(archive, 30, seed=6)
    indexer = AuditIndexer(archive, every_s=0.05)
    try:
        deadline = time.monotonic() + 10
        while _mark(archive)[0] < 30 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        started = time.monotonic()
        indexer.close()
        assert time.monotonic() - started < 5
    assert _mark(archive)[0] == 30
    assert _indexed(archive) == sum(map(len, truth.values()))


def test_postgresql_mark_never_passes_an_event_still_being_committed(
        postgres_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Sequence ids commit in any order on PostgreSQL: an event that drew its id before a
    newer one committed must not fall behind the mark unindexed. (SQLite's writers take
    turns, so its ids commit in order.)"""
    settings = Settings(archive=tmp_path / "archive", database_url=postgres_url)
    # long enough to see the indexer wait for the open transaction (by default it gives
    # way after LOCK_WAIT_MS: the next test)
    monkeypatch.setattr(audit_index, "LOCK_WAIT_MS", 20_000)
    with Archive.create(settings) as archive:
        patient = archive.add_patient("P-slow").id
        slow = archive.engine.connect()
        tx = slow.begin()
        slow.execute(text(
            "INSERT INTO audit_event (request_id, recorded_at, actor, actor_kind, role, action, "
            "method, route, status, client, detail) VALUES ('slow', now(), 'dr', 'user', "
            "'clinician', 'R', 'GET', '/x', 200, '', '')"))
        slow_id = slow.execute(text("SELECT max(id) FROM audit_event")).scalar()
        insert_records(archive, [_record({patient})])  # a newer event commits first
        result: list[int] = []
        runner = threading.Thread(target=lambda: result.append(index_patient_links(archive)))
        runner.start()
        runner.join(0.5)
        assert runner.is_alive(), "the indexer must wait for the open audit transaction"
        slow.execute(text("INSERT INTO audit_event_patient (event_id, patient_id) "
                          "VALUES (:e, :p)"), {"e": slow_id, "p": patient})
        tx.commit()
        slow.close()
        runner.join(10)
        assert not runner.is_alive()
        assert result == [2]
        found = [e.id for e, _ in audit_events(archive, patient="P-slow")]
        assert slow_id in found and len(found) == 2
        with archive.engine.connect() as conn:
            indexed = conn.execute(select(AuditPatientIndex.event_id)).scalars().all()
        assert slow_id in indexed


def test_sqlite_connections_go_back_to_the_pool_with_full_sync(tmp_path: Path) -> None:
    """The indexer commits its chunks without fsync (NORMAL); the connection it used must
    not carry that to the next user, who expects every commit flushed (FULL = 2)."""
    from rasterserver.config import sqlite_url

    root = tmp_path / "archive"
    settings = Settings(archive=root, database_url=sqlite_url(root))
    Archive.create(settings).close()
    with Archive(settings, connections=1) as archive:  # one pooled connection: reused
        archive.add_patient("P-0")
        insert_records(archive, [_record({1})])
        with archive.engine.connect() as conn:
            first = conn.connection.driver_connection
        assert index_patient_links(archive) == 1
        with archive.engine.connect() as conn:
            assert conn.connection.driver_connection is first
            assert conn.exec_driver_sql("PRAGMA synchronous").scalar() == 2


def test_postgresql_indexer_gives_way_to_a_lock_it_cannot_get_soon(
        postgres_url: str, tmp_path: Path) -> None:
    """Audit writers queue behind the indexer's waiting lock request, so it waits only
    briefly (an anti-wraparound vacuum, say, would not yield) and tries again next run."""
    settings = Settings(archive=tmp_path / "archive", database_url=postgres_url)
    with Archive.create(settings) as archive:
        patient = archive.add_patient("P-0").id
        insert_records(archive, [_record({patient})])
        holder = archive.engine.connect()
        tx = holder.begin()
        holder.execute(text("LOCK TABLE audit_event IN SHARE UPDATE EXCLUSIVE MODE"))
        try:
            started = time.monotonic()
            assert index_patient_links(archive) == 0
            assert time.monotonic() - started < 5
            assert _mark(archive) == (0, None)  # nothing moved, the lease given back
        finally:
            tx.rollback()
            holder.close()
        assert index_patient_links(archive) == 1
        assert _mark(archive)[0] == 1
