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
from rasterserver.records_surface import MeshRecord, Points, Surface
from rasterserver.store.derived import DerivedStore

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
