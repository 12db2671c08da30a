"""The archive service on real HDF5 files and a real catalogue (SQLite and PostgreSQL)."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
from sqlalchemy import func, select

from rasterserver.archive import Archive, FrameSource
from rasterserver.catalog.models import Acquisition, Calibration, Frame
from rasterserver.config import Settings
from rasterserver.errors import ConflictError, InputError, NotFoundError
from rasterserver.optics import default_station

RNG_SEED = 20261122


def _frame(seed: int = 0, shape: tuple[int, int] = (604, 576), dtype: str = "uint8") -> np.ndarray:
    info = np.iinfo(dtype)
    rng = np.random.default_rng(RNG_SEED + seed)
    return rng.integers(0, info.max, size=shape, dtype=dtype, endpoint=True)


@pytest.fixture
def archive(settings: Settings) -> Archive:
    arch = Archive.create(settings)
    arch.add_patient("P001", name="Jane Doe", birth_date=dt.date(2010, 3, 4), sex="female")
    yield arch
    arch.close()


def _stored_nothing(archive: Archive) -> bool:
    with archive.session() as s:
        rows = s.scalar(select(func.count()).select_from(Acquisition))
        frames = s.scalar(select(func.count()).select_from(Frame))
    files = [p for p in (archive.settings.archive / "raw").rglob("*") if p.is_file()]
    return rows == 0 and frames == 0 and not files


def test_ingest_stores_every_frame_bit_exact(archive: Archive, tmp_path: Path) -> None:
    a8, a16 = _frame(1), _frame(2, dtype="uint16")
    cv2.imwrite(str(tmp_path / "a.png"), a8)
    cv2.imwrite(str(tmp_path / "b.tif"), a16)
    np.save(tmp_path / "c.npy", a8)
    acq = archive.ingest(
        [
            FrameSource(tmp_path / "a.png", role="raster"),
            FrameSource(tmp_path / "b.tif", role="projector-off"),
            FrameSource(tmp_path / "c.npy", role="projector-on"),
        ],
        patient="P001",
        operator="op",
    )
    assert [f.role for f in acq.frames] == ["raster", "projector-off", "projector-on"]
    np.testing.assert_array_equal(archive.read_frame(acq.uid, 0), a8)
    np.testing.assert_array_equal(archive.read_frame(acq.uid, 1), a16)
    assert archive.read_frame(acq.uid, 1).dtype == np.uint16
    with h5py.File(archive.raw.path_for(acq.uid), "r") as h5:
        stored = {int(k): h5["frames"][k].attrs["sha256"] for k in h5["frames"]}
    assert stored == {f.index: f.sha256 for f in acq.frames}
    assert archive.verify().ok
    # The raw frame cannot be modified through what read_frame returns.
    with pytest.raises(ValueError):
        archive.read_frame(acq.uid, 0)[0, 0] = 1


def test_raw_bytes_need_and_use_shape_and_dtype(archive: Archive, tmp_path: Path) -> None:
    a = _frame(3, shape=(48, 32), dtype="uint16")
    (tmp_path / "f.raw").write_bytes(a.tobytes())
    acq = archive.ingest(
        [FrameSource(tmp_path / "f.raw")], patient="P001", shape=(48, 32), dtype="uint16"
    )
    np.testing.assert_array_equal(archive.read_frame(acq.uid), a)
    with pytest.raises(InputError):
        archive.ingest(
            [FrameSource(tmp_path / "f.raw")], patient="P001", shape=(48, 33), dtype="uint16"
        )


def _bad_inputs(tmp_path: Path) -> dict[str, Path]:
    good = _frame(4, shape=(60, 50))
    files: dict[str, Path] = {}
    cv2.imwrite(str(tmp_path / "colour.png"), np.dstack([good, good // 2, good // 3]))
    files["colour"] = tmp_path / "colour.png"
    np.save(tmp_path / "one_d.npy", good.ravel())
    files["one-dimensional"] = tmp_path / "one_d.npy"
    np.save(tmp_path / "stack.npy", np.stack([good, good]))
    files["stack"] = tmp_path / "stack.npy"
    (tmp_path / "empty.png").write_bytes(b"")
    files["empty"] = tmp_path / "empty.png"
    cv2.imwrite(str(tmp_path / "whole.png"), good)
    data = (tmp_path / "whole.png").read_bytes()
    (tmp_path / "truncated.png").write_bytes(data[: len(data) // 2])
    files["truncated"] = tmp_path / "truncated.png"
    (tmp_path / "notes.png").write_text("this is not an image\n")
    files["not-an-image"] = tmp_path / "notes.png"
    np.save(tmp_path / "float.npy", good.astype(np.float32))
    files["float"] = tmp_path / "float.npy"
    np.save(tmp_path / "empty_frame.npy", np.zeros((0, 50), np.uint8))
    files["zero-size"] = tmp_path / "empty_frame.npy"
    return files


@pytest.mark.parametrize(
    "case",
    [
        "colour",
        "one-dimensional",
        "stack",
        "empty",
        "truncated",
        "not-an-image",
        "float",
        "zero-size",
    ],
)
def test_bad_frame_stores_nothing_even_beside_good_ones(
    archive: Archive, tmp_path: Path, case: str
) -> None:
    bad = _bad_inputs(tmp_path)[case]
    np.save(tmp_path / "good.npy", _frame(5, shape=(60, 50)))
    with pytest.raises(InputError) as err:
        archive.ingest([FrameSource(tmp_path / "good.npy"), FrameSource(bad)], patient="P001")
    assert bad.name in str(err.value)
    assert _stored_nothing(archive)


def test_oversized_frame_refused(settings: Settings, tmp_path: Path) -> None:
    small = Settings(
        archive=settings.archive, database_url=settings.database_url, max_frame_bytes=1000
    )
    with Archive.create(small) as archive:
        archive.add_patient("P001")
        np.save(tmp_path / "big.npy", _frame(6, shape=(100, 100)))
        with pytest.raises(InputError, match=r"limit|larger|exceeds"):
            archive.ingest([FrameSource(tmp_path / "big.npy")], patient="P001")
        assert _stored_nothing(archive)


def test_colour_converted_when_asked(archive: Archive, tmp_path: Path) -> None:
    grey = _frame(7, shape=(40, 30))
    cv2.imwrite(str(tmp_path / "c.png"), np.dstack([grey, grey, grey]))
    acq = archive.ingest([FrameSource(tmp_path / "c.png")], patient="P001", convert_color=True)
    np.testing.assert_array_equal(archive.read_frame(acq.uid), grey)


def test_unknown_references_store_nothing(archive: Archive, tmp_path: Path) -> None:
    np.save(tmp_path / "f.npy", _frame(8, shape=(20, 20)))
    src = [FrameSource(tmp_path / "f.npy")]
    with pytest.raises(NotFoundError, match="unknown patient"):
        archive.ingest(src, patient="NOBODY")
    with pytest.raises(NotFoundError, match="station"):
        archive.ingest(src, patient="P001", station="nowhere")
    archive.add_station("S1")
    with pytest.raises(NotFoundError, match="calibration"):
        archive.ingest(src, patient="P001", station="S1", calibration_version=3)
    with pytest.raises(InputError):
        archive.ingest([], patient="P001")
    with pytest.raises(InputError, match="role"):
        archive.ingest([FrameSource(tmp_path / "f.npy", role="selfie")], patient="P001")
    assert _stored_nothing(archive)


def test_patient_identifier_unique(archive: Archive) -> None:
    with pytest.raises(ConflictError):
        archive.add_patient("P001")
    with pytest.raises(InputError):
        archive.add_patient("   ")


def _calibration(name: str) -> dict[str, object]:
    """A calibration of a 20x20 camera (the test frames' size)."""
    return default_station(width=20, height=20, name=name).to_dict()


def test_calibrations_are_versioned_and_immutable(archive: Archive, tmp_path: Path) -> None:
    archive.add_station("S1")
    first = archive.add_calibration("S1", _calibration("first"))
    second = archive.add_calibration("S1", _calibration("second"))
    assert (first.version, second.version) == (1, 2)
    assert archive.calibration("S1").version == 2
    assert archive.calibration("S1", 1).parameters["name"] == "first"
    np.save(tmp_path / "f.npy", _frame(9, shape=(20, 20)))
    acq = archive.ingest([FrameSource(tmp_path / "f.npy")], patient="P001", station="S1")
    assert acq.calibration_id == second.id
    with pytest.raises(ValueError, match="immutable"), archive.session() as s:
        row = s.get(Calibration, first.id)
        assert row is not None
        row.notes = "changed"
        s.flush()
    assert archive.calibration("S1", 1).notes == ""


def test_listing_by_patient_and_time(archive: Archive, tmp_path: Path) -> None:
    archive.add_patient("P002")
    np.save(tmp_path / "f.npy", _frame(10, shape=(20, 20)))
    t0 = dt.datetime(2024, 1, 1, tzinfo=dt.UTC)
    for i in range(4):
        archive.ingest(
            [FrameSource(tmp_path / "f.npy")],
            patient="P001" if i % 2 == 0 else "P002",
            acquired_at=t0 + dt.timedelta(days=30 * i),
        )
    mine = archive.acquisitions(patient="P001")
    assert len(mine) == 2 and all(a.patient and a.patient.identifier == "P001" for a in mine)
    assert mine[0].acquired_at > mine[1].acquired_at  # newest first
    window = archive.acquisitions(
        since=t0 + dt.timedelta(days=10), until=t0 + dt.timedelta(days=70)
    )
    assert len(window) == 2
    assert len(archive.acquisitions(limit=1, offset=3)) == 1
    # Visits are made per patient and day.
    assert mine[0].visit_id != mine[1].visit_id


def _flip_one_pixel_byte(path: Path, dataset: str) -> None:
    """Change one byte of a stored frame on disk, behind the store's back."""
    with h5py.File(path, "r") as h5:
        ds = h5[dataset]
        if ds.chunks is None:
            offset = ds.id.get_offset()
        else:
            info = ds.id.get_chunk_info(0)
            offset = info.byte_offset + info.size // 2
    with path.open("r+b") as fh:
        fh.seek(offset)
        byte = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([byte[0] ^ 0xFF]))


