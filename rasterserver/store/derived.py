"""Derived-results store: one write-once HDF5 file per (acquisition, stage result).

Raw frames are never rewritten; everything computed from them lives here, beside the raw
store, in files that are as durable and as self-describing as the raw ones.

File layout (format version 1)
------------------------------
Path: ``<root>/derived/<uid[0:2]>/<uid[2:4]>/<uid>.<stage>-<key>.h5``, where ``uid`` is the
acquisition's uid, ``stage`` the stage kind (``points``, ``surface``, ...) and ``key`` the
first 32 hex digits of the result's *chain key* (see :mod:`rasterserver.chain`). All
results of an acquisition therefore share its shard folder and its name prefix, and the name
is a function of what was computed: asking for the same computation twice can only ever name
the same file, and a result left behind by a crash is found again instead of duplicated.

Root attributes: ``format`` (``"rasterserver-derived"``), ``format_version`` (integer 2) and
``provenance``, one JSON object (canonical, sorted keys) with the strings ``acquisition``
(uid), ``stage``, ``plugin``, ``plugin_version``, ``params`` (canonical JSON), ``params_hash``,
``chain_key``, ``input_checksum`` (content hash of the input record), ``output_checksum``
(content hash of the stored record, :meth:`rasterserver.records.Record.content_hash`),
``record_kind``, ``created_utc`` and ``writer``. Format version 1 (written until November
2026) held the same strings as one root attribute each; both are read.

Group ``/record``: one contiguous dataset per field of the record as :meth:`Record.to_arrays`
gives them (scalars as scalar datasets, strings as fixed-length byte strings; no chunking or
filters: the arrays are small). Any HDF5 reader can open the files; the store rebuilds the
record in Python with the class its ``resolve`` callable names for the kind (the pipeline
passes its plugin registry's, so a fresh process knows every installed plugin's record kinds
whatever it has imported).

Files are built in memory (HDF5's core driver) and written with one ``write``: the per-file
cost of a result is then a few h5py calls, one write and one fsync.

Inherited fields (format version 3)
-----------------------------------
A stage often passes most of its input on unchanged: the line search adds ``line_id`` to the
peaks' five arrays, the order stage two more arrays, the numbering three. Such a result,
written with its input's stored file as ``base`` (:meth:`DerivedStore.write`), stores only
the fields that differ from the base's; the fields it shares with it byte for byte (same name,
dtype, shape and bytes, at least :data:`MIN_INHERITED_BYTES` long) are named in the
provenance's ``inherited`` (a JSON list) beside ``base`` (the base file's path relative to the
archive root) and ``base_checksum`` (the base record's content hash), and the file says
``format_version`` 3. Reading it reads the base (recursively, each checked against its
checksum) and checks the whole record against its own checksum, so a damaged or missing base
is an integrity error of every result built on it. The base is always the result's parent in
the catalogue (the result it was computed from), which pruning keeps as long as the result is
kept. For the built-in chain this stores 4.0 MB per 604x576 acquisition instead of 5.6 MB
(the three line stages 0.27 MB instead of 1.9 MB): fewer bytes to build, write and fsync.

Durability: written under a temporary name in the final folder, fsynced and published with a
link that refuses to replace (:mod:`.durable`; a Dask task's files synced together,
:mod:`.pending`), like the raw store; opened without HDF5 file locking (see :mod:`.raw`).
"""

from __future__ import annotations

import json
import re
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import Any, Literal

import h5py
import numpy as np

from rasterserver import __version__
from rasterserver.errors import ConflictError, InputError, IntegrityError, NotFoundError
from rasterserver.hashing import canonical_array
from rasterserver.records import Record, record_type
from rasterserver.store.durable import ensure_dir, fsync_dir, publish, write_synced
from rasterserver.store.layout import shard_path, temp_path, validate_uid
from rasterserver.store.pending import PendingFiles

__all__ = ["AREA", "FORMAT_NAME", "FORMAT_VERSION", "DerivedEntry", "DerivedStore", "RecentRecords",
           "StoredBase", "StoredResult"]

FORMAT_NAME = "rasterserver-derived"
FORMAT_VERSION = 2
#: The format version of a file with inherited fields (see the module's docstring).
FORMAT_VERSION_INHERITING = 3
#: Fields shorter than this are stored again rather than inherited: not worth the indirection.
MIN_INHERITED_BYTES = 4096
PROVENANCE = "provenance"
AREA = "derived"
SUFFIX = ".h5"
KEY_DIGITS = 32
#: A chain is a handful of stages: more bases in a row than this is a damaged file.
_MAX_BASES = 32

