"""Raw store: bit-exact round trips, write-once durability, and corruption found by check_file."""

from __future__ import annotations

import hashlib
import os
import random
import subprocess
import sys
import uuid
from pathlib import Path

import h5py
import numpy as np
import pytest

from rasterserver.errors import ConflictError, InputError, IntegrityError, NotFoundError
from rasterserver.store import FrameToWrite, RawStore, parse_compression
from rasterserver.store.layout import temp_path

SEED = 42
COMPRESSIONS = ["none", "gzip-1", "shuffle+gzip-4", "lzf"]


def _uid(n: int) -> str:
    """A fixed, well-spread uuid4 hex per test (different shards for different n)."""
    return uuid.UUID(bytes=random.Random(n).randbytes(16), version=4).hex


def _frames(dtype: type = np.uint16, shape: tuple[int, int] = (604, 576)) -> list[FrameToWrite]:
    rng = np.random.default_rng(SEED)
    top = np.iinfo(dtype).max
    return [
        FrameToWrite(0, "raster", rng.integers(0, top, shape, dtype=dtype, endpoint=True)),
        FrameToWrite(1, "projector-off", rng.integers(0, top // 8, shape, dtype=dtype)),
    ]


def _hash(array: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()


class SimulatedCrash(BaseException):
    """Not an Exception: like a real crash, nothing in the store gets to clean up."""


# --- round trips -----------------------------------------------------------------------------


@pytest.mark.parametrize("compression", COMPRESSIONS)
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_round_trip_is_bit_exact(tmp_path: Path, compression: str, dtype: type) -> None:
    store = RawStore(tmp_path, compression=compression)
    uid = _uid(1)
    frames = _frames(dtype)
    stored = store.write(uid, frames)

    assert [s.index for s in stored] == [0, 1]
    assert [s.role for s in stored] == ["raster", "projector-off"]
    for s, f in zip(stored, frames, strict=True):
        assert s.sha256 == _hash(f.array)
        assert s.shape == f.array.shape and s.dtype == np.dtype(dtype).name
        assert s.path == f"raw/{uid[:2]}/{uid[2:4]}/{uid}.h5"
        assert s.dataset == f"frames/{f.index}"
        out = store.read(uid, f.index)
        np.testing.assert_array_equal(out, f.array)
        assert out.dtype == dtype and not out.flags.writeable and out.flags.c_contiguous
    every = store.read_all(uid)
    assert list(every) == [0, 1]
    assert store.frames(uid) == stored
    assert store.check_file(uid, {s.index: s.sha256 for s in stored}).ok


def test_file_is_plain_hdf5_with_documented_attributes(tmp_path: Path) -> None:
    store = RawStore(tmp_path)
    uid = _uid(2)
    frames = _frames()
    store.write(uid, frames)
    path = tmp_path / "raw" / uid[:2] / uid[2:4] / f"{uid}.h5"
    assert store.path_for(uid) == path and store.exists(uid)
    # Read as a third party would: plain h5py and hashlib, no rasterserver code.
    with h5py.File(path, "r") as h5:
        assert h5.attrs["format"] == "rasterserver-raw"
        assert h5.attrs["format_version"] == 1
        assert h5.attrs["uid"] == uid
        assert h5.attrs["frame_count"] == 2
        assert "created_utc" in h5.attrs and "writer" in h5.attrs
        for f in frames:
            ds = h5[f"frames/{f.index}"]
            assert ds.attrs["index"] == f.index and ds.attrs["role"] == f.role
            assert ds.attrs["sha256"] == hashlib.sha256(ds[()].astype("<u2").tobytes()).hexdigest()


def test_degenerate_frames(tmp_path: Path) -> None:
    store = RawStore(tmp_path, compression="gzip-1")
    frames = [
        FrameToWrite(0, "raster", np.array([[7]], np.uint8)),
        FrameToWrite(1, "raster", np.zeros((604, 576), np.uint8)),
        FrameToWrite(2, "raster", np.full((604, 576), 65535, np.uint16)),
        FrameToWrite(3, "raster", np.array([[65535]], np.uint16)),
    ]
    uid = _uid(3)
    store.write(uid, frames)
    for f in frames:
        np.testing.assert_array_equal(store.read(uid, f.index), f.array)
    assert store.check_file(uid).ok


def test_big_endian_and_strided_inputs_are_stored_canonically(tmp_path: Path) -> None:
    store = RawStore(tmp_path)
    base = _frames()[0].array
    big = base.astype(">u2")
    strided = np.asfortranarray(base)[:, ::1]
    a, b = _uid(4), _uid(5)
    (sa,) = store.write(a, [FrameToWrite(0, "raster", big)])
    (sb,) = store.write(b, [FrameToWrite(0, "raster", strided)])
    assert sa.sha256 == sb.sha256 == _hash(base.astype("<u2"))
    np.testing.assert_array_equal(store.read(a, 0), base)


def test_large_frames_are_chunked_in_row_bands(tmp_path: Path) -> None:
    store = RawStore(tmp_path, compression="shuffle+gzip-1")
    frame = np.zeros((2448, 2048), np.uint16)
    uid = _uid(6)
    store.write(uid, [FrameToWrite(0, "raster", frame)])
    with h5py.File(store.path_for(uid), "r") as h5:
        chunks = h5["frames/0"].chunks
    assert chunks is not None and chunks[1] == 2048 and chunks[0] * 2048 * 2 <= 1024 * 1024


def test_uncompressed_frames_are_contiguous(tmp_path: Path) -> None:
    store = RawStore(tmp_path, compression="none")
    uid = _uid(7)
    store.write(uid, _frames())
    with h5py.File(store.path_for(uid), "r") as h5:
        assert h5["frames/0"].chunks is None and h5["frames/0"].compression is None


# --- refused writes --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("frames", "message"),
    [
        ([], "at least one frame"),
        ([FrameToWrite(0, "raster", np.zeros((2, 2), np.uint8))] * 2, "appears twice"),
        ([FrameToWrite(-1, "raster", np.zeros((2, 2), np.uint8))], "non-negative"),
        ([FrameToWrite(0, "", np.zeros((2, 2), np.uint8))], "role"),
        ([FrameToWrite(0, "raster", np.zeros((2, 2, 3), np.uint8))], "2-D"),
        ([FrameToWrite(0, "raster", np.zeros((0, 2), np.uint8))], "2-D"),
        ([FrameToWrite(0, "raster", np.zeros((2, 2), np.float32))], "float32"),
        ([FrameToWrite(0, "raster", np.zeros((2, 2), np.int16))], "int16"),
    ],
)
def test_invalid_frames_write_nothing(
    tmp_path: Path, frames: list[FrameToWrite], message: str
) -> None:
    store = RawStore(tmp_path)
    with pytest.raises(InputError, match=message):
        store.write(_uid(8), frames)
    assert list(store.scan()) == []


@pytest.mark.parametrize("uid", ["", "ABCDEF" * 6, "../" * 11, "a" * 31, "g" * 32])
def test_invalid_uids_are_refused(tmp_path: Path, uid: str) -> None:
    with pytest.raises(InputError, match="invalid archive uid"):
        RawStore(tmp_path).write(uid, _frames())


def test_unknown_compression_is_refused(tmp_path: Path) -> None:
    for spec in ("zstd", "lzf-3", "gzip-10", "shuffle+none"):
        with pytest.raises(InputError, match="unknown compression"):
            RawStore(tmp_path, compression=spec)
    assert parse_compression("gzip") == {"shuffle": False, "compression": "gzip",
                                         "compression_opts": 4}


def test_files_are_write_once(tmp_path: Path) -> None:
    store = RawStore(tmp_path)
    uid = _uid(9)
    first = store.write(uid, _frames())
    before = store.path_for(uid).read_bytes()
    with pytest.raises(ConflictError, match="write-once"):
        store.write(uid, _frames(np.uint8))
    assert store.path_for(uid).read_bytes() == before
    assert store.frames(uid) == first
    assert [e.kind for e in store.scan()] == ["final"]


def test_a_concurrent_writer_cannot_replace_a_published_file(tmp_path: Path) -> None:
    """The final name appears after our existence check (another process won the race)."""
    uid = _uid(10)
    rival = RawStore(tmp_path)

    def rival_publishes_first(step: str) -> None:
        if step == "fsynced":
            rival.write(uid, _frames(np.uint8))

    store = RawStore(tmp_path, crash_hook=rival_publishes_first)
    with pytest.raises(ConflictError):
        store.write(uid, _frames())
    np.testing.assert_array_equal(rival.read(uid, 0), _frames(np.uint8)[0].array)
    assert [e.kind for e in store.scan()] == ["final"]  # our temp file is gone


# --- durability steps ------------------------------------------------------------------------


def test_temp_file_is_never_visible_under_the_final_name(tmp_path: Path) -> None:
    uid = _uid(11)
    seen: list[tuple[str, bool, list[str]]] = []

    def hook(step: str) -> None:
        final = store.path_for(uid)
        seen.append((step, final.exists(), sorted(p.name for p in final.parent.iterdir())))

    store = RawStore(tmp_path, crash_hook=hook)
    store.write(uid, _frames())
    assert [s[0] for s in seen] == ["temp-written", "fsynced", "renamed"]
    for step, final_exists, names in seen[:2]:
        assert not final_exists, step
        assert len(names) == 1 and names[0].startswith(f"{uid}.h5.tmp-{os.getpid()}-")
    assert seen[2][1:] == (True, [f"{uid}.h5"])


@pytest.mark.parametrize("step", ["temp-written", "fsynced"])
def test_crash_before_rename_leaves_only_a_temp_file(tmp_path: Path, step: str) -> None:
    uid = _uid(12)

    def crash(name: str) -> None:
        if name == step:
            raise SimulatedCrash(name)

    store = RawStore(tmp_path, crash_hook=crash)
    with pytest.raises(SimulatedCrash):
        store.write(uid, _frames())
    assert not store.exists(uid)
    entries = list(store.scan())
    assert [(e.kind, e.uid) for e in entries] == [("temp", uid)]
    # The leftover is a complete HDF5 file, merely unpublished; check_file sees no final file.
    assert store.check_file(uid).status == "missing"


_KILLED_WRITER = """
import os, sys
from pathlib import Path
import numpy as np
from rasterserver.store import FrameToWrite, RawStore

def hook(step):
    if step == sys.argv[3]:
        os._exit(9)  # no cleanup of any kind, as with SIGKILL or a power cut

store = RawStore(Path(sys.argv[1]), crash_hook=hook)
store.write(sys.argv[2], [FrameToWrite(0, "raster", np.ones((64, 48), np.uint16))])
"""


@pytest.mark.parametrize(
    ("step", "expected"),
    [("temp-written", "temp"), ("fsynced", "temp"), ("renamed", "final")],
)
def test_killed_writer_leaves_an_explainable_state(
    tmp_path: Path, step: str, expected: str
) -> None:
    uid = _uid(25)
    done = subprocess.run(
        [sys.executable, "-c", _KILLED_WRITER, str(tmp_path), uid, step], check=False
    )
    assert done.returncode == 9
    store = RawStore(tmp_path)
    assert [(e.kind, e.uid) for e in store.scan()] == [(expected, uid)]
    assert store.check_file(uid).status == ("ok" if expected == "final" else "missing")


def test_crash_after_rename_leaves_a_complete_file(tmp_path: Path) -> None:
    uid = _uid(13)

    def crash(name: str) -> None:
        if name == "renamed":
            raise SimulatedCrash(name)

    store = RawStore(tmp_path, crash_hook=crash)
    with pytest.raises(SimulatedCrash):
        store.write(uid, _frames())
    assert store.check_file(uid).ok
    assert [e.kind for e in store.scan()] == ["final"]


def test_an_ordinary_failure_removes_the_temp_file(tmp_path: Path) -> None:
    def fail(name: str) -> None:
        if name == "fsynced":
            raise OSError(28, "No space left on device")

    store = RawStore(tmp_path, crash_hook=fail)
    with pytest.raises(OSError, match="No space"):
        store.write(_uid(14), _frames())
    assert list(store.scan()) == []


# --- reading errors --------------------------------------------------------------------------


def test_reading_what_does_not_exist(tmp_path: Path) -> None:
    store = RawStore(tmp_path)
    with pytest.raises(NotFoundError):
        store.read(_uid(15), 0)
    store.write(_uid(15), _frames())
    with pytest.raises(NotFoundError, match="no frame 5"):
        store.read(_uid(15), 5)
    assert not store.exists(_uid(16))


# --- verification ----------------------------------------------------------------------------


def _flip_byte_in_frame(path: Path, dataset: str) -> None:
    """Invert one byte inside a frame's pixel data, on disk, behind HDF5's back."""
    with h5py.File(path, "r") as h5:
        ds = h5[dataset]
        if ds.chunks is None:
            offset = ds.id.get_offset() + ds.id.get_storage_size() // 2
        else:
            info = ds.id.get_chunk_info(0)
            offset = info.byte_offset + info.size // 2
    with path.open("r+b") as fh:
        fh.seek(offset)
        (byte,) = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([byte ^ 0x01]))


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_one_flipped_byte_is_reported_corrupt(tmp_path: Path, compression: str) -> None:
    store = RawStore(tmp_path, compression=compression)
    uid = _uid(17)
    stored = store.write(uid, _frames())
    _flip_byte_in_frame(store.path_for(uid), "frames/1")

    report = store.check_file(uid, {s.index: s.sha256 for s in stored})
    assert report.status == "corrupt" and not report.ok
    bad = {p.index for p in report.problems}
    assert bad == {1}
    kinds = {p.kind for p in report.problems}
    # Deflate's checksum catches the flip while decoding; raw and LZF data decode to wrong pixels.
    assert kinds <= {"hash-mismatch", "catalog-mismatch", "unreadable-frame"} and kinds
    assert all(str(tmp_path) not in p.message for p in report.problems)
    assert report.hashes[0] == stored[0].sha256
    with pytest.raises(IntegrityError, match="frame 1"):
        store.read(uid, 1)
    np.testing.assert_array_equal(store.read(uid, 0), _frames()[0].array)
    # Without verification the damaged pixels are returned (or fail to decode).
    if "unreadable-frame" not in kinds:
        assert store.read(uid, 1, verify=False).shape == (604, 576)


@pytest.mark.parametrize("keep", [0.0, 0.01, 0.5, 0.99])
def test_truncated_file_is_reported_unreadable(tmp_path: Path, keep: float) -> None:
    store = RawStore(tmp_path)
    uid = _uid(18)
    store.write(uid, _frames())
    path = store.path_for(uid)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    report = store.check_file(uid)
    assert report.status in {"unreadable", "corrupt"} and not report.ok
    if keep < 0.5:
        assert report.status == "unreadable"
        assert report.problems[0].kind == "unreadable-file"
    with pytest.raises(IntegrityError):
        store.read_all(uid)


def test_not_an_hdf5_file_is_unreadable(tmp_path: Path) -> None:
    store = RawStore(tmp_path)
    uid = _uid(19)
    path = store.path_for(uid)
    path.parent.mkdir(parents=True)
    path.write_text("not hdf5")
    report = store.check_file(uid)
    assert report.status == "unreadable"
    assert "not a readable HDF5 file" in report.problems[0].message
    with h5py.File(path, "w") as h5:
        h5["something"] = 1
    assert store.check_file(uid).problems[0].kind == "bad-attributes"


def test_missing_file(tmp_path: Path) -> None:
    report = RawStore(tmp_path).check_file(_uid(20), {0: "0" * 64})
    assert report.status == "missing" and report.problems[0].kind == "missing-file"


def test_catalogue_disagreements(tmp_path: Path) -> None:
    store = RawStore(tmp_path)
    uid = _uid(21)
    stored = store.write(uid, _frames())
    expected = {0: stored[0].sha256, 1: "f" * 64, 2: "e" * 64}
    report = store.check_file(uid, expected)
    assert report.status == "corrupt"
    assert {(p.kind, p.index) for p in report.problems} == {
        ("catalog-mismatch", 1), ("missing-frame", 2)
    }
    report = store.check_file(uid, {0: stored[0].sha256})
    assert {(p.kind, p.index) for p in report.problems} == {("extra-frame", 1)}
    assert store.check_file(uid).ok  # without catalogue: the file's own hashes only


def test_tampered_attributes_are_reported(tmp_path: Path) -> None:
    store = RawStore(tmp_path)
    uid = _uid(22)
    store.write(uid, _frames())
    with h5py.File(store.path_for(uid), "r+") as h5:
        h5["frames/0"].attrs["sha256"] = "0" * 64
        h5.attrs["frame_count"] = 3
    kinds = {(p.kind, p.index) for p in store.check_file(uid).problems}
    assert kinds == {("hash-mismatch", 0), ("bad-attributes", None)}


def test_scan_lists_finals_temps_and_strays(tmp_path: Path) -> None:
    store = RawStore(tmp_path)
    good, partial = _uid(23), _uid(24)
    assert not good.startswith("ffff")
    store.write(good, _frames(np.uint8, (4, 4)))
    leftover = temp_path(store.path_for(partial))
    leftover.parent.mkdir(parents=True, exist_ok=True)
    leftover.write_bytes(b"\x89HDF partial")
    misplaced = tmp_path / "raw" / "ff" / "ff" / f"{good}.h5"
    misplaced.parent.mkdir(parents=True)
    misplaced.write_bytes(b"")
    (store.path_for(good).parent / "notes.txt").write_text("?")

    entries = list(store.scan())
    assert {(e.kind, e.uid, e.path.name) for e in entries} == {
        ("final", good, f"{good}.h5"),
        ("temp", partial, leftover.name),
        ("stray", None, f"{good}.h5"),
        ("stray", None, "notes.txt"),
    }
    assert list(RawStore(tmp_path / "empty").scan()) == []