def test_verify_finds_corrupt_missing_orphaned_and_temporary(
    archive: Archive, tmp_path: Path
) -> None:
    np.save(tmp_path / "f.npy", _frame(11))
    acqs = [archive.ingest([FrameSource(tmp_path / "f.npy")], patient="P001") for _ in range(3)]
    assert archive.verify().ok
    corrupt, missing, _ok = acqs
    frame = corrupt.frames[0]
    _flip_one_pixel_byte(archive.raw.path_for(corrupt.uid), frame.dataset)
    archive.raw.path_for(missing.uid).unlink()
    orphan_uid = "f" * 32
    orphan = archive.raw.path_for(orphan_uid)
    orphan.parent.mkdir(parents=True, exist_ok=True)
    orphan.write_bytes(archive.raw.path_for(_ok.uid).read_bytes())
    leftover = archive.raw.path_for("e" * 32).with_name("e" * 32 + ".h5.tmp-1-abc")
    leftover.parent.mkdir(parents=True, exist_ok=True)
    leftover.write_bytes(b"partial")

    report = archive.verify()
    kinds = {(p.kind, p.uid) for p in report.problems}
    assert ("corrupt", corrupt.uid) in kinds or ("unreadable", corrupt.uid) in kinds
    assert ("missing", missing.uid) in kinds
    assert ("orphaned", orphan_uid) in kinds
    assert any(p.kind == "temporary" for p in report.problems)
    assert all(p.uid != _ok.uid for p in report.problems)
    assert not report.ok


