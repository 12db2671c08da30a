"""The schema exists only through migrations, and the migrations agree with the models."""

from __future__ import annotations

from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect

from rasterserver.catalog import auth_models as _auth_models  # noqa: F401  (its tables)
from rasterserver.catalog import job_models as _job_models  # noqa: F401  (its tables)
from rasterserver.catalog import migrate
from rasterserver.catalog.database import make_engine
from rasterserver.catalog.models import Base


def test_upgrade_creates_every_table_and_models_match(database_url: str) -> None:
    engine = make_engine(database_url)
    assert migrate.current_revision(engine) is None
    migrate.upgrade(engine)
    assert migrate.current_revision(engine) == migrate.head_revision(engine)
    tables = set(inspect(engine).get_table_names())
    assert set(Base.metadata.tables) <= tables
    with engine.connect() as conn:
        ctx = MigrationContext.configure(conn, opts={"compare_type": True})
        diff = compare_metadata(ctx, Base.metadata)
    assert diff == [], f"models and migrations disagree: {diff}"
    engine.dispose()


def test_downgrade_to_base_and_up_again(database_url: str) -> None:
    engine = make_engine(database_url)
    migrate.upgrade(engine)
    migrate.downgrade(engine, "base")
    assert migrate.current_revision(engine) is None
    assert not set(Base.metadata.tables) & set(inspect(engine).get_table_names())
    migrate.upgrade(engine)
    assert migrate.current_revision(engine) == migrate.head_revision(engine)
    engine.dispose()


def test_require_current_names_the_command_to_run(database_url: str) -> None:
    engine = make_engine(database_url)
    with pytest.raises(migrate.SchemaError, match="rasterserver db upgrade"):
        migrate.require_current(engine)
    migrate.upgrade(engine)
    migrate.require_current(engine)
    engine.dispose()


def test_0004_links_the_patients_of_recorded_events_and_guards_its_downgrade(
    database_url: str, tmp_path: Path,
) -> None:
    from sqlalchemy import text

    from rasterserver.archive import Archive
    from rasterserver.config import Settings
    from rasterserver.services.audit import AuditNote, write_events
    from rasterserver.services.audit_trail import audit_events
    from rasterserver.services.auth import Principal

    engine = make_engine(database_url)
    migrate.upgrade(engine, "0003")
    event = ("INSERT INTO audit_event (request_id, recorded_at, actor, actor_kind, role, "
             "action, method, route, status, patient_id, client, detail) VALUES ('r1', "
             "'2026-01-02 03:04:05', 'dr', 'user', 'clinician', 'R', 'GET', '/acquisitions', "
             "200, {}, '', '')")
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO patient (identifier, name, sex, created_at) VALUES "
                          "('P-1', '', 'unknown', '2026-01-01'), "
                          "('P-2', '', 'unknown', '2026-01-01')"))
        p1, p2 = conn.execute(text("SELECT id FROM patient ORDER BY identifier")).scalars()
        # before 0004 a list touching two patients was two rows; a refusal had none
        for pid in (p1, p2, "NULL"):
            conn.execute(text(event.format(pid)))
    migrate.upgrade(engine)
    archive = Archive(Settings(archive=tmp_path / "archive", database_url=database_url))
    try:
        events = audit_events(archive)
        assert [who for _, who in events] == [["P-1"], ["P-2"], []]
        assert [e.id for e, _ in audit_events(archive, patient="P-2")] == [events[1][0].id]
        with pytest.raises(Exception, match="append-only"), engine.begin() as conn:
            conn.execute(text("DELETE FROM audit_event_patient"))
        # downgrading to 0003 with nothing recorded since would lose nothing...
        migrate.downgrade(engine, "0003")
        migrate.upgrade(engine)
        # ...but an event recorded since names its patients only in the links
        write_events(archive, AuditNote(principal=Principal(1, "dr", "clinician", "user"),
                                        patient_ids={p1, p2}),
                     method="GET", route="/acquisitions", route_name="list_acquisitions",
                     status=200, client="")
        assert audit_events(archive)[-1][1] == ["P-1", "P-2"]
        with pytest.raises(RuntimeError, match="would lose"):
            migrate.downgrade(engine, "0003")
        assert migrate.current_revision(engine) == migrate.head_revision(engine)
    finally:
        archive.close()
        engine.dispose()


