"""Frame decoding and validation: every accepted format round-trips, every bad input is refused
with a message that names the file and the problem."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from rasterserver.errors import InputError
from rasterserver.imageio import decode_frame_bytes, read_frame

RNG_SEED = 1234


def _frame(dtype: type = np.uint8, shape: tuple[int, int] = (604, 576)) -> np.ndarray:
    rng = np.random.default_rng(RNG_SEED)
    return rng.integers(0, np.iinfo(dtype).max, size=shape, dtype=dtype, endpoint=True)


def _write_image(path: Path, array: np.ndarray) -> Path:
    assert cv2.imwrite(str(path), array)
    return path


def _check_frame(out: np.ndarray, expected: np.ndarray) -> None:
    assert out.dtype == expected.dtype
    assert out.shape == expected.shape
    np.testing.assert_array_equal(out, expected)
    assert out.flags.c_contiguous
    assert not out.flags.writeable


# --- formats that must round-trip ------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".png", ".tif", ".tiff"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_and_tiff_round_trip(tmp_path: Path, suffix: str, dtype: type) -> None:
    frame = _frame(dtype)
    _check_frame(read_frame(_write_image(tmp_path / f"f{suffix}", frame)), frame)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, ">u2"])
def test_npy_round_trips_and_is_made_little_endian(tmp_path: Path, dtype: object) -> None:
    frame = _frame(np.uint16 if dtype != np.uint8 else np.uint8).astype(dtype)
    np.save(tmp_path / "f.npy", frame)
    out = read_frame(tmp_path / "f.npy")
    _check_frame(out, frame.astype(frame.dtype.newbyteorder("<")))
    assert out.dtype.byteorder in ("<", "=", "|")


def test_fortran_order_npy_is_returned_c_contiguous(tmp_path: Path) -> None:
    frame = np.asfortranarray(_frame(np.uint16, (50, 40)))
    np.save(tmp_path / "f.npy", frame)
    _check_frame(read_frame(tmp_path / "f.npy"), np.ascontiguousarray(frame))


@pytest.mark.parametrize("dtype", ["uint8", "uint16"])
def test_raw_round_trips(tmp_path: Path, dtype: str) -> None:
    frame = _frame(np.dtype(dtype).type, (604, 576))
    path = tmp_path / "f.raw"
    path.write_bytes(frame.astype(np.dtype(dtype).newbyteorder("<")).tobytes())
    _check_frame(read_frame(path, shape=(604, 576), dtype=dtype), frame)


def test_big_endian_raw_is_converted(tmp_path: Path) -> None:
    frame = _frame(np.uint16, (20, 30))
    path = tmp_path / "f.bin"
    path.write_bytes(frame.astype(">u2").tobytes())
    _check_frame(read_frame(path, shape=(20, 30), dtype=">u2"), frame)


def test_unknown_extension_with_shape_and_dtype_is_raw(tmp_path: Path) -> None:
    frame = _frame(np.uint8, (6, 5))
    path = tmp_path / "f.dat"
    path.write_bytes(frame.tobytes())
    _check_frame(read_frame(path, shape=(6, 5), dtype="uint8"), frame)


def test_decode_frame_bytes_matches_read_frame(tmp_path: Path) -> None:
    frame = _frame(np.uint16)
    path = _write_image(tmp_path / "f.png", frame)
    _check_frame(decode_frame_bytes(path.read_bytes(), name="upload.png"), frame)


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_colour_is_converted_only_on_request_keeping_depth(tmp_path: Path, suffix: str) -> None:
    grey = _frame(np.uint16, (40, 30))
    path = _write_image(tmp_path / f"c{suffix}", np.dstack([grey, grey, grey]))
    with pytest.raises(InputError, match=r"c\S*: colour image \(3 channels\).*--convert-color"):
        read_frame(path)
    _check_frame(read_frame(path, convert_color=True), grey)


def test_real_colour_converts_to_bgr_luma(tmp_path: Path) -> None:
    bgr = np.zeros((4, 4, 3), np.uint8)
    bgr[..., 2] = 200  # pure red in OpenCV's BGR order
    path = _write_image(tmp_path / "red.png", bgr)
    with pytest.raises(InputError, match="colour image"):
        read_frame(path)
    out = read_frame(path, convert_color=True)
    assert out.dtype == np.uint8 and out.shape == (4, 4)
    assert int(out[0, 0]) == round(0.299 * 200)


@pytest.mark.parametrize(
    ("shape", "dtype"),
    [((1, 1), np.uint8), ((1, 1), np.uint16), ((604, 576), np.uint8)],
)
def test_degenerate_frames(tmp_path: Path, shape: tuple[int, int], dtype: type) -> None:
    for value in (0, np.iinfo(dtype).max):
        frame = np.full(shape, value, dtype=dtype)
        for suffix in (".png", ".tif"):
            _check_frame(read_frame(_write_image(tmp_path / f"d{suffix}", frame)), frame)
        np.save(tmp_path / "d.npy", frame)
        _check_frame(read_frame(tmp_path / "d.npy"), frame)


def test_expected_shape_and_dtype_are_checked_for_images(tmp_path: Path) -> None:
    path = _write_image(tmp_path / "f.png", _frame(np.uint8, (10, 8)))
    assert read_frame(path, shape=(10, 8), dtype="uint8").shape == (10, 8)
    with pytest.raises(InputError, match=r"f.png: frame is 10x8 but 8x10 was expected"):
        read_frame(path, shape=(8, 10))
    with pytest.raises(InputError, match=r"f.png: frame is uint8 but uint16 was expected"):
        read_frame(path, dtype="uint16")


# --- inputs that must be refused -------------------------------------------------------------


def _refused(path: Path, pattern: str, **kwargs: object) -> InputError:
    with pytest.raises(InputError, match=pattern) as info:
        read_frame(path, **kwargs)  # type: ignore[arg-type]
    message = str(info.value)
    assert message.startswith(path.name + ":")
    # The patient folder must never reach a message or a log.
    assert str(path.parent) not in message
    return info.value


def test_missing_and_empty_files(tmp_path: Path) -> None:
    _refused(tmp_path / "nope.png", "no such file")
    (tmp_path / "empty.png").write_bytes(b"")
    _refused(tmp_path / "empty.png", "empty file")


def test_not_an_image(tmp_path: Path) -> None:
    (tmp_path / "notes.png").write_text("patient notes, not a picture\n")
    _refused(tmp_path / "notes.png", "not an image")


def test_jpeg_is_refused_as_lossy(tmp_path: Path) -> None:
    path = _write_image(tmp_path / "f.jpg", _frame(np.uint8, (16, 16)))
    _refused(path, "JPEG is lossy")


@pytest.mark.parametrize("suffix", [".png", ".tif"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("keep", [0.1, 0.5, 0.9, 0.999])
def test_truncated_png_and_tiff_are_refused(
    tmp_path: Path, suffix: str, dtype: type, keep: float
) -> None:
    good = _write_image(tmp_path / f"good{suffix}", _frame(dtype))
    data = good.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(data[: int(len(data) * keep)])
    _refused(cut, "truncated")


def _tiff_strip_after_directory(array: np.ndarray) -> bytes:
    """A minimal grey TIFF whose directory comes *before* the pixels (as many cameras write)."""
    rows, cols = array.shape
    pixels = array.astype("<u2").tobytes()
    entries = [
        (256, 3, 1, cols), (257, 3, 1, rows), (258, 3, 1, 16), (259, 3, 1, 1),
        (262, 3, 1, 1), (273, 4, 1, 0), (277, 3, 1, 1), (278, 3, 1, rows),
        (279, 4, 1, len(pixels)),
    ]
    data_offset = 8 + 2 + 12 * len(entries) + 4
    out = b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", len(entries))
    for tag, typ, count, value in entries:
        value = data_offset if tag == 273 else value
        packed = struct.pack("<HH", value, 0) if typ == 3 else struct.pack("<I", value)
        out += struct.pack("<HHI", tag, typ, count) + packed
    return out + struct.pack("<I", 0) + pixels


def test_tiff_truncated_in_its_pixels_is_refused(tmp_path: Path) -> None:
    # OpenCV's own TIFFs put the directory last, so cutting them loses the directory; here the
    # directory survives and only pixel data are missing.
    frame = _frame(np.uint16, (100, 80))
    data = _tiff_strip_after_directory(frame)
    whole = tmp_path / "whole.tif"
    whole.write_bytes(data)
    _check_frame(read_frame(whole), frame)
    for cut in (len(data) - 1, len(data) // 2):
        part = tmp_path / "part.tif"
        part.write_bytes(data[:cut])
        _refused(part, "truncated")


def test_png_without_end_chunk_is_refused(tmp_path: Path) -> None:
    data = _write_image(tmp_path / "g.png", _frame(np.uint8, (30, 20))).read_bytes()
    assert data.endswith(b"IEND\xaeB`\x82")
    (tmp_path / "noend.png").write_bytes(data[:-12])
    _refused(tmp_path / "noend.png", "truncated")


def test_corrupt_png_data_is_refused(tmp_path: Path) -> None:
    data = bytearray(_write_image(tmp_path / "g.png", _frame(np.uint8, (64, 64))).read_bytes())
    middle = len(data) // 2
    data[middle : middle + 16] = bytes(16)
    (tmp_path / "bad.png").write_bytes(bytes(data))
    _refused(tmp_path / "bad.png", "corrupt")


def test_truncated_npy_is_refused(tmp_path: Path) -> None:
    np.save(tmp_path / "f.npy", _frame(np.uint16, (30, 20)))
    data = (tmp_path / "f.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(data[:-7])
    _refused(tmp_path / "cut.npy", "truncated or corrupt NPY")
    (tmp_path / "head.npy").write_bytes(data[:20])
    _refused(tmp_path / "head.npy", "corrupt NPY header")


@pytest.mark.parametrize(
    ("shape", "label"), [((10,), "1-D"), ((3, 10, 8), "3-D"), ((2, 2, 2, 2), "4-D")]
)
def test_wrong_dimensions_are_refused(tmp_path: Path, shape: tuple[int, ...], label: str) -> None:
    np.save(tmp_path / "f.npy", np.zeros(shape, np.uint8))
    _refused(tmp_path / "f.npy", f"{label} array .* a frame must be a 2-D")


def test_multi_page_tiff_is_refused(tmp_path: Path) -> None:
    pages = [np.full((8, 6), i, np.uint8) for i in range(3)]
    path = tmp_path / "stack.tif"
    assert cv2.imwritemulti(str(path), pages)
    _refused(path, r"multi-page TIFF \(3 pages\)")


@pytest.mark.parametrize("dtype", ["float32", "float64", "int32", "int16", "bool", "complex64"])
def test_other_dtypes_are_refused(tmp_path: Path, dtype: str) -> None:
    np.save(tmp_path / "f.npy", np.zeros((4, 4), dtype=dtype))
    _refused(tmp_path / "f.npy", f"dtype {np.dtype(dtype).name} is not accepted")


def test_float_tiff_is_refused(tmp_path: Path) -> None:
    path = _write_image(tmp_path / "f.tif", np.zeros((4, 4), np.float32))
    _refused(path, "pixel type float32 is not accepted")


def test_object_npy_is_refused(tmp_path: Path) -> None:
    np.save(tmp_path / "f.npy", np.array([[None, 1]], dtype=object), allow_pickle=True)
    _refused(tmp_path / "f.npy", "Python objects")


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_alpha_is_refused_even_with_convert_color(tmp_path: Path, suffix: str) -> None:
    path = _write_image(tmp_path / f"a{suffix}", np.zeros((5, 5, 4), np.uint8))
    _refused(path, r"alpha channel \(4 channels\)", convert_color=True)


def test_zero_size_dimensions_are_refused(tmp_path: Path) -> None:
    np.save(tmp_path / "z.npy", np.zeros((0, 5), np.uint8))
    _refused(tmp_path / "z.npy", "zero-size dimension")
    with pytest.raises(InputError, match="must be positive"):
        decode_frame_bytes(b"", name="z.raw", shape=(0, 5), dtype="uint8")


def test_raw_size_must_match_exactly(tmp_path: Path) -> None:
    path = tmp_path / "f.raw"
    path.write_bytes(bytes(604 * 576 * 2 - 1))
    _refused(path, r"raw file is 695807 bytes but 604x576 uint16 needs exactly 695808",
             shape=(604, 576), dtype="uint16")
    path.write_bytes(bytes(604 * 576 * 2 + 2))
    _refused(path, "needs exactly", shape=(604, 576), dtype="uint16")


def test_raw_needs_shape_and_dtype(tmp_path: Path) -> None:
    path = tmp_path / "f.raw"
    path.write_bytes(bytes(12))
    _refused(path, "needs a shape and a dtype")
    _refused(path, "dtype 'float32' is not accepted", shape=(3, 4), dtype="float32")


def test_frames_over_the_limit_are_refused(tmp_path: Path) -> None:
    frame = _frame(np.uint16, (100, 100))  # 20,000 bytes decoded
    png = _write_image(tmp_path / "big.png", frame)
    _refused(png, "larger than the frame limit of 19999 bytes", max_bytes=19_999)
    assert read_frame(png, max_bytes=20_000).shape == (100, 100)
    np.save(tmp_path / "big.npy", frame)
    _refused(tmp_path / "big.npy", "larger than the frame limit", max_bytes=19_999)
    raw = tmp_path / "big.raw"
    raw.write_bytes(frame.tobytes())
    _refused(raw, "larger than the frame limit", shape=(100, 100), dtype="uint16",
             max_bytes=19_999)


def test_huge_file_is_refused_before_reading(tmp_path: Path) -> None:
    path = tmp_path / "huge.raw"
    with path.open("wb") as fh:  # sparse: no disk space used
        fh.truncate(64 * 1024 * 1024)
    _refused(path, "file of 67108864 bytes is larger", shape=(8192, 8192), dtype="uint8",
             max_bytes=1024 * 1024)


def _png_bomb(rows: int, cols: int) -> bytes:
    """A tiny PNG whose header declares a huge 16-bit image (a decompression bomb)."""
    import zlib

    def chunk(kind: bytes, payload: bytes) -> bytes:
        crc = zlib.crc32(kind + payload) & 0xFFFFFFFF
        return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", cols, rows, 16, 0, 0, 0, 0)
    # Rows of zeros compress to almost nothing; a few are enough to make a valid stream start.
    pixels = zlib.compress(bytes((1 + 2 * cols) * 16), 9)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", pixels)
            + chunk(b"IEND", b""))


def test_decompression_bomb_is_refused_from_its_header() -> None:
    data = _png_bomb(60_000, 60_000)
    assert len(data) < 4096  # a few kB declaring 7.2 GB of pixels
    with pytest.raises(InputError, match=r"bomb.png: image of 60000x60000 pixels"):
        decode_frame_bytes(data, name="bomb.png")


def test_tiff_declaring_a_huge_image_is_refused() -> None:
    data = bytearray(_tiff_strip_after_directory(np.zeros((4, 4), np.uint16)))
    # Rewrite width and length (first two entries) to 50,000.
    for entry in (0, 1):
        struct.pack_into("<H", data, 8 + 2 + 12 * entry + 8, 50_000)
    with pytest.raises(InputError, match="image of 50000x50000 pixels"):
        decode_frame_bytes(bytes(data), name="bomb.tif")


def test_messages_use_the_base_name_only() -> None:
    with pytest.raises(InputError) as info:
        decode_frame_bytes(b"garbage", name="/data/patients/Doe_John/scan.png")
    assert str(info.value).startswith("scan.png: not an image")
    assert "Doe_John" not in str(info.value)