def test_ingest_many_is_all_or_nothing(archive: Archive, tmp_path: Path) -> None:
    from rasterserver.archive import AcquisitionSpec

    np.save(tmp_path / "f.npy", _frame(12, shape=(30, 20)))
    good = AcquisitionSpec(frames=[FrameSource(tmp_path / "f.npy")], patient="P001")
    rows = archive.ingest_many([good] * 5, workers=3)
    assert len({r.uid for r in rows}) == 5 and archive.verify().ok
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    bad = AcquisitionSpec(frames=[FrameSource(tmp_path / "bad.png")], patient="P001")
    with pytest.raises(InputError):
        archive.ingest_many([good, good, bad], workers=2)
    unknown = AcquisitionSpec(frames=[FrameSource(tmp_path / "f.npy")], patient="NOBODY")
    with pytest.raises(NotFoundError):
        archive.ingest_many([good, unknown])
    assert len(archive.acquisitions()) == 5
    assert archive.verify().ok  # no file left behind by the refused batches


def test_concurrent_ingests_share_the_visit(archive: Archive) -> None:
    from concurrent.futures import ThreadPoolExecutor

    frame = _frame(13, shape=(30, 20))
    when = dt.datetime(2025, 6, 1, 9, tzinfo=dt.UTC)

    def one(i: int) -> str:
        acq = archive.ingest([FrameSource(frame, name=f"f{i}")], patient="P001", acquired_at=when)
        return acq.uid

    with ThreadPoolExecutor(8) as pool:
        uids = list(pool.map(one, range(16)))
    rows = archive.acquisitions(patient="P001")
    assert sorted(a.uid for a in rows) == sorted(uids)
    assert len({a.visit_id for a in rows}) == 1
    assert archive.verify().ok