def test_0007_rekeys_the_links_and_indexes_those_recorded(database_url: str) -> None:
    from sqlalchemy import text

    engine = make_engine(database_url)
    migrate.upgrade(engine, "0006")
    with engine.begin() as conn:
        for n in range(3):
            conn.execute(text(
                "INSERT INTO audit_event (request_id, recorded_at, actor, actor_kind, role, "
                "action, method, route, status, client, detail) VALUES "
                f"('r{n}', '2026-01-02 03:04:05', 'dr', 'user', 'clinician', 'R', 'GET', "
                "'/acquisitions', 200, '', '')"))
        events = conn.execute(text("SELECT id FROM audit_event ORDER BY id")).scalars().all()
        links = [(7, events[0]), (3, events[0]), (7, events[2])]
        for patient, event in links:
            conn.execute(text("INSERT INTO audit_event_patient (patient_id, event_id) "
                              "VALUES (:p, :e)"), {"p": patient, "e": event})
    migrate.upgrade(engine)

    def rows(table: str) -> list[tuple[int, int]]:
        with engine.connect() as conn:
            return sorted(conn.execute(text(f"SELECT patient_id, event_id FROM {table}")).all())

    assert rows("audit_event_patient") == sorted(links)
    assert rows("audit_patient_index") == sorted(links)
    with engine.connect() as conn:
        assert conn.execute(text("SELECT indexed_through FROM audit_index_mark")).all() == [
            (events[-1],)]
    key = inspect(engine).get_pk_constraint("audit_event_patient")["constrained_columns"]
    assert key == ["event_id", "patient_id"]
    with pytest.raises(Exception, match="append-only"), engine.begin() as conn:
        conn.execute(text("DELETE FROM audit_event_patient"))

    migrate.downgrade(engine, "0006")  # the index is derived: nothing is lost
    assert rows("audit_event_patient") == sorted(links)
    key = inspect(engine).get_pk_constraint("audit_event_patient")["constrained_columns"]
    assert key == ["patient_id", "event_id"]
    with pytest.raises(Exception, match="append-only"), engine.begin() as conn:
        conn.execute(text("DELETE FROM audit_event_patient"))
    engine.dispose()


def test_0008_names_the_runner_of_pipeline_runs_and_goes_back(database_url: str) -> None:
    from sqlalchemy import text

    engine = make_engine(database_url)
    migrate.upgrade(engine, "0007")
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO acquisition (uid, kind, acquired_at, operator, notes, "
                          "created_at) VALUES ('a1', 'test', '2026-01-01', '', '', "
                          "'2026-01-01')"))
        acq = conn.execute(text("SELECT id FROM acquisition")).scalar_one()
        run = ("INSERT INTO pipeline_run (acquisition_id, chain, status, started_at, error, "
               "host, package_version, computed, reused{}) VALUES (:a, '[]', 'running', "
               "'2026-01-01', '', 'h', '', 0, 0{})")
        conn.execute(text(run.format("", "")), {"a": acq})
        old = conn.execute(text("SELECT id FROM pipeline_run")).scalar_one()
        # a result refers to the run: neither direction may need to rebuild pipeline_run
        conn.execute(text(
            "INSERT INTO stage_result (acquisition_id, run_id, frame_index, stage, plugin, "
            "plugin_version, plugin_package, params, params_hash, chain_key, input_checksum, "
            "output_checksum, record_kind, store_path, reason, package_version, host, "
            "duration_s, created_at) VALUES (:a, :r, 0, 'peaks', 'p', '1', '', '{}', 'x', "
            "'k', 'i', 'o', 'peaks', 'derived/x.h5', '', '', 'h', 0, '2026-01-01')"),
            {"a": acq, "r": old})
    migrate.upgrade(engine)
    with engine.begin() as conn:
        # runs recorded before name no process
        assert conn.execute(text("SELECT runner FROM pipeline_run")).scalar_one() == ""
        conn.execute(text(run.format(", runner", ", 'h:12@b/3'")), {"a": acq})
    assert "runner" in {c["name"] for c in inspect(engine).get_columns("pipeline_run")}
    migrate.downgrade(engine, "0007")
    assert "runner" not in {c["name"] for c in inspect(engine).get_columns("pipeline_run")}
    with engine.connect() as conn:
        assert conn.execute(text("SELECT COUNT(*) FROM pipeline_run")).scalar_one() == 2
        assert conn.execute(text("SELECT run_id FROM stage_result")).scalar_one() == old
    migrate.upgrade(engine)
    assert migrate.current_revision(engine) == migrate.head_revision(engine)
    engine.dispose()