_STAGE = re.compile(r"[a-z][a-z0-9_-]{0,31}")
_KEY = re.compile(r"[0-9a-f]{64}")
_NAME = re.compile(
    rf"(?P<uid>[0-9a-f]{{32}})\.(?P<stage>[a-z][a-z0-9_-]{{0,31}})-(?P<key>[0-9a-f]{{{KEY_DIGITS}}})"
    rf"{re.escape(SUFFIX)}(?P<temp>\.tmp-.+)?"
)
_META_KEYS = (
    "acquisition",
    "stage",
    "plugin",
    "plugin_version",
    "params",
    "params_hash",
    "chain_key",
    "input_checksum",
    "output_checksum",
    "record_kind",
    "created_utc",
    "writer",
    "base",
    "base_checksum",
    "inherited",
)


@dataclass(frozen=True)
class StoredResult:
    """A stage result as stored.

    Attributes
    ----------
    path : str
        File path relative to the archive root, POSIX separators.
    output_checksum : str
        Content hash of the stored record.
    adopted : bool
        True when the file existed already (same chain key and content) and was reused, e.g.
        after a crash between writing the file and committing its catalogue row.
    record_kind : str
        The stored record's kind.
    reason : str
        The record's ``reason`` (why it is empty, or a note), empty if it has none.
    """

    path: str
    output_checksum: str
    adopted: bool = False
    record_kind: str = ""
    reason: str = ""


@dataclass(frozen=True)
class DerivedEntry:
    """One file found under ``<root>/derived``.

    Attributes
    ----------
    path : Path
        Absolute path.
    kind : {"final", "temp", "stray"}
        A published result, a leftover partial write, or anything else.
    uid, stage, key : str or None
        What the name says, for ``final`` and ``temp`` files.
    """

    path: Path
    kind: Literal["final", "temp", "stray"]
    uid: str | None = None
    stage: str | None = None
    key: str | None = None


@dataclass(frozen=True)
class StoredBase:
    """The stored input of a result being written, whose unchanged fields it may inherit.

    Attributes
    ----------
    path : str
        The input's file, relative to the archive root (its catalogue ``store_path``).
    record : Record
        The input record as stored.
    checksum : str
        Its content hash (its catalogue ``output_checksum``).
    """

    path: str
    record: Record
    checksum: str


def _inherited(arrays: Mapping[str, Any], base: Record) -> list[str]:
    """The fields of ``arrays`` that ``base`` holds with the same dtype, shape and bytes."""
    own = base.to_arrays()
    names = []
    for name, value in arrays.items():
        theirs = own.get(name)
        if theirs is None:
            continue
        a, b = canonical_array(np.asarray(value)), canonical_array(np.asarray(theirs))
        if (a.nbytes < MIN_INHERITED_BYTES or a.dtype != b.dtype or a.shape != b.shape
                or a.dtype.hasobject):
            continue
        # bytes, not values: 0.0 and -0.0 (or two NaNs) compare by value but hash apart
        if a is b or np.array_equal(a.reshape(-1).view(np.uint8), b.reshape(-1).view(np.uint8)):
            names.append(name)
    return names


def _file_image(
    name: str, meta: Mapping[str, str], record: Record, inherited: frozenset[str] = frozenset()
) -> bytes:
    """The bytes of a derived HDF5 file (format version 2, or 3 when fields are inherited:
    those are left out), built in memory.

    HDF5's in-memory ("core") driver without a backing store: the library's many small writes
    (superblock, object headers, heaps, each dataset) go to memory, and the finished image is
    written to disk with one ``write`` and one ``fsync`` (:func:`.durable.write_synced`). The
    image is byte for byte an ordinary HDF5 file. Provenance is one JSON attribute and the
    datasets are made with h5py's low-level calls: per attribute and per dataset, h5py's
    high-level layer costs more than HDF5 itself for arrays this small.
    """
    with h5py.File(
        name, "w", driver="core", backing_store=False, locking=False, libver="earliest"
    ) as h5:
        h5.attrs["format"] = FORMAT_NAME
        version = FORMAT_VERSION_INHERITING if inherited else FORMAT_VERSION
        h5.attrs["format_version"] = np.int64(version)
        h5.attrs[PROVENANCE] = json.dumps(dict(meta), sort_keys=True, separators=(",", ":"))
        group = h5.create_group("record").id
        for key, value in record.to_arrays().items():
            if key not in inherited:
                _put(group, key, np.asarray(value))
        h5.flush()
        return bytes(h5.id.get_file_image())


