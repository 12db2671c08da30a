"""SQLAlchemy 2.0 typed models of the catalogue.

Times are stored in UTC and read back as aware UTC datetimes on both backends
(:class:`~rasterserver.catalog.utc_datetime.UtcDateTime`). Pixel data never lives here: a
:class:`Frame` row names the HDF5 file and dataset holding it, with the SHA-256 of its bytes
so ``verify`` can prove the two agree.
"""

from __future__ import annotations

import datetime as dt
from typing import Any, ClassVar

from sqlalchemy import (
    JSON,
    CheckConstraint,
    Date,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    String,
    Text,
    UniqueConstraint,
    event,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, relationship

from rasterserver.catalog.utc_datetime import UtcDateTime
from rasterserver.catalog.vocabulary import ACQUISITION_KINDS, SEXES
from rasterserver.catalog.vocabulary import FRAME_ROLES as FRAME_ROLES  # re-exported
from rasterserver.identifiers import lookup_key

# Explicit constraint names keep migrations identical on SQLite and PostgreSQL and let
# Alembic's batch mode (SQLite) find constraints it has to rebuild.
NAMING_CONVENTION = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}



def utcnow() -> dt.datetime:
    """Return the current time in UTC (timezone-aware)."""
    return dt.datetime.now(dt.UTC)