def test_0009_keys_patients_and_keeps_earlier_look_alikes_apart(
    database_url: str, tmp_path: Path,
) -> None:
    import numpy as np
    from sqlalchemy import text

    from rasterserver.archive import Archive, FrameSource
    from rasterserver.config import Settings
    from rasterserver.errors import ConflictError

    engine = make_engine(database_url)
    migrate.upgrade(engine, "0008")
    # registered before the rules: look-alikes of each other, a '/', a newline
    legacy = ["\u00e9", "e\u0301", "P-1", "p-1", "SL/01", "a\nb"]
    with engine.begin() as conn:
        for identifier in legacy:
            conn.execute(text("INSERT INTO patient (identifier, name, sex, created_at) VALUES "
                              "(:i, '', 'unknown', '2026-01-01')"), {"i": identifier})
    migrate.upgrade(engine)
    with engine.connect() as conn:
        keys = dict(conn.execute(text("SELECT identifier, identifier_key FROM patient")).all())
    # the oldest of each group has the key, the later look-alike none
    assert keys == {"\u00e9": "\u00e9", "e\u0301": None, "P-1": "p-1", "p-1": None,
                    "SL/01": "sl/01", "a\nb": "a\nb"}
    archive = Archive(Settings(archive=tmp_path / "archive", database_url=database_url))
    try:
        # every stored patient is still found under its exact identifier, and only it
        for identifier in legacy:
            assert archive.patient(identifier).identifier == identifier
            assert archive.patient_info(identifier).identifier == identifier
        frame = np.zeros((4, 4), np.uint8)
        uid = archive.ingest([FrameSource(frame)], patient="e\u0301").uid
        assert [a.uid for a in archive.find(patient="e\u0301")] == [uid]
        assert archive.find(patient="\u00e9") == []
        # a look-up that is neither exact goes by the key: to the oldest
        assert archive.patient("E\u0301").identifier == "\u00e9"
        with pytest.raises(ConflictError):
            archive.add_patient("\uff30-1")
    finally:
        archive.close()
    migrate.downgrade(engine, "0008")
    assert "identifier_key" not in {c["name"] for c in inspect(engine).get_columns("patient")}
    migrate.upgrade(engine)
    assert migrate.current_revision(engine) == migrate.head_revision(engine)
    engine.dispose()


def test_0013_indexes_the_references_a_deleted_result_is_checked_against(
    database_url: str,
) -> None:
    # deleting a result (prune) or a run checks that no result names it: without these
    # indexes each check read the whole table (70,000 results: not done in 13 minutes)
    engine = make_engine(database_url)
    migrate.upgrade(engine, "0012")
    indexed = {tuple(ix["column_names"]) for ix in inspect(engine).get_indexes("stage_result")}
    assert ("parent_id",) not in indexed and ("run_id",) not in indexed
    migrate.upgrade(engine)
    indexed = {tuple(ix["column_names"]) for ix in inspect(engine).get_indexes("stage_result")}
    assert {("parent_id",), ("run_id",)} <= indexed
    migrate.downgrade(engine, "0012")
    indexed = {tuple(ix["column_names"]) for ix in inspect(engine).get_indexes("stage_result")}
    assert ("parent_id",) not in indexed
    engine.dispose()
