"""Clean up what ``verify`` reports, without ever losing data (``rasterserver verify --repair``).

The write protocol (:mod:`rasterserver.archive`, :mod:`rasterserver.store.durable`) is: write
under a temporary name, fsync, publish by link + unlink, then commit the catalogue row. That
protocol decides what is provably safe to do with each kind of problem:

``temporary``
    Never published, so no row can refer to it and no reader has seen it: **deleted**.
``orphaned``
    Published and complete, but without a row: it may hold the only copy of frames someone
    took. Never deleted: **moved** (one atomic rename on the same filesystem, folders
    fsynced) to ``<archive>/quarantine/<UTC date>/<its path in the archive>`` and recorded in
    ``manifest.json`` there, so a person can inspect it and re-ingest it.
``stray``
    Not made by rasterserver: **left alone** and reported.
``missing``, ``corrupt``, ``unreadable``
    Raw frames are never modified after ingest, and a damaged stored result is still named
    by its catalogue row (the pipeline would reuse the row rather than recompute): **not
    touched**, reported as needing a person (restore from backup).

Every file is looked at again right before anything is done to it, because the archive is
live: a writer may still be working on a young temporary file, and an ingest may commit the
row of an "orphan" after ``verify`` ran. Hence:

* files younger than ``min_age`` (default one hour) are *deferred*: an ingest publishes its
  file a moment before it commits the row, so a young orphan may be one in flight, which no
  lock can tell apart (ingest takes the write lock only to commit);
* the row is looked up again under the archive's write lock (on SQLite this excludes an
  ingest's commit for the whole check-and-move; on PostgreSQL the lock does nothing), and
  once more right after the move: a row that appeared in between gets its file put back.

A second run finds nothing left to do: deleted and moved files are gone from the scanned
areas, and nothing else is ever changed.

Patient data never appear in the log or in the manifest: files are named by uid only.
"""

from __future__ import annotations

import datetime as dt
import errno
import fcntl
import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from sqlalchemy import select

from rasterserver.catalog.models import Acquisition, StageResult
from rasterserver.errors import ConflictError
from rasterserver.integrity import Problem
from rasterserver.store.durable import ensure_dir, fsync_dir, fsync_file
from rasterserver.store.layout import is_uid, temp_path

if TYPE_CHECKING:
    from rasterserver.archive import Archive

__all__ = [
    "DEFAULT_MIN_AGE",
    "MANIFEST",
    "QUARANTINE",
    "RepairAction",
    "RepairReport",
    "repair",
]

log = logging.getLogger(__name__)

#: Files younger than this are left for a later run (see the module docstring).
DEFAULT_MIN_AGE = dt.timedelta(hours=1)
#: Folder inside the archive that receives orphaned files.
QUARANTINE = "quarantine"
#: The record of what was moved, one per quarantine day folder.
MANIFEST = "manifest.json"
MANIFEST_FORMAT = "rasterserver-quarantine"
_AREAS = ("raw", "derived")
_TEMP_MARK = ".tmp-"

#: ``deleted``/``quarantined``: done (or, in a dry run, what would be done). ``resolved``: the
#: problem went away since ``verify`` ran. ``deferred``: not safe *yet* (too young, or not
#: movable now); a later run retries. ``left``: not ours, left alone. ``attention``: needs a
#: person.
ActionKind = Literal["deleted", "quarantined", "resolved", "deferred", "left", "attention"]
_VERBS: dict[ActionKind, tuple[str, str]] = {  # (done, dry run)
    "deleted": ("deleted", "would delete"),
    "quarantined": ("quarantined", "would quarantine"),
    "resolved": ("resolved", "resolved"),
    "deferred": ("deferred", "deferred"),
    "left": ("left alone", "left alone"),
    "attention": ("needs a person", "needs a person"),
}


