"""Do files and catalogue agree? One classifier for the raw and the derived stores.

Both stores are written the same way (under a temporary name, fsynced, published, then the
catalogue row committed: :mod:`rasterserver.store.durable`), so a file is in one of the
same few states whichever store holds it. :func:`classify_files` tells them apart:

``temporary``
    a partial write left by an interrupted writer (no row can refer to it);
``stray``
    a file rasterserver did not make;
``orphaned``
    a complete file without its row: the writer stopped between publishing and committing;
``missing``
    a row without its file;
``corrupt`` / ``unreadable``
    a file whose contents differ from what the row records, or that cannot be read.

:func:`verify_raw` and :func:`verify_derived` feed it each store's rows, files and check;
:func:`verify_archive` runs both. :mod:`rasterserver.repair` acts on the problems found.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, Protocol, TypeVar

from sqlalchemy import select

from rasterserver.errors import IntegrityError, NotFoundError

if TYPE_CHECKING:
    from rasterserver.archive import Archive
    from rasterserver.catalog.catalog import Catalog
    from rasterserver.store.derived import DerivedStore
    from rasterserver.store.raw import RawStore

__all__ = [
    "DERIVED_WORDING",
    "RAW_WORDING",
    "ArchiveReport",
    "Problem",
    "Progress",
    "VerifyReport",
    "Wording",
    "classify_files",
    "verify_archive",
    "verify_derived",
    "verify_raw",
]

#: Called with (done, total) while a long check runs.
Progress = Callable[[int, int], None]

K = TypeVar("K", bound=Hashable)


@dataclass(frozen=True)
class Problem:
    """One thing ``verify`` found wrong.

    Attributes
    ----------
    kind : str
        ``missing``, ``corrupt``, ``unreadable``, ``orphaned``, ``temporary`` or ``stray``.
    uid : str or None
        The acquisition concerned.
    path : Path or None
        The file concerned.
    detail : str
        What is wrong and what it means.
    """

    kind: str
    uid: str | None
    path: Path | None
    detail: str


@dataclass
class VerifyReport:
    """Outcome of verifying one store (:func:`verify_raw`, :func:`verify_derived`).

    Attributes
    ----------
    acquisitions_checked : int
        Acquisitions whose files were checked.
    frames_checked : int
        Frames (raw store) or stored results (derived store) checked.
    problems : list of Problem
    """

    acquisitions_checked: int = 0
    frames_checked: int = 0
    problems: list[Problem] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when nothing is missing, corrupt, orphaned or left over."""
        return not self.problems


@dataclass
class ArchiveReport:
    """Outcome of :func:`verify_archive`: the raw frames and the stored results."""

    raw: VerifyReport
    derived: VerifyReport

    @property
    def problems(self) -> list[Problem]:
        """Every problem, the raw store's first."""
        return [*self.raw.problems, *self.derived.problems]

    @property
    def ok(self) -> bool:
        """True when both stores are intact."""
        return self.raw.ok and self.derived.ok


class Wording(NamedTuple):
    """What each state means in one store (the ``detail`` of its problems)."""

    temporary: str
    orphaned: str
    missing: str


RAW_WORDING = Wording(
    temporary="partial write left by an interrupted ingest (no catalogue row refers to it); "
              "safe to delete",
    orphaned="complete file without a catalogue row: an ingest stopped between writing the "
             "file and committing the row",
    missing="catalogue row without its file",
)
DERIVED_WORDING = Wording(
    temporary="partial write of an interrupted run; safe to delete",
    orphaned="result file without a catalogue row: processing stopped between writing it "
             "and recording it; the same computation will adopt it",
    missing="stored result row without its file",
)

STRAY = "file not made by rasterserver"


class ScannedFile(Protocol):
    """A file a store's ``scan`` found (:class:`~rasterserver.store.layout.ShardEntry`,
    :class:`~rasterserver.store.derived.DerivedEntry`)."""

    @property
    def path(self) -> Path: ...
    @property
    def kind(self) -> str: ...  # "final", "temp" or "stray"
    @property
    def uid(self) -> str | None: ...


def classify_files(
    rows: Mapping[K, str | None],
    files: Iterable[ScannedFile],
    key_of: Callable[[ScannedFile], K],
    check: Callable[[K], Iterable[Problem]],
    wording: Wording,
    *,
    progress: Progress | None = None,
) -> list[Problem]:
    """Compare one store's files with its catalogue rows.

    Parameters
    ----------
    rows : mapping
        What the catalogue expects, by key (a uid, a path), in the order to check them;
        each value is the acquisition uid the key belongs to.
    files : iterable of ScannedFile
        What the store's ``scan`` found.
    key_of : callable
        The key of a published (``final``) file, to match it with its row.
    check : callable
        Checks the file of one row; gives its problems (``missing``, ``corrupt``,
        ``unreadable``), none when it is sound.
    wording : Wording
        The store's explanations.
    progress : Progress, optional
        Called with (done, total) after each row and each orphan.

    Returns
    -------
    list of Problem
        Temporary and stray files in scan order, then the rows' problems, then orphans.
    """
    problems: list[Problem] = []
    published: dict[K, ScannedFile] = {}
    for entry in files:
        if entry.kind == "final":
            published[key_of(entry)] = entry
        elif entry.kind == "temp":
            problems.append(Problem("temporary", entry.uid, entry.path, wording.temporary))
        else:
            problems.append(Problem("stray", None, entry.path, STRAY))
    orphans = [key for key in published if key not in rows]
    total = len(rows) + len(orphans)
    done = 0
    for key in rows:
        problems.extend(check(key))
        done += 1
        if progress:
            progress(done, total)
    for key in orphans:
        entry = published[key]
        problems.append(Problem("orphaned", entry.uid, entry.path, wording.orphaned))
        done += 1
        if progress:
            progress(done, total)
    return problems