class Base(DeclarativeBase):
    """Declarative base of every catalogue table."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map: ClassVar[dict[Any, Any]] = {
        dict[str, Any]: JSON,
        dt.datetime: UtcDateTime(),
    }


def _identifier_key(context: Any) -> str:
    return lookup_key(context.get_current_parameters()["identifier"])


class Patient(Base):
    """A patient, identified by the site's own identifier (unique within the site).

    ``identifier_key`` is the identifier's comparison key
    (:func:`~rasterserver.identifiers.lookup_key`: case and look-alike characters folded),
    unique, so ``p-1`` cannot be registered beside ``P-1``. It is NULL only for a patient
    registered before revision 0009 whose key another, older patient already had (see there).
    """

    __tablename__ = "patient"
    __table_args__ = (
        CheckConstraint(f"sex IN {SEXES!r}", name="sex"),
        Index("ix_patient_identifier_key", "identifier_key", unique=True),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    identifier: Mapped[str] = mapped_column(String(64), unique=True)
    identifier_key: Mapped[str | None] = mapped_column(String(255), default=_identifier_key)
    name: Mapped[str] = mapped_column(String(200), default="")
    birth_date: Mapped[dt.date | None] = mapped_column(Date)
    sex: Mapped[str] = mapped_column(String(8), default="unknown")
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)

    visits: Mapped[list[Visit]] = relationship(back_populates="patient")
    acquisitions: Mapped[list[Acquisition]] = relationship(back_populates="patient")


class Visit(Base):
    """One appointment of a patient; a visit may hold several acquisitions."""

    __tablename__ = "visit"
    __table_args__ = (UniqueConstraint("patient_id", "visit_date"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    patient_id: Mapped[int] = mapped_column(ForeignKey("patient.id", ondelete="RESTRICT"))
    visit_date: Mapped[dt.date] = mapped_column(Date)
    notes: Mapped[str] = mapped_column(Text, default="")

    patient: Mapped[Patient] = relationship(back_populates="visits")


class Station(Base):
    """An acquisition set-up: one camera and one projector in a fixed arrangement."""

    __tablename__ = "station"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(100), unique=True)
    description: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)

    calibrations: Mapped[list[Calibration]] = relationship(back_populates="station")


class Raster(Base):
    """A raster diapositive: line positions and light/heavy kinds (``rasterserver.raster/1``).

    ``sha256`` is the hash of the canonical JSON definition, so the same diapositive stored
    twice is recognised.
    """

    __tablename__ = "raster"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(100), unique=True)
    definition: Mapped[dict[str, Any]] = mapped_column(JSON)
    sha256: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)


class Calibration(Base):
    """An immutable, versioned calibration of a station (``rasterserver.calibration/1``).

    Versions count up per station. Rows are never updated: a recalibration is a new version,
    so every acquisition keeps the calibration it was taken with.
    """

    __tablename__ = "calibration"
    __table_args__ = (UniqueConstraint("station_id", "version"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    station_id: Mapped[int] = mapped_column(ForeignKey("station.id", ondelete="RESTRICT"))
    version: Mapped[int] = mapped_column(Integer)
    raster_id: Mapped[int | None] = mapped_column(ForeignKey("raster.id", ondelete="RESTRICT"))
    parameters: Mapped[dict[str, Any]] = mapped_column(JSON)
    residuals: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    sha256: Mapped[str] = mapped_column(String(64))
    valid_from: Mapped[dt.datetime] = mapped_column(default=utcnow)
    # The control-point frames it was computed from, archived like any acquisition.
    source_acquisition_id: Mapped[int | None] = mapped_column(
        ForeignKey("acquisition.id", ondelete="RESTRICT", use_alter=True)
    )
    notes: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)

    station: Mapped[Station] = relationship(back_populates="calibrations")
    raster: Mapped[Raster | None] = relationship()


class Acquisition(Base):
    """One recording: the frames taken together of a patient (or a calibration body).

    ``uid`` names the acquisition's HDF5 file; it is chosen at ingest and never reused.
    """

    __tablename__ = "acquisition"
    __table_args__ = (
        CheckConstraint(f"kind IN {ACQUISITION_KINDS!r}", name="kind"),
        CheckConstraint("kind <> 'patient' OR patient_id IS NOT NULL", name="patient_required"),
        Index("ix_acquisition_patient_time", "patient_id", "acquired_at"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    uid: Mapped[str] = mapped_column(String(32), unique=True)
    kind: Mapped[str] = mapped_column(String(16), default="patient")
    patient_id: Mapped[int | None] = mapped_column(
        ForeignKey("patient.id", ondelete="RESTRICT")
    )
    visit_id: Mapped[int | None] = mapped_column(ForeignKey("visit.id", ondelete="RESTRICT"))
    station_id: Mapped[int | None] = mapped_column(ForeignKey("station.id", ondelete="RESTRICT"))
    calibration_id: Mapped[int | None] = mapped_column(
        ForeignKey("calibration.id", ondelete="RESTRICT")
    )
    acquired_at: Mapped[dt.datetime] = mapped_column(index=True)
    operator: Mapped[str] = mapped_column(String(100), default="")
    notes: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)

    patient: Mapped[Patient | None] = relationship(back_populates="acquisitions")
    visit: Mapped[Visit | None] = relationship()
    station: Mapped[Station | None] = relationship()
    calibration: Mapped[Calibration | None] = relationship(foreign_keys=[calibration_id])
    frames: Mapped[list[Frame]] = relationship(
        back_populates="acquisition", order_by="Frame.index", cascade="all, delete-orphan"
    )


class Frame(Base):
    """One raw camera frame of an acquisition, as stored in the acquisition's HDF5 file."""

    __tablename__ = "frame"
    __table_args__ = (UniqueConstraint("acquisition_id", "index"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    acquisition_id: Mapped[int] = mapped_column(
        ForeignKey("acquisition.id", ondelete="CASCADE")
    )
    index: Mapped[int] = mapped_column(Integer)
    role: Mapped[str] = mapped_column(String(32), default="raster")
    height: Mapped[int] = mapped_column(Integer)
    width: Mapped[int] = mapped_column(Integer)
    dtype: Mapped[str] = mapped_column(String(16))
    sha256: Mapped[str] = mapped_column(String(64))
    store_path: Mapped[str] = mapped_column(String(255))
    dataset: Mapped[str] = mapped_column(String(100))

    acquisition: Mapped[Acquisition] = relationship(back_populates="frames")


class IngestKey(Base):
    """An idempotency key under which a source (a station's account, the CLI) stored an
    acquisition: a retried upload finds it here instead of being stored twice.

    Written in the same transaction as the acquisition, so a key never names a missing
    acquisition, and of two concurrent uploads under one key only one commits.
    """

    __tablename__ = "ingest_key"

    source: Mapped[str] = mapped_column(String(100), primary_key=True)
    key: Mapped[str] = mapped_column(String(100), primary_key=True)
    acquisition_id: Mapped[int] = mapped_column(
        ForeignKey("acquisition.id", ondelete="CASCADE")
    )
    # of the frames' bytes and the metadata: the same key for another upload is refused
    request_sha256: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)


@event.listens_for(Session, "before_flush")
def _calibrations_are_immutable(session: Session, _ctx: object, _instances: object) -> None:
    """Refuse any change to a stored calibration: a recalibration is a new version."""
    for obj in session.dirty:
        if isinstance(obj, Calibration) and session.is_modified(obj):
            raise ValueError(
                f"calibration {obj.id} (version {obj.version}) is immutable; "
                "store a new version instead"
            )


# --- pipeline provenance -----------------------------------------------------------------------

RUN_STATUSES = ("running", "done", "failed")


class PipelineRun(Base):
    """One request to process an acquisition through a chain of stages.

    ``chain`` lists, per stage in order, the kind, plugin, algorithm version and parameters
    hash used. A run that reuses every stored result still gets a row (``computed = 0``), so
    the log of who asked for what is complete.

    ``runner`` names the process doing the run. A ``running`` run whose runner is gone (the
    process was killed) is marked ``failed`` with an error beginning ``interrupted:``, and
    ``finished_at`` when that was noticed (see migration 0008 for why not a status of its own).
    """

    __tablename__ = "pipeline_run"
    __table_args__ = (
        CheckConstraint(f"status IN {RUN_STATUSES!r}", name="status"),
        Index("ix_pipeline_run_acquisition_started", "acquisition_id", "started_at"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    acquisition_id: Mapped[int] = mapped_column(
        ForeignKey("acquisition.id", ondelete="RESTRICT")
    )
    calibration_id: Mapped[int | None] = mapped_column(
        ForeignKey("calibration.id", ondelete="RESTRICT")
    )
    chain: Mapped[list[dict[str, Any]]] = mapped_column(JSON)
    status: Mapped[str] = mapped_column(String(16), default="running")
    started_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    finished_at: Mapped[dt.datetime | None] = mapped_column()
    error: Mapped[str] = mapped_column(Text, default="")
    host: Mapped[str] = mapped_column(String(255), default="")
    # the process doing it (rasterserver.runner); empty for runs recorded before revision 0008
    runner: Mapped[str] = mapped_column(String(300), default="", server_default="")
    package_version: Mapped[str] = mapped_column(String(64), default="")
    computed: Mapped[int] = mapped_column(Integer, default=0)
    reused: Mapped[int] = mapped_column(Integer, default=0)

    acquisition: Mapped[Acquisition] = relationship()
    calibration: Mapped[Calibration | None] = relationship()


class StageResult(Base):
    """One stored stage output of an acquisition, with everything needed to trust and reuse it.

    ``chain_key`` is the SHA-256 over the frame's checksum and, for this stage and every one
    before it, the plugin name, algorithm version, parameters hash and (for stages that use
    them) the calibration and raster checksums: asking for the same computation again finds
    this row instead of recomputing. Rows are never updated; reprocessing with other plugins,
    parameters or a new calibration adds rows beside the old ones.
    """

    __tablename__ = "stage_result"
    __table_args__ = (
        UniqueConstraint("acquisition_id", "chain_key"),
        Index("ix_stage_result_acquisition_stage", "acquisition_id", "stage"),
        # deleting a result or a run checks that no result names it (prune): a lookup each
        Index("ix_stage_result_parent", "parent_id"),
        Index("ix_stage_result_run", "run_id"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    acquisition_id: Mapped[int] = mapped_column(
        ForeignKey("acquisition.id", ondelete="RESTRICT")
    )
    run_id: Mapped[int | None] = mapped_column(ForeignKey("pipeline_run.id", ondelete="RESTRICT"))
    parent_id: Mapped[int | None] = mapped_column(
        ForeignKey("stage_result.id", ondelete="RESTRICT")
    )
    calibration_id: Mapped[int | None] = mapped_column(
        ForeignKey("calibration.id", ondelete="RESTRICT")
    )
    frame_index: Mapped[int] = mapped_column(Integer)
    stage: Mapped[str] = mapped_column(String(32))
    plugin: Mapped[str] = mapped_column(String(100))
    plugin_version: Mapped[str] = mapped_column(String(32))
    plugin_package: Mapped[str] = mapped_column(String(200), default="")
    params: Mapped[dict[str, Any]] = mapped_column(JSON)
    params_hash: Mapped[str] = mapped_column(String(64))
    chain_key: Mapped[str] = mapped_column(String(64))
    input_checksum: Mapped[str] = mapped_column(String(64))
    output_checksum: Mapped[str] = mapped_column(String(64))
    record_kind: Mapped[str] = mapped_column(String(32))
    store_path: Mapped[str] = mapped_column(String(255))
    reason: Mapped[str] = mapped_column(Text, default="")
    package_version: Mapped[str] = mapped_column(String(64), default="")
    host: Mapped[str] = mapped_column(String(255), default="")
    duration_s: Mapped[float] = mapped_column(default=0.0)
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)

    acquisition: Mapped[Acquisition] = relationship()
    calibration: Mapped[Calibration | None] = relationship()
    run: Mapped[PipelineRun | None] = relationship()


class StageResultInput(Base):
    """One input of a result computed from several acquisitions (a comparison of visits).

    A single-acquisition result names its input by ``parent_id``; a result of a stage whose
    input comes from several acquisitions has one row here per input result (``role`` says
    which: ``a.mesh``, ``b.analysis``, ...). Deleting an input result is refused while a
    result computed from it exists.
    """

    __tablename__ = "stage_result_input"
    __table_args__ = (Index("ix_stage_result_input_input", "input_id"),)

    result_id: Mapped[int] = mapped_column(
        ForeignKey("stage_result.id", ondelete="RESTRICT"), primary_key=True
    )
    position: Mapped[int] = mapped_column(Integer, primary_key=True)
    role: Mapped[str] = mapped_column(String(32))
    input_id: Mapped[int] = mapped_column(ForeignKey("stage_result.id", ondelete="RESTRICT"))
    acquisition_id: Mapped[int] = mapped_column(ForeignKey("acquisition.id", ondelete="RESTRICT"))