@dataclass(frozen=True)
class RepairAction:
    """What repair did (or, in a dry run, would do) about one problem.

    Attributes
    ----------
    action : str
        ``deleted``, ``quarantined``, ``resolved``, ``deferred``, ``left`` or ``attention``.
    kind : str
        The problem's kind as ``verify`` reported it (``temporary``, ``orphaned``, ...).
    uid : str or None
        The acquisition concerned.
    path : str
        The file, relative to the archive (POSIX separators); empty if verify named none.
    detail : str
        Why, and what a person should do if anything.
    destination : str or None
        For ``quarantined``: where the file is (or would be), relative to the archive.
    """

    action: ActionKind
    kind: str
    uid: str | None
    path: str
    detail: str
    destination: str | None = None

    def verb(self, dry_run: bool) -> str:
        """The action as a word for a person, e.g. ``"would delete"`` in a dry run."""
        return _VERBS[self.action][dry_run]


@dataclass
class RepairReport:
    """Outcome of :func:`repair` (:meth:`rasterserver.archive.Archive.repair`).

    Attributes
    ----------
    dry_run : bool
        True when nothing was changed and the actions say what would be done.
    actions : list of RepairAction
        One per problem handed in, in the same order.
    quarantine : Path or None
        The quarantine folder of this run (``<archive>/quarantine/<date>``), if any file was
        (or would be) moved there.
    """

    dry_run: bool = False
    actions: list[RepairAction] = field(default_factory=list)
    quarantine: Path | None = None

    def count(self, action: ActionKind) -> int:
        """Number of problems that got ``action``."""
        return sum(a.action == action for a in self.actions)

    @property
    def remaining(self) -> list[RepairAction]:
        """The problems still in the archive afterwards (in a dry run: all but resolved)."""
        still: set[str] = {"deferred", "left", "attention"}
        if self.dry_run:
            still |= {"deleted", "quarantined"}
        return [a for a in self.actions if a.action in still]

    @property
    def ok(self) -> bool:
        """True when the archive is intact afterwards: nothing remains to report."""
        return not self.remaining

    def summary(self) -> str:
        """One line saying what was done and what is left."""
        would = "would " if self.dry_run else ""
        parts = []
        if n := self.count("deleted"):
            parts.append(f"{would}delete{'' if would else 'd'} {n} temporary file(s)")
        if n := self.count("quarantined"):
            where = (f" into {self.quarantine.parent.name}/{self.quarantine.name}"
                     if self.quarantine else "")
            parts.append(f"{would}quarantine{'' if would else 'd'} {n} orphaned file(s){where}")
        if n := self.count("resolved"):
            parts.append(f"{n} resolved since verify ran")
        if n := self.count("deferred"):
            parts.append(f"{n} deferred (run again later)")
        if n := self.count("left"):
            parts.append(f"{n} stray file(s) left alone")
        if n := self.count("attention"):
            parts.append(f"{n} need(s) a person (restore from backup)")
        text = ", ".join(parts) if parts else "nothing to repair"
        return ("dry run, nothing changed: " if self.dry_run else "repair: ") + text


@dataclass(frozen=True)
class _Target:
    """A problem's file, checked to be one of ours in ``raw/`` or ``derived/``."""

    area: str
    path: Path
    relative: str