def _put(group: h5py.h5g.GroupID, name: str, array: np.ndarray) -> None:
    # contiguous, no filters: what Group.create_dataset(name, data=array) makes, for less
    if array.dtype.kind in "OUV":  # h5py's own rules for objects, unicode, void
        h5py.Group(group).create_dataset(name, data=array)
        return
    if not array.flags.c_contiguous:
        array = array.copy(order="C")  # (ascontiguousarray would turn a scalar into 1-d)
    space = (
        h5py.h5s.create(h5py.h5s.SCALAR) if array.ndim == 0 else h5py.h5s.create_simple(array.shape)
    )
    dataset = h5py.h5d.create(group, name.encode(), h5py.h5t.py_create(array.dtype), space)
    if array.size:
        dataset.write(h5py.h5s.ALL, h5py.h5s.ALL, array)


def _provenance(h5: h5py.File) -> dict[str, str]:
    """The provenance strings of an open derived file, of either format version."""
    if PROVENANCE in h5.attrs:
        try:
            meta = json.loads(_text(h5.attrs[PROVENANCE]))
        except ValueError:
            return {}
        return (
            {key: str(meta[key]) for key in _META_KEYS if key in meta}
            if isinstance(meta, dict)
            else {}
        )
    return {key: _text(h5.attrs[key]) for key in _META_KEYS if key in h5.attrs}


def _text(value: Any) -> str:
    return value.decode("utf-8") if isinstance(value, bytes) else str(value)


class RecentRecords:
    """The last few records one reader read and checked, by path and content hash.

    Parameters
    ----------
    size : int, optional
        How many are kept (the newest).
    """

    def __init__(self, size: int = 8) -> None:
        self.size = size
        self._records: OrderedDict[tuple[str, str], Record] = OrderedDict()

    def get(self, relative: str, checksum: str) -> Record | None:
        """The record stored at ``relative`` with content hash ``checksum``, if kept."""
        return self._records.get((relative, checksum))

    def put(self, relative: str, checksum: str, record: Record) -> None:
        """Keep ``record``, read from ``relative`` and checked to have ``checksum``."""
        self._records[(relative, checksum)] = record
        self._records.move_to_end((relative, checksum))
        while len(self._records) > self.size:
            self._records.popitem(last=False)