def verify_raw(catalog: Catalog, raw: RawStore, *,
               progress: Progress | None = None) -> VerifyReport:
    """Re-hash every raw frame and compare the raw files with the acquisitions' rows.

    Parameters
    ----------
    catalog : Catalog
        The catalogue.
    raw : RawStore
        The raw store.
    progress : Progress, optional
        Called with (done, total) after each file.

    Returns
    -------
    VerifyReport
        ``frames_checked`` counts the frames re-hashed.
    """
    from rasterserver.catalog.models import Acquisition, Frame

    expected: dict[str, dict[int, str]] = {}
    with catalog.session() as s:
        for uid, index, digest in s.execute(
                select(Acquisition.uid, Frame.index, Frame.sha256).join(Frame)):
            expected.setdefault(uid, {})[index] = digest
        for (uid,) in s.execute(select(Acquisition.uid)):
            expected.setdefault(uid, {})
    report = VerifyReport(acquisitions_checked=len(expected))

    def check(uid: str) -> list[Problem]:
        file_report = raw.check_file(uid, expected[uid])
        report.frames_checked += len(file_report.hashes)
        path = raw.path_for(uid)
        if file_report.status == "missing":
            return [Problem("missing", uid, path, RAW_WORDING.missing)]
        kind = "unreadable" if file_report.status == "unreadable" else "corrupt"
        return [Problem(kind, uid, path, problem.message) for problem in file_report.problems]

    report.problems = classify_files(
        {uid: uid for uid in sorted(expected)}, raw.scan(), _uid_of, check, RAW_WORDING,
        progress=progress)
    return report


def verify_derived(catalog: Catalog, derived: DerivedStore, *,
                   progress: Progress | None = None) -> VerifyReport:
    """Check stored results against their rows: every row's file exists and matches.

    Parameters
    ----------
    catalog : Catalog
        The catalogue.
    derived : DerivedStore
        The derived-results store.
    progress : Progress, optional
        Called with (done, total) after each result.

    Returns
    -------
    VerifyReport
        ``frames_checked`` counts the results checked.
    """
    from rasterserver.catalog.models import Acquisition, StageResult
    from rasterserver.store.derived import RecentRecords

    with catalog.session() as s:
        rows = list(s.execute(
            select(Acquisition.uid, StageResult.store_path, StageResult.output_checksum)
            .join(Acquisition, Acquisition.id == StageResult.acquisition_id)
            .order_by(StageResult.acquisition_id, StageResult.id)))
    owners = {path: uid for uid, path, _sum in rows}
    checksums = {path: checksum for _uid, path, checksum in rows}
    report = VerifyReport(acquisitions_checked=len(set(owners.values())))

    # rows by acquisition, each in the order they were stored: a result's parent just before
    # it, so the fields it inherits are taken from the parent read and checked a moment ago
    recent = RecentRecords()

    def check(path: str) -> list[Problem]:
        report.frames_checked += 1
        where = derived.root / path
        try:
            derived.read(path, expected_checksum=checksums[path], recent=recent)
        except NotFoundError:
            return [Problem("missing", owners[path], where, DERIVED_WORDING.missing)]
        except IntegrityError as exc:
            return [Problem("corrupt", owners[path], where, str(exc))]
        return []

    def relative(entry: ScannedFile) -> str:
        return entry.path.relative_to(derived.root).as_posix()

    report.problems = classify_files(owners, derived.scan(), relative, check, DERIVED_WORDING,
                                     progress=progress)
    return report


def verify_archive(archive: Archive, *, progress: Progress | None = None) -> ArchiveReport:
    """Verify the raw frames and the stored results of ``archive``.

    Parameters
    ----------
    archive : Archive
        The archive.
    progress : Progress, optional
        Called with (done, total) after each file, over both stores: the total grows by the
        stored results once the raw files are done.

    Returns
    -------
    ArchiveReport
    """
    # the plugin registry resolves the record kinds of stored results (plugins may add some)
    from rasterserver.registry import get_registry
    from rasterserver.store.derived import DerivedStore

    raw = verify_raw(archive.catalog, archive.raw, progress=progress)
    # the raw files' count, once known, is where the stored results' count starts
    raw_files = raw.acquisitions_checked + sum(p.kind == "orphaned" for p in raw.problems)

    def after_raw(done: int, total: int) -> None:
        if progress:
            progress(raw_files + done, raw_files + total)

    derived = DerivedStore(archive.settings.archive, resolve=get_registry().record_type)
    return ArchiveReport(
        raw=raw, derived=verify_derived(archive.catalog, derived, progress=after_raw))


def _uid_of(entry: ScannedFile) -> str:
    assert entry.uid is not None  # a published file's name is its uid
    return entry.uid