def repair(
    archive: Archive,
    problems: Sequence[Problem],
    *,
    dry_run: bool = False,
    min_age: dt.timedelta = DEFAULT_MIN_AGE,
    progress: Callable[[int, int], None] | None = None,
    now: dt.datetime | None = None,
) -> RepairReport:
    """Act on the problems ``verify`` found, by the rules of the module docstring.

    Parameters
    ----------
    archive : Archive
        The archive the problems were found in.
    problems : sequence of Problem
        From :meth:`Archive.verify` and :meth:`rasterserver.pipeline.Pipeline.verify`.
    dry_run : bool, default False
        Change nothing; the report says what would be done.
    min_age : datetime.timedelta, default one hour
        Leave temporary and orphaned files younger than this for a later run: they may be
        an ingest or a processing run still at work.
    progress : callable, optional
        Called with ``(done, total)`` after each problem.
    now : datetime, optional
        The time of the run (UTC), which names the quarantine folder; now by default.

    Returns
    -------
    RepairReport

    Raises
    ------
    ConflictError
        Another repair of this archive is running.
    """
    now = now or dt.datetime.now(dt.UTC)
    root = archive.settings.archive
    report = RepairReport(dry_run=dry_run)
    day = root / QUARANTINE / now.strftime("%Y-%m-%d")
    with _exclusive(root, enabled=not dry_run):
        for done, problem in enumerate(problems, start=1):
            action = _handle(archive, problem, day, dry_run=dry_run, now=now,
                             min_age=min_age.total_seconds())
            report.actions.append(action)
            if action.action == "quarantined":
                report.quarantine = day
            if progress:
                progress(done, len(problems))
    return report


def _handle(archive: Archive, problem: Problem, day: Path, *, dry_run: bool,
            now: dt.datetime, min_age: float) -> RepairAction:
    root = archive.settings.archive
    target = _locate(root, problem)
    shown = target.relative if target else (problem.path.name if problem.path else "")

    def act(action: ActionKind, detail: str, destination: str | None = None) -> RepairAction:
        return RepairAction(action, problem.kind, problem.uid, shown, detail, destination)

    if problem.kind in ("missing", "corrupt", "unreadable"):
        return act("attention", f"{problem.detail}; {_advice(problem.kind, target)}")
    if problem.kind == "stray":
        return act("left", "not made by rasterserver: left alone for a person to look at")
    if problem.kind not in ("temporary", "orphaned"):
        return act("attention", f"unknown kind of problem: {problem.detail}")
    if target is None or not _name_fits(problem, target):
        # Never act on a path that is not where and how the stores name their files.
        return act("left", "not a file rasterserver would have written there: left alone")
    try:
        if problem.kind == "temporary":
            return _delete_temporary(target, act, dry_run=dry_run, min_age=min_age)
        return _quarantine_orphan(archive, problem, target, day, act, dry_run=dry_run,
                                  now=now, min_age=min_age)
    except OSError as exc:
        # Permissions, a full disk: nothing half-done (each step is one system call), so
        # report it and carry on with the rest.
        return act("deferred", f"could not be repaired now ({exc.strerror or exc}); "
                               "run again when the cause is fixed")


def _delete_temporary(target: _Target, act: Callable[..., RepairAction], *, dry_run: bool,
                      min_age: float) -> RepairAction:
    # A temporary file was never published (publish() links it under the final name and
    # only then does a row get committed), so no row and no reader can depend on it.
    age = _age(target.path)
    if age is None:
        return act("resolved", "gone since verify ran (the writer finished or cleaned up)")
    if age < min_age:
        return act("deferred", f"written {_ago(age)} ago: a writer may still be at work; "
                               "run again later")
    if dry_run:
        return act("deleted", "partial write of an interrupted ingest or run: safe to delete")
    try:
        target.path.unlink()
    except FileNotFoundError:
        return act("resolved", "gone since verify ran (the writer finished or cleaned up)")
    fsync_dir(target.path.parent)  # the removal survives a power cut
    log.info("repair: deleted a temporary %s file of %s", target.area, target.relative)
    return act("deleted", "partial write of an interrupted ingest or run: deleted")