def test_ingest_attaches_the_calibration_valid_when_taken(archive: Archive) -> None:
    archive.add_station("S2")
    jan = dt.datetime(2025, 1, 1, tzinfo=dt.UTC)
    old = archive.add_calibration("S2", _calibration("old"), valid_from=jan)
    new = archive.add_calibration("S2", _calibration("new"), valid_from=jan + dt.timedelta(days=90))
    frame = _frame(14, shape=(20, 20))

    def taken(days: int) -> Acquisition:
        return archive.ingest(
            [FrameSource(frame, name="f")], patient="P001", station="S2",
            acquired_at=jan + dt.timedelta(days=days),
        )

    assert taken(30).calibration_id == old.id
    assert taken(120).calibration_id == new.id
    with pytest.raises(NotFoundError, match="valid at"):
        taken(-10)
    explicit = archive.ingest(
        [FrameSource(frame, name="f")], patient="P001", station="S2", calibration_version=2,
        acquired_at=jan + dt.timedelta(days=30),
    )
    assert explicit.calibration_id == new.id


def test_find_returns_the_same_acquisitions_as_summaries(archive: Archive) -> None:
    archive.add_patient("P002")
    frame = _frame(15, shape=(20, 20))
    t0 = dt.datetime(2024, 5, 1, tzinfo=dt.UTC)
    for i in range(5):
        archive.ingest(
            [FrameSource(frame, name="a"), FrameSource(frame, name="b")][: 1 + i % 2],
            patient="P001" if i < 3 else "P002",
            acquired_at=t0 + dt.timedelta(days=i),
        )
    since, until = t0 + dt.timedelta(days=1), t0 + dt.timedelta(days=4)
    full = archive.acquisitions(since=since, until=until)
    found = archive.find(since=since, until=until)
    assert [f.uid for f in found] == [a.uid for a in full]
    assert [[(x.index, x.sha256, x.height) for x in f.frames] for f in found] == [
        [(x.index, x.sha256, x.height) for x in a.frames] for a in full]
    assert all(f.acquired_at.tzinfo is not None for f in found)
    one = archive.info(full[0].uid)
    assert one == found[0] and one.patient_id == full[0].patient_id
    with pytest.raises(NotFoundError):
        archive.info("0" * 32)
    assert [f.patient for f in found] == ["P002", "P001", "P001"]
    assert [f.uid for f in archive.find(patient="P002")] == [
        a.uid for a in archive.acquisitions(patient="P002")
    ]
    assert len(archive.find(limit=2, offset=4)) == 1


def test_ingest_once_stores_a_retried_upload_once(archive: Archive) -> None:
    import threading

    frame = _frame(5, shape=(30, 20))
    first, replayed = archive.ingest_once([FrameSource(frame, name="a")], source="cam-1",
                                          key="k1", patient="P001")
    assert not replayed
    again, replayed = archive.ingest_once([FrameSource(frame, name="renamed")], source="cam-1",
                                          key="k1", patient="P001")
    assert replayed and again.uid == first.uid
    # another source may use the same key for its own upload
    own, replayed = archive.ingest_once([FrameSource(frame)], source="cam-2", key="k1",
                                        patient="P001")
    assert not replayed and own.uid != first.uid
    with pytest.raises(ConflictError, match="different upload"):
        archive.ingest_once([FrameSource(frame)], source="cam-1", key="k1", patient="P001",
                            notes="other metadata")
    with pytest.raises(InputError):
        archive.ingest_once([FrameSource(frame)], source="cam-1", key="", patient="P001")
    # concurrent attempts under one key: one commits, the others get its acquisition
    results: list[tuple[str, bool]] = []
    start = threading.Barrier(4)

    def attempt() -> None:
        start.wait()
        acq, was = archive.ingest_once([FrameSource(_frame(9, shape=(30, 20)))], source="cam-1",
                                       key="k2", patient="P001")
        results.append((acq.uid, was))

    threads = [threading.Thread(target=attempt) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len({uid for uid, _ in results}) == 1 and sum(not was for _, was in results) == 1
    assert len(archive.acquisitions(limit=100)) == 3
    assert archive.verify().ok  # no orphaned file from the attempts that lost
