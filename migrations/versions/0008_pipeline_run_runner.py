"""pipeline runs name their runner, so a run whose process was killed is not running for ever

``pipeline_run`` rows are committed ``running`` before processing starts; a process killed
by the OOM killer, ``kill -9`` or a power cut left them so for good. ``runner`` names the
process, as ``api_job.runner`` does: ``host:pid@boot/start/pidns``
(:mod:`rasterserver.runner`), with the boot id and start time so that a pid the kernel has
given to another process since does not keep the run alive. A run on this host whose runner
is gone is then stored as ``failed`` with an error beginning ``interrupted:``.

Why ``failed`` with that text rather than a new status ``interrupted``:

* it is what ``api_job`` already does with a job whose server process is gone, so the
  catalogue has one meaning for "its process died";
* the statuses are part of the HTTP API (``GET /acquisitions/{uid}/runs?status=``) and of
  scripts around it; for all of them a killed run is a run that did not finish and has to be
  repeated, which ``failed`` already says, and the ``interrupted:`` prefix tells it apart
  from a chain that failed on the data;
* a new status means a new CHECK constraint, and SQLite changes one only by rebuilding
  ``pipeline_run``, which ``stage_result`` references with ON DELETE RESTRICT: with foreign
  keys enforced inside the migration's transaction, dropping the old table counts every
  referenced run as a violation and the commit fails. It would take rebuilding
  ``stage_result``, the largest table, as well.

Runs recorded before this revision get an empty runner: their process cannot be identified,
so nothing marks them automatically; ``rasterserver runs reap --host NAME`` does, once the
staff know nothing is processing there any more.

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-22 08:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # a plain ADD COLUMN on both dialects (no table rebuild on SQLite): NOT NULL needs the
    # server default for the rows already there
    op.add_column(
        "pipeline_run",
        sa.Column("runner", sa.String(length=300), nullable=False, server_default=""),
    )


def downgrade() -> None:
    # only the runner is lost; runs already marked interrupted stay failed with their text.
    # SQLite >= 3.35 drops a column in place, so no rebuild (see above) is needed either.
    op.drop_column("pipeline_run", "runner")