def _quarantine_orphan(archive: Archive, problem: Problem, target: _Target, day: Path,
                       act: Callable[..., RepairAction], *, dry_run: bool, now: dt.datetime,
                       min_age: float) -> RepairAction:
    committed = "its catalogue row was committed since verify ran: left in place"
    age = _age(target.path)
    if age is None:
        return act("resolved", "gone since verify ran")
    if age < min_age:
        return act("deferred", f"published {_ago(age)} ago: an ingest or run may be about to "
                               "commit its row; run again later")
    destination = _free_name(day / target.relative)
    shown = destination.relative_to(archive.settings.archive).as_posix()
    if dry_run:
        if _has_row(archive, target, problem.uid):
            return act("resolved", committed)
        return act("quarantined", "complete file without a catalogue row: would be kept in "
                                  "quarantine for a person to inspect or re-ingest", shown)
    # Published files are immutable, so the hash can be taken before the lock is held.
    try:
        size, digest = _file_digest(target.path)
    except FileNotFoundError:
        return act("resolved", "gone since verify ran")
    with archive.write_lock():
        if not target.path.is_file():
            return act("resolved", "gone since verify ran")
        if _has_row(archive, target, problem.uid):
            return act("resolved", committed)
        try:
            _move(target.path, destination)
        except OSError as exc:
            if exc.errno == errno.EXDEV:
                return act("deferred", "the quarantine folder is on another filesystem, so "
                                       "the file cannot be moved atomically: left in place")
            raise
        # On PostgreSQL the write lock excludes nothing: an ingest may have committed while
        # the file moved. Its row must find its file, so put the file back.
        if _has_row(archive, target, problem.uid):
            _move(destination, target.path)
            return act("resolved", f"{committed} (the file was put back)")
    _record(day / MANIFEST, {
        "kind": "orphaned",
        "area": target.area,
        "uid": problem.uid,
        "original": target.relative,
        "quarantined": destination.relative_to(day).as_posix(),
        "size": size,
        "sha256": digest,
        "moved_utc": now.isoformat(timespec="seconds"),
        "reason": problem.detail,
        "what_to_do": _ORPHAN_ADVICE[target.area],
    })
    log.info("repair: quarantined an orphaned %s file of %s", target.area, problem.uid)
    return act("quarantined", "complete file without a catalogue row: kept in quarantine "
                              "(see its manifest.json) for a person to inspect or re-ingest",
               shown)


_ORPHAN_ADVICE = {
    "raw": "Frames of an acquisition whose ingest stopped before its catalogue row was "
           "committed; which patient they belong to is not recorded. Inspect them (any HDF5 "
           "reader) and, if they are wanted, ingest them again; otherwise they may be deleted.",
    "derived": "A stage result whose processing stopped before its row was committed; it "
               "can be recomputed from the raw frame with `rasterserver process` and may be "
               "deleted after inspection.",
}


def _advice(kind: str, target: _Target | None) -> str:
    """What a person should do about a missing, corrupt or unreadable file."""
    if target is not None and target.area == "derived":
        # Checked: re-running the pipeline reuses the result the row names and does not
        # rewrite its file, so recomputing is no cure while the row stands.
        return ("the raw frame it was computed from is untouched, so nothing measured is lost; "
                "restore the file from backup (re-running `rasterserver process` reuses the "
                "catalogue's result and does not rewrite it)")
    verb = "restore" if kind == "missing" else "replace"
    return (f"raw frames are never modified after ingest, so repair leaves it alone: {verb} "
            "the file from backup (the catalogue's SHA-256 of each frame proves the right copy)")


def _locate(root: Path, problem: Problem) -> _Target | None:
    """The problem's file if it lies in a shard folder of ``raw/`` or ``derived/``."""
    if problem.path is None:
        return None
    try:
        relative = problem.path.relative_to(root)
    except ValueError:
        return None
    parts = relative.parts
    # <area>/<uid[0:2]>/<uid[2:4]>/<name>, nothing else, no "..": see store.layout
    if len(parts) != 4 or parts[0] not in _AREAS or ".." in parts:
        return None
    return _Target(parts[0], problem.path, relative.as_posix())


