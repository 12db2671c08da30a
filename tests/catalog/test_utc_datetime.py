"""Times keep their instant on both catalogues: offsets converted to UTC, read back in UTC."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pytest
from sqlalchemy import select, text

from rasterserver.archive import Archive, FrameSource
from rasterserver.catalog.auth_models import ApiToken
from rasterserver.catalog.models import Acquisition, Patient, Visit
from rasterserver.catalog.utc_datetime import NaiveDatetimeError
from rasterserver.config import Settings
from rasterserver.errors import InputError
from rasterserver.optics import default_station
from rasterserver.services import auth

PLUS_FIVE = dt.timezone(dt.timedelta(hours=5))
#: the instant of 2025-03-01T10:15+05:00
INSTANT = dt.datetime(2025, 3, 1, 5, 15, tzinfo=dt.UTC)


@pytest.fixture
def archive(settings: Settings) -> Archive:
    arch = Archive.create(settings)
    arch.add_patient("P-1")
    yield arch
    arch.close()


def _ingest(archive: Archive, when: dt.datetime) -> str:
    frame = np.random.default_rng(7).integers(0, 255, (8, 8), dtype=np.uint8)
    return archive.ingest([FrameSource(frame, name="f")], patient="P-1", acquired_at=when).uid


def test_an_offset_is_stored_as_its_instant_and_read_back_in_utc(archive: Archive) -> None:
    uid = _ingest(archive, dt.datetime(2025, 3, 1, 10, 15, tzinfo=PLUS_FIVE))
    info = archive.info(uid)
    assert info.acquired_at == INSTANT and info.acquired_at.utcoffset() == dt.timedelta(0)
    row = archive.acquisition(uid)
    assert row.acquired_at == INSTANT and row.acquired_at.tzinfo is dt.UTC
    # what is in the database itself, not only what the type gives back
    with archive.engine.connect() as conn:
        stored = conn.execute(text("SELECT acquired_at FROM acquisition")).scalar_one()
    assert str(stored).startswith("2025-03-01 05:15:00")
    # the visit is the clinic's day: the date at the offset the time was given with
    late = _ingest(archive, dt.datetime(2025, 3, 2, 1, 0, tzinfo=PLUS_FIVE))
    with archive.session() as s:
        visit = s.scalar(select(Visit).join(Acquisition).where(Acquisition.uid == late))
    assert visit.visit_date == dt.date(2025, 3, 2)


def test_since_and_until_compare_instants(archive: Archive) -> None:
    uid = _ingest(archive, dt.datetime(2025, 3, 1, 10, 15, tzinfo=PLUS_FIVE))
    at = INSTANT.astimezone(dt.timezone(dt.timedelta(hours=-3)))  # 02:15-03:00, same instant
    assert [a.uid for a in archive.find(since=at)] == [uid]
    assert archive.find(since=at + dt.timedelta(seconds=1)) == []
    assert archive.find(until=at) == []
    assert [a.uid for a in archive.find(until=at + dt.timedelta(seconds=1))] == [uid]
    assert [a.uid for a in archive.acquisitions(since=at, until=INSTANT + dt.timedelta(1))] == [uid]


def test_every_time_column_reads_back_aware_utc(archive: Archive) -> None:
    auth.add_account(archive, "admin-1", role="admin")
    auth.create_token(archive, "admin-1")
    [token] = auth.tokens(archive)
    auth.revoke_token(archive, token.id)
    archive.add_station("st-1")
    cal = archive.add_calibration(
        "st-1", default_station().to_dict(), valid_from=dt.datetime(2025, 1, 1, 8, tzinfo=PLUS_FIVE)
    )
    with archive.session() as s:
        patient = s.scalar(select(Patient))
        token_row = s.scalar(select(ApiToken))
    assert patient.created_at.tzinfo is dt.UTC
    assert token_row.created_at.tzinfo is dt.UTC and token_row.revoked_at.tzinfo is dt.UTC
    assert archive.calibration("st-1").valid_from == dt.datetime(2025, 1, 1, 3, tzinfo=dt.UTC)
    assert cal.created_at.tzinfo is not None
    assert archive.patient_info("P-1").created_at.tzinfo is dt.UTC


def test_a_time_without_zone_is_refused_not_guessed(archive: Archive) -> None:
    naive = dt.datetime(2025, 3, 1, 10, 15)
    with pytest.raises(InputError, match="no time zone"):
        _ingest(archive, naive)
    with pytest.raises(InputError, match="no time zone"):
        archive.find(since=naive)
    archive.add_station("st-1")
    with pytest.raises(InputError, match="no time zone"):
        archive.add_calibration("st-1", default_station().to_dict(), valid_from=naive)
    # below the service, the column type itself refuses
    with pytest.raises(Exception) as caught, archive.session() as s:
        s.execute(select(Acquisition).where(Acquisition.acquired_at < naive)).all()
    assert isinstance(caught.value.__cause__ or caught.value, NaiveDatetimeError)


def test_postgresql_in_another_session_zone_still_reads_utc(postgres_url: str, tmp_path) -> None:
    settings = Settings(archive=tmp_path / "archive", database_url=postgres_url)
    Archive.create(settings).close()
    # a server or role configured for local time hands timestamptz back in that zone
    url = (
        postgres_url
        + ("&" if "?" in postgres_url else "?")
        + "options=-c%20timezone%3DAsia/Kolkata"
    )
    archive = Archive(Settings(archive=settings.archive, database_url=url))
    try:
        archive.add_patient("P-1")
        uid = _ingest(archive, dt.datetime(2025, 3, 1, 10, 15, tzinfo=PLUS_FIVE))
        with archive.engine.connect() as conn:
            assert conn.execute(text("SHOW timezone")).scalar_one() == "Asia/Kolkata"
        assert archive.info(uid).acquired_at.tzinfo is dt.UTC
        assert archive.info(uid).acquired_at == INSTANT
    finally:
        archive.close()


def test_stored_text_in_any_iso_form_reads_back_utc(archive: Archive) -> None:
    # rows written by hand or by earlier versions hold other ISO forms of the same UTC time
    with archive.engine.begin() as conn:
        for identifier, created in (("P-2", "2026-01-01"), ("P-3", "2026-01-02 03:04:05")):
            conn.execute(
                text(
                    "INSERT INTO patient (identifier, identifier_key, name, sex, created_at) "
                    "VALUES (:i, :i, '', 'unknown', :c)"
                ),
                {"i": identifier, "c": created},
            )
    assert archive.patient_info("P-2").created_at == dt.datetime(2026, 1, 1, tzinfo=dt.UTC)
    assert archive.patient_info("P-3").created_at == dt.datetime(2026, 1, 2, 3, 4, 5, tzinfo=dt.UTC)
    assert archive.patient_info("P-1").created_at.tzinfo is dt.UTC
