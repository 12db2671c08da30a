"""Processing jobs in the catalogue: a job row and one task row per acquisition.

A job (``rasterserver process``, ``POST /jobs``) is created with every acquisition it will
process already resolved into task rows, in one transaction, so the job is the catalogue's
and not its coordinator's: a coordinator killed mid-job leaves the rows, and
``rasterserver jobs resume`` runs the tasks still ``pending``. A task is marked ``done`` only
after its results are committed; a coordinator killed between the two redoes that task, and
redoing finds every result stored under its chain key (:mod:`rasterserver.pipeline`), so
nothing is computed or stored twice.

Schema: migration 0012.
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
)
from sqlalchemy.orm import Mapped, mapped_column

from rasterserver.catalog.models import Base, utcnow

#: A job's states. ``queued``: created, no coordinator yet; ``running``: a coordinator
#: (``runner``) works on it; ``paused``: stopped on request, resumable; ``cancelled``: stopped
#: for good; ``done``: every task done; ``failed``: finished with failed tasks, or stopped by
#: an error of the job as a whole (its pending tasks can be resumed).
JOB_STATES = ("queued", "running", "paused", "cancelled", "done", "failed")
#: A task's states.
TASK_STATES = ("pending", "done", "failed")


class ProcessingJob(Base):
    """A processing job over many acquisitions.

    ``selection`` is what was asked for (uids, patient, dates, station, plugin version, ...),
    the task rows are what it resolved to. ``chain`` holds the request (plugin per stage
    kind, parameters, calibration) and, per target, the resolved steps with their plugin
    versions and parameters: a resume refuses to continue with other versions. ``done``,
    ``failed`` count finished tasks (``total - done - failed`` are left); they are updated in
    the transaction that finishes each task. ``resumed_at`` and ``resumed_count`` are when
    the current (or last) coordinator took the job and how many tasks were finished then,
    for its rate.
    """

    __tablename__ = "processing_job"
    __table_args__ = (
        CheckConstraint(f"state IN {JOB_STATES!r}", name="state"),
        Index("ix_processing_job_created_at", "created_at"),
        Index("ix_processing_job_state", "state"),
    )

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    origin: Mapped[str] = mapped_column(String(16))
    owner: Mapped[str] = mapped_column(String(100))
    selection: Mapped[dict[str, Any]] = mapped_column(JSON)
    chain: Mapped[dict[str, Any]] = mapped_column(JSON)
    targets: Mapped[list[str]] = mapped_column(JSON)
    engine: Mapped[str] = mapped_column(String(300), default="")
    state: Mapped[str] = mapped_column(String(16), default="queued")
    total: Mapped[int] = mapped_column(Integer, default=0)
    done: Mapped[int] = mapped_column(Integer, default=0)
    failed: Mapped[int] = mapped_column(Integer, default=0)
    runner: Mapped[str] = mapped_column(String(300), default="")
    error: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    started_at: Mapped[dt.datetime | None] = mapped_column()
    resumed_at: Mapped[dt.datetime | None] = mapped_column()
    resumed_count: Mapped[int] = mapped_column(Integer, default=0)
    progress_at: Mapped[dt.datetime | None] = mapped_column()
    finished_at: Mapped[dt.datetime | None] = mapped_column()


class ProcessingTask(Base):
    """One acquisition of a job: ``pending`` until its results are committed.

    ``uid`` is kept as given (an unknown uid is a task that fails, as with ``process``);
    ``acquisition_id`` is set when it names an acquisition. ``attempts`` counts the
    coordinators that started it: more than one means it was redone after a coordinator
    stopped.
    """

    __tablename__ = "processing_task"
    __table_args__ = (
        CheckConstraint(f"state IN {TASK_STATES!r}", name="state"),
        Index("ix_processing_task_job_state", "job_id", "state", "position"),
    )

    job_id: Mapped[str] = mapped_column(
        ForeignKey("processing_job.id", ondelete="CASCADE"), primary_key=True
    )
    position: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    uid: Mapped[str] = mapped_column(Text)
    acquisition_id: Mapped[int | None] = mapped_column(
        ForeignKey("acquisition.id", ondelete="RESTRICT"), index=True
    )
    state: Mapped[str] = mapped_column(String(16), default="pending")
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    computed: Mapped[int] = mapped_column(Integer, default=0)
    reused: Mapped[int] = mapped_column(Integer, default=0)
    reason: Mapped[str] = mapped_column(Text, default="")
    error: Mapped[str] = mapped_column(Text, default="")
    exit_code: Mapped[int] = mapped_column(Integer, default=0)
    finished_at: Mapped[dt.datetime | None] = mapped_column()