def _name_fits(problem: Problem, target: _Target) -> bool:
    """True if the file's name is what the stores give a ``temporary``/``orphaned`` file."""
    uid = problem.uid
    if uid is None or not is_uid(uid):
        return False
    _area, top, sub, name = Path(target.relative).parts
    if top + sub != uid[:4] or not name.startswith(uid + "."):
        return False
    stem, mark, _rest = name.partition(_TEMP_MARK)
    if problem.kind == "temporary":
        return bool(mark) and stem.endswith(".h5")
    if mark or not name.endswith(".h5"):
        return False
    return target.area == "derived" or name == f"{uid}.h5"


def _has_row(archive: Archive, target: _Target, uid: str | None) -> bool:
    """Whether the catalogue now has the row the file was missing."""
    if target.area == "raw":
        query = select(Acquisition.id).where(Acquisition.uid == uid).limit(1)
    else:
        query = select(StageResult.id).where(StageResult.store_path == target.relative).limit(1)
    with archive.reading() as conn:
        return conn.execute(query).first() is not None


def _age(path: Path) -> float | None:
    """Seconds since the file last changed (data or name), or None if it is gone."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    # ctime moves when publish() links the file under its final name, mtime when data are
    # written: the later of the two is when a writer last touched it.
    return max(0.0, time.time() - max(st.st_mtime, st.st_ctime))


def _ago(seconds: float) -> str:
    return f"{seconds / 60:.0f} min" if seconds >= 60 else f"{seconds:.0f} s"


def _free_name(destination: Path) -> Path:
    """``destination``, or ``<uid>~2.<rest>`` etc. if a file of that name is quarantined."""
    candidate, n = destination, 1
    head, dot, tail = destination.name.partition(".")
    while candidate.exists():
        n += 1
        candidate = destination.with_name(f"{head}~{n}{dot}{tail}")
    return candidate


def _move(source: Path, destination: Path) -> None:
    """Move a file within the archive's filesystem atomically and durably, never replacing.

    One ``rename``: after a crash the file has either its old name or its new one, never
    both or neither. The file's data were fsynced before it was first published; what
    changes here are the two folders' entries, so those are fsynced.
    """
    ensure_dir(destination.parent)
    if destination.exists():  # rename would replace it; names are unique per source file
        raise FileExistsError(errno.EEXIST, "destination exists")
    os.rename(source, destination)
    fsync_dir(destination.parent)
    fsync_dir(source.parent)


def _file_digest(path: Path) -> tuple[int, str]:
    """Size and SHA-256 of a file's bytes, so the manifest can prove the copy unchanged."""
    digest = hashlib.sha256()
    size = 0
    with path.open("rb") as fh:
        while chunk := fh.read(1 << 20):
            digest.update(chunk)
            size += len(chunk)
    return size, digest.hexdigest()


def _record(manifest: Path, entry: dict[str, object]) -> None:
    """Append ``entry`` to the quarantine manifest, replacing it atomically."""
    document: dict[str, object] = {"format": MANIFEST_FORMAT, "format_version": 1,
                                   "entries": []}
    if manifest.exists():
        document = json.loads(manifest.read_text(encoding="utf-8"))
    entries = document.setdefault("entries", [])
    assert isinstance(entries, list)
    entries.append(entry)
    temp = temp_path(manifest)
    temp.write_text(json.dumps(document, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    fsync_file(temp)
    # Replacing is wanted here (the manifest grows); the old or the new one survives a crash.
    os.replace(temp, manifest)
    fsync_dir(manifest.parent)


@contextmanager
def _exclusive(root: Path, *, enabled: bool) -> Iterator[None]:
    """One repair at a time per archive: two would race on the manifest's read and write."""
    if not enabled or not root.is_dir():  # no folder: no file to move or delete either
        yield
        return
    # A flock on the archive folder itself: no lock file to leave behind in the archive.
    fd = os.open(root, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConflictError("another `rasterserver verify --repair` is running on this "
                                "archive; try again when it has finished") from None
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)