class DerivedStore:
    """Write-once store of stage results under ``<root>/derived``.

    Parameters
    ----------
    root : Path
        Archive root (the folder that also holds ``raw/``).
    resolve : callable, optional
        Record kind → record class; raises NotFoundError for an unknown kind. By default the
        classes already imported (:func:`rasterserver.records.record_type`); the pipeline
        passes :meth:`rasterserver.registry.Registry.record_type`.
    """

    def __init__(self, root: Path, *, resolve: Callable[[str], type[Record]] = record_type) -> None:
        self.root = Path(root)
        self.area = self.root / AREA
        self.resolve = resolve

    # --- names -----------------------------------------------------------------------------

    def path_for(self, uid: str, stage: str, chain_key: str) -> Path:
        """Return the final path of a result (whether or not it exists).

        Parameters
        ----------
        uid : str
            Acquisition uid.
        stage : str
            Stage kind, lowercase letters, digits, ``-`` and ``_``.
        chain_key : str
            64 hex digits.

        Returns
        -------
        Path
        """
        validate_uid(uid)
        if not _STAGE.fullmatch(stage):
            raise InputError(f"invalid stage kind {stage!r} for a derived file name")
        if not _KEY.fullmatch(chain_key):
            raise InputError(f"invalid chain key {chain_key!r}: expected 64 hex digits")
        return shard_path(self.area, uid, f".{stage}-{chain_key[:KEY_DIGITS]}{SUFFIX}")

    def relative_path(self, uid: str, stage: str, chain_key: str) -> str:
        """Path of a result relative to the archive root, POSIX separators."""
        return self.path_for(uid, stage, chain_key).relative_to(self.root).as_posix()

    def _absolute(self, relative: str) -> Path:
        path = (self.root / relative).resolve()
        if not path.is_relative_to(self.area.resolve()):
            raise InputError(f"{relative!r} is not a derived-results path")
        return path

    # --- writing ---------------------------------------------------------------------------

    def write(
        self,
        uid: str,
        record: Record,
        *,
        stage: str,
        plugin: str,
        plugin_version: str,
        params: Mapping[str, Any],
        params_hash: str,
        chain_key: str,
        input_checksum: str,
        sync_dir: bool = True,
        checksum: str | None = None,
        base: StoredBase | None = None,
        pending: PendingFiles | None = None,
    ) -> StoredResult:
        """Store one stage result durably; never replaces a file.

        If the final file exists already and holds the same chain key and content (a crash
        after publishing, or a concurrent worker computing the same thing), it is adopted.

        Parameters
        ----------
        uid : str
            Acquisition uid.
        record : Record
            The stage's output.
        stage, plugin, plugin_version : str
            What computed it.
        params : Mapping
            The validated parameters, JSON-ready.
        params_hash, chain_key, input_checksum : str
            Provenance (see :mod:`rasterserver.chain`).
        sync_dir : bool, optional
            Fsync the shard folder after publishing. False when several results of one
            acquisition are written in a row (they share its folder): the caller then calls
            :meth:`sync` once, before any catalogue row names them.
        checksum : str, optional
            ``record.content_hash()`` when the caller has it already.
        base : StoredBase, optional
            The stored record this one was computed from: the fields they share byte for
            byte are not stored again but read from its file (format version 3). Only a
            result's catalogue parent may be its base (pruning keeps parents).
        pending : PendingFiles, optional
            If deferring, the file is left to it unsynced and unpublished (its ``publish``).

        Returns
        -------
        StoredResult

        Raises
        ------
        ConflictError
            A file with this name exists but holds something else.
        """
        final = self.path_for(uid, stage, chain_key)
        relative = final.relative_to(self.root).as_posix()
        checksum = checksum or record.content_hash()
        reason = str(getattr(record, "reason", "") or "")
        adopt = partial(self._adopt, final, relative, chain_key, checksum, record.kind, reason)
        if final.exists():
            return adopt()
        defer = pending is not None and pending.deferring
        ensure_dir(final.parent, sync=not defer)
        temp = temp_path(final)
        meta = {
            "acquisition": uid,
            "stage": stage,
            "plugin": plugin,
            "plugin_version": plugin_version,
            "params": json.dumps(dict(params), sort_keys=True, separators=(",", ":")),
            "params_hash": params_hash,
            "chain_key": chain_key,
            "input_checksum": input_checksum,
            "output_checksum": checksum,
            "record_kind": record.kind,
            "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            "writer": f"rasterserver {__version__}",
        }
        inherited = _inherited(record.to_arrays(), base.record) if base is not None else []
        if base is not None and inherited:
            meta["base"] = base.path
            meta["base_checksum"] = base.checksum
            meta["inherited"] = json.dumps(sorted(inherited))
        try:
            write_synced(temp, _file_image(temp.name, meta, record, frozenset(inherited)),
                         sync=not defer)
            if pending is not None and defer:
                pending.add(uid, temp, final, adopt)
                return StoredResult(relative, checksum, False, record.kind, reason)
            try:
                publish(temp, final, sync_dir=sync_dir)
            except ConflictError:  # another writer published the same name since our check
                return adopt()
        except Exception:
            temp.unlink(missing_ok=True)
            raise
        return StoredResult(relative, checksum, False, record.kind, reason)

    def sync(self, uid: str) -> None:
        """Fsync the shard folder of ``uid`` (see ``sync_dir`` in :meth:`write`)."""
        folder = shard_path(self.area, uid, SUFFIX).parent
        if folder.is_dir():
            fsync_dir(folder)

    def _adopt(
        self, final: Path, relative: str, chain_key: str, checksum: str, kind: str, reason: str
    ) -> StoredResult:
        try:
            meta = self.metadata(relative)
        except IntegrityError as exc:
            raise ConflictError(f"{relative} exists but is unreadable: {exc}") from None
        if meta.get("chain_key") != chain_key or meta.get("output_checksum") != checksum:
            raise ConflictError(f"{relative} exists with other contents; derived files are "
                                "write-once")
        return StoredResult(relative, checksum, True, kind, reason)

    # --- reading ---------------------------------------------------------------------------

    def metadata(self, relative: str) -> dict[str, str]:
        """The provenance attributes of a stored result (without reading its arrays).

        Raises
        ------
        NotFoundError
            No such file.
        IntegrityError
            Not a readable derived file.
        """
        with self._open(relative) as h5:
            return _provenance(h5)

    def read(
        self,
        relative: str,
        *,
        expected_checksum: str | None = None,
        recent: RecentRecords | None = None,
    ) -> Record:
        """Load a stored result as its record class.

        Parameters
        ----------
        relative : str
            Path relative to the archive root (as in the catalogue).
        expected_checksum : str, optional
            Content hash the record must have (the catalogue's ``output_checksum``); a
            mismatch means the file was altered and raises.
        recent : RecentRecords, optional
            Records this caller read and checked a moment ago: a base found there is not
            read again (``verify`` reads every result, bases before the results built on
            them).

        Returns
        -------
        Record

        Raises
        ------
        NotFoundError
            The file is missing.
        IntegrityError
            It, or the base it inherits fields from, is damaged or missing.
        """
        return self._read(relative, expected_checksum, recent, depth=0)

    def _read(
        self,
        relative: str,
        expected_checksum: str | None,
        recent: RecentRecords | None,
        *,
        depth: int,
    ) -> Record:
        # depth: how many results built on this one are being read (inherited fields), a
        # bound against a cycle of bases in a forged file
        with self._open(relative) as h5:
            meta = _provenance(h5)
            kind = meta.get("record_kind", "")
            stored = meta.get("output_checksum", "")
            group = h5.get("record")
            if not isinstance(group, h5py.Group):
                raise IntegrityError(f"{relative}: no record group")
            try:
                arrays = {name: np.asarray(ds[()]) for name, ds in group.items()}
            except (OSError, ValueError) as exc:
                raise IntegrityError(f"{relative}: unreadable record ({exc})") from None
        if meta.get("inherited"):
            arrays.update(self._inherited_arrays(relative, meta, depth, recent))
        try:
            cls = self.resolve(kind)
        except NotFoundError:
            raise IntegrityError(
                f"{relative}: record kind {kind!r} is unknown here (is its plugin installed?)"
            ) from None
        try:
            record = cls.from_arrays(arrays)
        except (InputError, TypeError) as exc:
            raise IntegrityError(f"{relative}: stored {kind} record is invalid: {exc}") from None
        digest = record.content_hash()
        for expected in (stored, expected_checksum):
            if expected and digest != expected:
                raise IntegrityError(f"{relative}: contents do not match their checksum")
        if recent is not None:
            recent.put(relative, digest, record)
        return record

    def _inherited_arrays(
        self, relative: str, meta: Mapping[str, str], depth: int, recent: RecentRecords | None
    ) -> dict[str, np.ndarray]:
        """The fields a format-3 file inherits, read from its base."""
        base = meta.get("base", "")
        try:
            names = json.loads(meta["inherited"])
        except ValueError:
            names = None
        if not base or not isinstance(names, list) or depth >= _MAX_BASES:
            raise IntegrityError(f"{relative}: its inherited fields have no usable base")
        checksum = meta.get("base_checksum", "")
        known = recent.get(base, checksum) if recent is not None and checksum else None
        try:
            record = known if known is not None else self._read(
                base, checksum or None, recent, depth=depth + 1)
        except NotFoundError:
            raise IntegrityError(
                f"{relative}: the result it inherits fields from, {base}, is missing"
            ) from None
        except IntegrityError as exc:
            raise IntegrityError(f"{relative}: its base is damaged ({exc})") from None
        arrays = record.to_arrays()
        missing = [name for name in names if name not in arrays]
        if missing:
            raise IntegrityError(f"{relative}: its base {base} lacks {', '.join(missing)}")
        return {name: np.asarray(arrays[name]) for name in names}

    def _open(self, relative: str) -> h5py.File:
        path = self._absolute(relative)
        if not path.is_file():
            raise NotFoundError(f"derived result {relative} is missing")
        try:
            h5 = h5py.File(path, "r", locking=False)
        except OSError as exc:
            raise IntegrityError(f"{relative}: unreadable HDF5 file ({exc})") from None
        if _text(h5.attrs.get("format", "")) != FORMAT_NAME:
            h5.close()
            raise IntegrityError(f"{relative}: not a rasterserver derived file")
        return h5

    def exists(self, relative: str) -> bool:
        """True if the file ``relative`` exists."""
        return self._absolute(relative).is_file()

    def scan(self) -> Iterator[DerivedEntry]:
        """List every file under ``<root>/derived``, sorted.

        Yields
        ------
        DerivedEntry
        """
        if not self.area.is_dir():
            return
        for top in sorted(self.area.iterdir()):
            subs = sorted(top.iterdir()) if top.is_dir() else [top]
            for sub in subs:
                files = sorted(sub.iterdir()) if sub.is_dir() else [sub]
                for path in files:
                    yield _classify(path, top.name + sub.name)


def _classify(path: Path, shard: str) -> DerivedEntry:
    match = _NAME.fullmatch(path.name)
    if match is None or not path.is_file() or match["uid"][:4] != shard:
        return DerivedEntry(path, "stray")
    kind: Literal["final", "temp"] = "temp" if match["temp"] else "final"
    return DerivedEntry(path, kind, match["uid"], match["stage"], match["key"])
