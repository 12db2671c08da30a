"""Catalogue tables of the HTTP API: accounts, API tokens, the audit trail, jobs.

Kept apart from :mod:`rasterserver.catalog.models` because they describe who may see the
archive, not what it holds. Tokens are stored only as SHA-256 digests: a copied database
grants no access. The researchers' pseudonym key is not here at all (migration 0010 moved
it out, see :mod:`rasterserver.pseudonym_key`): a copied database re-identifies no one.
Audit events are append-only: the ORM refuses to change or delete one, and the migration
adds database triggers that refuse it too (so neither a bug nor a hand-typed ``UPDATE``
rewrites history).
"""

from __future__ import annotations

import datetime as dt
from typing import Any

from sqlalchemy import (
    JSON,
    CheckConstraint,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    event,
)
from sqlalchemy.orm import Mapped, Session, mapped_column, relationship

from rasterserver.catalog.models import Base, utcnow

ROLES = ("admin", "clinician", "station", "researcher")
ACCOUNT_KINDS = ("user", "service")
#: FHIR AuditEvent.action codes: create, read, update, delete, execute.
AUDIT_ACTIONS = ("C", "R", "U", "D", "E")


class ApiAccount(Base):
    """A person (``user``) or a machine (``service``, e.g. an acquisition station)."""

    __tablename__ = "api_account"
    __table_args__ = (
        CheckConstraint(f"role IN {ROLES!r}", name="role"),
        CheckConstraint(f"kind IN {ACCOUNT_KINDS!r}", name="kind"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(100), unique=True)
    role: Mapped[str] = mapped_column(String(16))
    kind: Mapped[str] = mapped_column(String(8), default="user")
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    #: When the account was disabled (its tokens are refused); None while it is enabled.
    disabled_at: Mapped[dt.datetime | None] = mapped_column()

    tokens: Mapped[list[ApiToken]] = relationship(back_populates="account")


class ApiToken(Base):
    """A bearer token of an account; only its SHA-256 digest is kept.

    ``prefix`` (the first characters of the token) lets a person tell tokens apart in
    ``token list`` without the secret being stored.
    """

    __tablename__ = "api_token"

    id: Mapped[int] = mapped_column(primary_key=True)
    account_id: Mapped[int] = mapped_column(ForeignKey("api_account.id", ondelete="RESTRICT"))
    token_sha256: Mapped[str] = mapped_column(String(64), unique=True)
    prefix: Mapped[str] = mapped_column(String(16))
    label: Mapped[str] = mapped_column(String(100), default="")
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    revoked_at: Mapped[dt.datetime | None] = mapped_column()
    #: Refused from this time on. None (only tokens given no end by hand) never expires.
    expires_at: Mapped[dt.datetime | None] = mapped_column()

    account: Mapped[ApiAccount] = relationship(back_populates="tokens")


class AuditEvent(Base):
    """One request to the archive: who, what, when, from where, with what outcome.

    The patients whose data the request touched are :class:`AuditEventPatient` rows: a list
    of a hundred acquisitions is one event and a hundred two-integer links, not a hundred
    copies of the event. "Who saw patient X" is one range scan of :class:`AuditPatientIndex`.
    """

    __tablename__ = "audit_event"
    __table_args__ = (CheckConstraint(f"action IN {AUDIT_ACTIONS!r}", name="action"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    request_id: Mapped[str] = mapped_column(String(32), index=True)
    recorded_at: Mapped[dt.datetime] = mapped_column(default=utcnow, index=True)
    actor: Mapped[str] = mapped_column(String(100))
    actor_kind: Mapped[str] = mapped_column(String(8), default="")
    role: Mapped[str] = mapped_column(String(16), default="")
    action: Mapped[str] = mapped_column(String(1))
    method: Mapped[str] = mapped_column(String(8))
    # the route template, never the concrete path: that may carry a patient identifier
    route: Mapped[str] = mapped_column(String(200))
    status: Mapped[int] = mapped_column(Integer)
    # Only events recorded before migration 0004 (one row per patient then) have it; the
    # migration copied those into AuditEventPatient, which is where every query looks.
    patient_id: Mapped[int | None] = mapped_column(
        ForeignKey("patient.id", ondelete="RESTRICT")
    )
    acquisition_uid: Mapped[str | None] = mapped_column(String(32))
    client: Mapped[str] = mapped_column(String(100), default="")
    detail: Mapped[str] = mapped_column(Text, default="")


class AuditEventPatient(Base):
    """A patient whose data an :class:`AuditEvent` touched (append-only, like the event).

    Keyed by event first, so the links of a request are appended after those of the
    previous one: a commit of many requests' links touches a page or two. Keyed by patient
    (as before migration 0007), a list of a hundred patients wrote into a hundred places of
    the index, and every group commit rewrote hundreds of pages: a quarter of the server's
    work under load. "Who saw patient X" is answered by :class:`AuditPatientIndex`, which
    :mod:`rasterserver.services.audit_index` fills from these rows in large sorted batches.

    No foreign keys, on purpose. The links are written in the same transaction as their
    event, by one function, with patient ids just read from the catalogue; neither events
    nor patients are ever deleted. Checking the keys anyway cost PostgreSQL a shared lock on
    every patient row listed (40 % of the audit write under load, and contention between
    clinicians reading the same patients), and an audit trail should not depend on the rows
    it records staying as they are.
    """

    __tablename__ = "audit_event_patient"
    __table_args__ = ({"sqlite_with_rowid": False},)

    event_id: Mapped[int] = mapped_column(primary_key=True)
    patient_id: Mapped[int] = mapped_column(primary_key=True)


class AuditPatientIndex(Base):
    """The audit links by patient: "who saw patient X, when" is one range scan of the key.

    Derived from :class:`AuditEventPatient` (the record) by the audit indexer, which adds
    the links of the events after :attr:`AuditIndexMark.indexed_through`, sorted by patient
    and many at a time, so each page of this index is rewritten once per batch rather than
    once per request. Queries by patient read this table and the links after the mark, so
    they are complete whether or not the indexer has caught up. Append-only like the record.
    """

    __tablename__ = "audit_patient_index"
    __table_args__ = ({"sqlite_with_rowid": False},)

    patient_id: Mapped[int] = mapped_column(primary_key=True)
    event_id: Mapped[int] = mapped_column(primary_key=True)


class AuditIndexMark(Base):
    """How far :class:`AuditPatientIndex` is complete (a single row, ``id`` 1).

    Every link of the events up to ``indexed_through`` is in the index. ``lease_until`` lets
    one indexer at a time work (each server process runs one); a lease that has run out,
    of an indexer that died, is taken over.
    """

    __tablename__ = "audit_index_mark"

    id: Mapped[int] = mapped_column(primary_key=True)
    indexed_through: Mapped[int] = mapped_column(Integer, default=0)
    lease_until: Mapped[dt.datetime | None] = mapped_column()


JOB_STATUSES = ("queued", "running", "done", "failed")


class ApiJob(Base):
    """A processing job started over HTTP, kept in the catalogue so that any server worker
    can report it and it survives a restart.

    ``runner`` names the process running it (``host:pid``, see :mod:`rasterserver.runner`): a
    job whose runner is gone is reported as failed instead of running forever.
    """

    __tablename__ = "api_job"
    __table_args__ = (
        CheckConstraint(f"status IN {JOB_STATUSES!r}", name="status"),
        Index("ix_api_job_created_at", "created_at"),
    )

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    owner: Mapped[str] = mapped_column(String(100))
    uids: Mapped[list[str]] = mapped_column(JSON)
    status: Mapped[str] = mapped_column(String(16), default="queued")
    done: Mapped[int] = mapped_column(Integer, default=0)
    total: Mapped[int] = mapped_column(Integer, default=0)
    runner: Mapped[str] = mapped_column(String(300), default="")
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    finished_at: Mapped[dt.datetime | None] = mapped_column()
    error: Mapped[str] = mapped_column(Text, default="")
    outcomes: Mapped[list[dict[str, Any]]] = mapped_column(JSON, default=list)


@event.listens_for(Session, "before_flush")
def _audit_is_append_only(session: Session, _ctx: object, _instances: object) -> None:
    """Refuse to change or delete an audit event through the ORM."""
    for obj in (*session.dirty, *session.deleted):
        if isinstance(obj, AuditEvent | AuditEventPatient | AuditPatientIndex):
            raise ValueError("audit events are append-only")
