"""Derived-results store: durable write-once files, round trips, adoption, scanning, damage."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import h5py
import numpy as np
import pytest

from rasterserver.errors import ConflictError, InputError, IntegrityError, NotFoundError
from rasterserver.records import Image
from rasterserver.records_lines import Lines, Peaks
from rasterserver.records_surface import MeshRecord, Points, Surface
from rasterserver.store.derived import DerivedStore, RecentRecords, StoredBase

UID = "0123456789abcdef0123456789abcdef"
KEY = hashlib.sha256(b"chain").hexdigest()


def _points(n: int = 50) -> Points:
    rng = np.random.default_rng(0)
    return Points(
        x=rng.normal(size=n),
        y=rng.normal(size=n),
        z=rng.normal(size=n),
        number=np.arange(n, dtype=np.int32),
        col=np.arange(n, dtype=np.int32),
        row=rng.uniform(0, 600, n),
        area=rng.uniform(0, 200, n).astype(np.float32),
        image_shape=np.array([604, 576]),
        reason="3 peaks dropped; Wirbelsäule",
    )


def _write(store: DerivedStore, record, *, key: str = KEY, stage: str = "points"):
    return store.write(
        UID,
        record,
        stage=stage,
        plugin="points.ray-plane",
        plugin_version="1",
        params={"tolerance": 1e-7},
        params_hash="ab" * 32,
        chain_key=key,
        input_checksum="cd" * 32,
    )


@pytest.mark.parametrize(
    "record",
    [
        _points(),
        Points.empty((604, 576), "no numbered raster lines"),
        Surface(x0=-3.0, y0=6.0, spacing=3.0, z=np.array([[1.0, np.nan], [2.0, 3.0]])),
        Surface.empty("no points"),
        MeshRecord.empty("nothing"),
        Image(np.arange(12, dtype=np.uint16).reshape(3, 4)),
    ],
    ids=["points", "empty-points", "surface", "empty-surface", "empty-mesh", "image"],
)
def test_round_trip_keeps_content_and_checksum(tmp_path: Path, record) -> None:
    store = DerivedStore(tmp_path)
    stored = _write(store, record)
    assert stored.output_checksum == record.content_hash() and not stored.adopted
    assert stored.path == f"derived/01/23/{UID}.points-{KEY[:32]}.h5"
    back = store.read(stored.path, expected_checksum=stored.output_checksum)
    assert type(back) is type(record) and back == record
    meta = store.metadata(stored.path)
    assert meta["acquisition"] == UID and meta["plugin"] == "points.ray-plane"
    assert meta["chain_key"] == KEY and meta["record_kind"] == record.kind
    assert meta["params"] == '{"tolerance":1e-07}'


def test_files_are_plain_hdf5(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    stored = _write(store, _points())
    with h5py.File(tmp_path / stored.path, "r") as h5:
        assert h5.attrs["format"] == "rasterserver-derived"
        assert int(h5.attrs["format_version"]) == 2
        provenance = json.loads(h5.attrs["provenance"])
        assert provenance["chain_key"] == KEY and provenance["acquisition"] == UID
        assert h5["record/x"].shape == (50,) and h5["record/x"].dtype == np.float64
        assert h5["record/x"].chunks is None and h5["record/x"].compression is None
        assert h5["record/reason"][()].decode() == "3 peaks dropped; Wirbelsäule"
        assert h5["record/col"].dtype == np.int32 and h5["record/area"].dtype == np.float32


def _write_format_1(path: Path, record, *, chain_key: str = KEY) -> None:
    """A file as the store wrote it before format version 2: one root attribute per string."""
    meta = {
        "acquisition": UID,
        "stage": "points",
        "plugin": "points.ray-plane",
        "plugin_version": "1",
        "params": '{"tolerance":1e-07}',
        "params_hash": "ab" * 32,
        "chain_key": chain_key,
        "input_checksum": "cd" * 32,
        "output_checksum": record.content_hash(),
        "record_kind": record.kind,
        "created_utc": "2026-11-01T10:00:00+00:00",
        "writer": "rasterserver 0.9",
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w-", locking=False, libver="earliest") as h5:
        h5.attrs["format"] = "rasterserver-derived"
        h5.attrs["format_version"] = np.int64(1)
        for name, value in meta.items():
            h5.attrs[name] = value
        group = h5.create_group("record")
        for name, array in record.to_arrays().items():
            group.create_dataset(name, data=np.asarray(array))


@pytest.mark.parametrize("record", [_points(), Surface.empty("no points")], ids=["points", "empty"])
def test_files_of_format_1_still_read_and_are_adopted(tmp_path: Path, record) -> None:
    store = DerivedStore(tmp_path)
    relative = store.relative_path(UID, "points", KEY)
    _write_format_1(tmp_path / relative, record)
    back = store.read(relative, expected_checksum=record.content_hash())
    assert type(back) is type(record) and back == record
    meta = store.metadata(relative)
    assert meta["chain_key"] == KEY and meta["writer"] == "rasterserver 0.9"
    # the same computation again adopts the old file instead of refusing it
    assert _write(store, record).adopted


def test_same_result_twice_is_adopted_other_content_refused(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    first = _write(store, _points())
    again = _write(store, _points())
    assert again.adopted and again.path == first.path
    other = dataclasses.replace(_points(), reason="different")
    with pytest.raises(ConflictError, match="write-once"):
        _write(store, other)
    assert [e.kind for e in store.scan()] == ["final"]


def test_no_temporary_file_is_left_after_a_failed_write(tmp_path: Path, monkeypatch) -> None:
    store = DerivedStore(tmp_path)

    def broken(_fd: int) -> None:
        raise OSError("disk full")

    # fails after the temporary file exists: it must be removed
    monkeypatch.setattr("rasterserver.store.durable.os.fsync", broken)
    with pytest.raises(OSError, match="disk full"):
        _write(store, _points())
    assert list(store.scan()) == []


def test_scan_tells_final_temporary_and_stray_files(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    stored = _write(store, _points())
    folder = (tmp_path / stored.path).parent
    (folder / f"{stored.path.rsplit('/', 1)[1]}.tmp-123-abcd").write_bytes(b"partial")
    (folder / "notes.txt").write_text("?")
    kinds = {e.path.name: (e.kind, e.uid, e.stage) for e in store.scan()}
    assert kinds[Path(stored.path).name] == ("final", UID, "points")
    assert ("temp", UID, "points") in kinds.values()
    assert kinds["notes.txt"] == ("stray", None, None)


def test_altered_or_missing_files_are_integrity_errors(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    stored = _write(store, _points())
    path = tmp_path / stored.path
    os.chmod(path, 0o644)
    with h5py.File(path, "r+", locking=False) as h5:
        h5["record/z"][0] = 99.0
    with pytest.raises(IntegrityError, match="checksum"):
        store.read(stored.path)
    path.write_bytes(b"not hdf5")
    with pytest.raises(IntegrityError, match="unreadable"):
        store.read(stored.path)
    path.unlink()
    with pytest.raises(NotFoundError, match="missing"):
        store.read(stored.path)


def test_names_are_validated(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    with pytest.raises(InputError, match="uid"):
        store.path_for("../../etc", "points", KEY)
    with pytest.raises(InputError, match="stage"):
        store.path_for(UID, "../x", KEY)
    with pytest.raises(InputError, match="chain key"):
        store.path_for(UID, "points", "abc")
    with pytest.raises(InputError, match="not a derived"):
        store.read("raw/01/23/x.h5")


# --- inherited fields (format version 3) -------------------------------------------------------


def _peaks(n: int = 4000) -> Peaks:
    rng = np.random.default_rng(1)
    return Peaks(
        col=(np.arange(n) // 4).astype(np.int32),  # sorted by (col, row)
        row=(np.arange(n) % 4) * 100.0 + rng.uniform(0, 50, n),
        area=rng.uniform(1, 200, n).astype(np.float32),
        height=rng.uniform(1, 50, n).astype(np.float32),
        width=rng.integers(3, 9, n).astype(np.int16),
        image_shape=np.array([576, 604]),
        dropped=3,
    )


def _write_on(store: DerivedStore, record, stage: str, key: str, base=None):
    return store.write(
        UID, record, stage=stage, plugin=f"{stage}.x", plugin_version="1", params={},
        params_hash="ab" * 32, chain_key=key, input_checksum="cd" * 32, base=base,
    )


def _chain(store: DerivedStore, lines: Lines | None = None):
    """A peaks result and a lines result built on it, as the worker stores them."""
    peaks = _peaks()
    first = _write_on(store, peaks, "peaks", "1" * 64)
    lines = lines or Lines.extend(peaks, line_id=np.arange(peaks.n_peaks, dtype=np.int32) // 40)
    second = _write_on(store, lines, "lines", "2" * 64,
                       base=StoredBase(first.path, peaks, first.output_checksum))
    return peaks, first, lines, second


def test_a_result_stores_only_what_its_base_lacks(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    peaks, first, lines, second = _chain(store)
    with h5py.File(tmp_path / second.path, "r") as h5:
        assert int(h5.attrs["format_version"]) == 3
        # row, col, area, height, width come from the peaks file; the small fields are
        # stored again (image_shape, dropped), the new one too
        assert sorted(h5["record"]) == ["dropped", "image_shape", "line_id"]
    meta = store.metadata(second.path)
    assert meta["base"] == first.path and meta["base_checksum"] == first.output_checksum
    assert json.loads(meta["inherited"]) == ["area", "col", "height", "row", "width"]
    back = store.read(second.path, expected_checksum=lines.content_hash())
    assert type(back) is Lines and back == lines
    assert (tmp_path / second.path).stat().st_size < (tmp_path / first.path).stat().st_size / 2
    # the same computation again adopts it
    assert _write_on(store, lines, "lines", "2" * 64,
                     base=StoredBase(first.path, peaks, first.output_checksum)).adopted


def test_only_fields_with_the_same_bytes_are_inherited(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    peaks = _peaks()
    flipped = peaks.row.copy()
    flipped[5] = np.nextafter(flipped[5], np.inf)  # one bit apart
    lines = Lines(col=peaks.col.copy(), row=flipped, area=peaks.area.astype(np.float32),
                  height=peaks.height, width=peaks.width, image_shape=peaks.image_shape,
                  line_id=np.zeros(peaks.n_peaks, dtype=np.int32), dropped=3)
    _, _, _, second = _chain(store, lines)
    assert json.loads(store.metadata(second.path)["inherited"]) == [
        "area", "col", "height", "width"]
    assert store.read(second.path, expected_checksum=lines.content_hash()) == lines


def test_zero_and_negative_zero_are_not_the_same_bytes(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    peaks = dataclasses.replace(_peaks(), row=np.zeros(4000))
    first = _write_on(store, peaks, "peaks", "1" * 64)
    lines = Lines.extend(peaks, row=np.full(4000, -0.0), line_id=np.zeros(4000, np.int32))
    second = _write_on(store, lines, "lines", "2" * 64,
                       base=StoredBase(first.path, peaks, first.output_checksum))
    assert "row" not in json.loads(store.metadata(second.path)["inherited"])
    assert np.signbit(store.read(second.path).row).all()


def test_nothing_in_common_writes_an_ordinary_file(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    peaks = _peaks()
    first = _write_on(store, peaks, "peaks", "1" * 64)
    stored = _write_on(store, _points(), "points", "3" * 64,
                       base=StoredBase(first.path, peaks, first.output_checksum))
    meta = store.metadata(stored.path)
    assert "base" not in meta and "inherited" not in meta
    with h5py.File(tmp_path / stored.path, "r") as h5:
        assert int(h5.attrs["format_version"]) == 2


def test_a_missing_or_damaged_base_is_an_integrity_error(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    _, first, _, second = _chain(store)
    base = tmp_path / first.path
    os.chmod(base, 0o644)
    with h5py.File(base, "r+", locking=False) as h5:
        h5["record/row"][0] = 1e6
    with pytest.raises(IntegrityError, match="its base is damaged"):
        store.read(second.path)
    base.unlink()
    with pytest.raises(IntegrityError, match=r"inherits fields from, derived/.*, is missing"):
        store.read(second.path)


def test_a_forged_base_cycle_is_refused(tmp_path: Path) -> None:
    store = DerivedStore(tmp_path)
    _, _, _, second = _chain(store)
    path = tmp_path / second.path
    os.chmod(path, 0o644)
    with h5py.File(path, "r+", locking=False) as h5:
        meta = json.loads(h5.attrs["provenance"])
        meta["base"] = second.path  # its own base
        meta.pop("base_checksum")
        h5.attrs["provenance"] = json.dumps(meta)
    with pytest.raises(IntegrityError, match="no usable base"):
        store.read(second.path)


def test_a_recent_base_is_not_read_again(tmp_path: Path, monkeypatch) -> None:
    store = DerivedStore(tmp_path)
    _, first, lines, second = _chain(store)
    recent = RecentRecords(size=2)
    store.read(first.path, recent=recent)
    opened: list[str] = []
    original = DerivedStore._open

    def counting(self: DerivedStore, relative: str):
        opened.append(relative)
        return original(self, relative)

    monkeypatch.setattr(DerivedStore, "_open", counting)
    assert store.read(second.path, recent=recent) == lines
    assert opened == [second.path]  # the base came from the reader's recent records
    # a base recorded under another checksum (its file was replaced since) is read again
    other = RecentRecords()
    other.put(first.path, "0" * 64, lines)
    opened.clear()
    assert store.read(second.path, recent=other) == lines
    assert opened == [second.path, first.path]
    # only the newest records are kept
    small = RecentRecords(size=1)
    small.put("a", "1", lines)
    small.put("b", "2", lines)
    assert small.get("a", "1") is None and small.get("b", "2") is lines
