"""Records: validation, the generic array round trip (dict, HDF5, npz) and the content hash."""

from __future__ import annotations

import pickle
import re
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import h5py
import numpy as np
import pytest

from rasterserver.errors import InputError, NotFoundError
from rasterserver.records import Image, Record, record_type, record_types


def _image(seed: int = 7, dtype: type = np.uint16, shape: tuple[int, int] = (12, 16)) -> Image:
    rng = np.random.default_rng(seed)
    return Image(rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype), role="raster")


class Sample(Record):
    """A record with every supported field type, as a pipeline record would look."""

    kind: ClassVar[str] = "test-records.sample"
    values: np.ndarray
    count: int
    scale: float
    valid: bool
    label: str
    weights: np.ndarray | None = None
    note: str | None = None


def _sample(**changes: object) -> Sample:
    fields: dict[str, object] = {
        "values": np.linspace(0.0, 1.0, 5),
        "count": 3,
        "scale": 0.25,
        "valid": True,
        "label": "Wirbelsäule",  # non-ASCII on purpose: strings are stored as UTF-8 bytes
        "weights": np.ones(5, dtype=np.float32),
    }
    fields.update(changes)
    return Sample(**fields)  # type: ignore[arg-type]


# --- Image ---------------------------------------------------------------------------------


def test_image_accepts_uint8_and_uint16_and_defaults_role() -> None:
    assert Image(np.zeros((2, 3), dtype=np.uint8)).role == "raster"
    assert Image(np.zeros((2, 3), dtype=np.uint16), role="texture").role == "texture"


@pytest.mark.parametrize(
    ("pixels", "message"),
    [
        (np.zeros((2, 3, 3), dtype=np.uint8), "2-D"),
        (np.zeros(4, dtype=np.uint8), "2-D"),
        (np.zeros((2, 3), dtype=np.float32), "uint8 or uint16"),
        (np.zeros((2, 3), dtype=np.int16), "uint8 or uint16"),
        (np.zeros((2, 3), dtype=np.uint32), "uint8 or uint16"),
        (np.zeros((0, 3), dtype=np.uint8), "empty"),
    ],
)
def test_image_refuses_unusable_pixels(pixels: np.ndarray, message: str) -> None:
    with pytest.raises(InputError, match=message):
        Image(pixels)


def test_image_refuses_empty_role_and_non_arrays() -> None:
    with pytest.raises(InputError, match="role"):
        Image(np.zeros((2, 2), dtype=np.uint8), role="")
    with pytest.raises(TypeError, match=r"Image\.pixels must be a numpy array"):
        Image([[1, 2], [3, 4]])  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"Image\.role must be a str"):
        Image(np.zeros((2, 2), dtype=np.uint8), role=3)  # type: ignore[arg-type]


def test_record_arrays_are_read_only_views_and_the_callers_array_stays_writable() -> None:
    pixels = np.zeros((3, 4), dtype=np.uint8)
    image = Image(pixels)
    with pytest.raises(ValueError, match="read-only"):
        image.pixels[0, 0] = 1
    with pytest.raises(AttributeError):
        image.role = "dark"  # type: ignore[misc]
    pixels[0, 0] = 5  # no copy was made: the record sees the caller's data
    assert image.pixels[0, 0] == 5


def test_repr_summarises_arrays() -> None:
    assert repr(_image()) == "Image(pixels=<uint16 12x16>, role='raster')"


# --- round trips ---------------------------------------------------------------------------


def test_image_round_trips_through_arrays() -> None:
    image = _image()
    arrays = image.to_arrays()
    assert set(arrays) == {"pixels", "role"}
    assert arrays["role"].shape == ()
    assert arrays["role"].dtype.kind == "S"  # bytes, which h5py stores as a plain string
    back = Image.from_arrays(arrays)
    assert back == image
    assert back.content_hash() == image.content_hash()
    assert back.role == "raster"


def test_every_field_type_round_trips() -> None:
    sample = _sample()
    arrays = sample.to_arrays()
    assert arrays["count"].dtype == np.int64 and arrays["count"].shape == ()
    assert arrays["scale"].dtype == np.float64
    assert arrays["valid"].dtype == np.bool_
    assert "note" not in arrays  # None is left out, not stored as a sentinel
    back = Sample.from_arrays(arrays)
    assert back == sample
    assert (back.count, back.scale, back.valid, back.label, back.note) == (
        3,
        0.25,
        True,
        "Wirbelsäule",
        None,
    )
    assert type(back.count) is int and type(back.scale) is float and type(back.valid) is bool


def test_optional_and_defaulted_fields_may_be_missing() -> None:
    arrays = _sample(weights=None).to_arrays()
    assert "weights" not in arrays
    assert Sample.from_arrays(arrays).weights is None
    pixels = _image().pixels
    assert Image.from_arrays({"pixels": pixels}).role == "raster"


def test_round_trip_through_hdf5(tmp_path: Path) -> None:
    image, sample = _image(), _sample()
    with h5py.File(tmp_path / "records.h5", "w") as f:
        for name, record in (("image", image), ("sample", sample)):
            group = f.create_group(name)
            group.attrs["kind"] = record.kind
            for key, array in record.to_arrays().items():
                group.create_dataset(key, data=array)
    with h5py.File(tmp_path / "records.h5", "r") as f:
        # An h5py group is a Mapping of datasets: from_arrays reads it directly.
        back_image = record_type(f["image"].attrs["kind"]).from_arrays(f["image"])
        back_sample = Sample.from_arrays(f["sample"])
    assert back_image == image
    assert back_image.content_hash() == image.content_hash()
    assert back_sample == sample
    assert back_sample.label == "Wirbelsäule"


def test_round_trip_through_npz(tmp_path: Path) -> None:
    sample = _sample()
    np.savez(tmp_path / "sample.npz", **sample.to_arrays())
    with np.load(tmp_path / "sample.npz") as arrays:
        assert Sample.from_arrays(arrays) == sample


def test_records_pickle_for_dask_workers() -> None:
    image = _image()
    assert pickle.loads(pickle.dumps(image)) == image


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        ({"role": np.array(b"raster")}, "missing field"),
        ({"pixels": np.zeros((2, 2), np.uint8), "colour": np.array(1)}, "no field"),
        ({"pixels": np.zeros((2, 2), np.uint8), "role": np.array([b"a", b"b"])}, "0-d"),
        ({"pixels": np.zeros((2, 2), np.uint8), "role": np.array(1.5)}, "string"),
    ],
)
def test_from_arrays_refuses_mismatched_arrays(arrays: dict[str, np.ndarray], message: str) -> None:
    with pytest.raises(InputError, match=message):
        Image.from_arrays(arrays)


def test_from_arrays_refuses_wrong_scalar_dtype() -> None:
    arrays = _sample().to_arrays()
    arrays["count"] = np.array(2.5)
    with pytest.raises(InputError, match=r"Sample\.count must hold an int"):
        Sample.from_arrays(arrays)


# --- content hash --------------------------------------------------------------------------


def test_content_hash_is_pinned() -> None:
    # Stored provenance refers to these digests: changing the scheme invalidates every cache.
    image = Image(np.arange(6, dtype=np.uint8).reshape(2, 3))
    assert image.content_hash() == (
        "ab872d7f086653851a13cb529de8ef26b7c3c2970241b14957d25efe98098366"
    )


def test_content_hash_sees_every_difference() -> None:
    image = _image(dtype=np.uint8)
    pixels = image.pixels.copy()
    pixels[3, 4] ^= 1
    variants = [
        image,
        Image(pixels),
        Image(image.pixels, role="dark"),
        Image(image.pixels.astype(np.uint16)),  # same values, other dtype
        Image(image.pixels.reshape(16, 12)),  # same bytes, other shape
    ]
    hashes = {variant.content_hash() for variant in variants}
    assert len(hashes) == len(variants)


def test_content_hash_ignores_memory_layout_and_byte_order() -> None:
    image = _image()
    fortran = Image(np.asfortranarray(image.pixels))
    big_endian = Image(image.pixels.astype(">u2"))
    assert big_endian == image == fortran
    assert big_endian.content_hash() == image.content_hash() == fortran.content_hash()
    strided = np.zeros((12, 32), dtype=np.uint16)
    strided[:, ::2] = image.pixels
    assert Image(strided[:, ::2]).content_hash() == image.content_hash()


def test_content_hash_includes_the_kind() -> None:
    class Other(Record):
        kind: ClassVar[str] = "test-records.other-image"
        pixels: np.ndarray
        role: str = "raster"

    image = _image()
    other = Other(image.pixels)
    assert other.to_arrays().keys() == image.to_arrays().keys()
    assert other.content_hash() != image.content_hash()
    assert other != image


def test_records_compare_by_content_and_are_unhashable() -> None:
    assert _image(seed=1) == _image(seed=1)
    assert _image(seed=1) != _image(seed=2)
    assert _sample() != _sample(note="x")
    with pytest.raises(TypeError):
        hash(_image())


# --- declaring records ---------------------------------------------------------------------


def test_record_kinds_are_registered() -> None:
    assert record_type("image") is Image
    assert record_types()["test-records.sample"] is Sample
    with pytest.raises(NotFoundError, match="no record kind 'nope'"):
        record_type("nope")


def test_a_record_must_declare_a_unique_kind() -> None:
    with pytest.raises(TypeError, match="must declare kind"):

        class NoKind(Record):
            values: np.ndarray

    with pytest.raises(
        TypeError, match=r"'image' .* is already used by rasterserver\.records\.Image"
    ):

        class Clash(Record):
            kind: ClassVar[str] = "image"
            values: np.ndarray


def test_unsupported_field_types_are_refused_at_class_definition() -> None:
    with pytest.raises(TypeError, match=r"Bad\.items: record fields must be numpy arrays"):

        class Bad(Record):
            kind: ClassVar[str] = "test-records.bad"
            items: list[int]

    with pytest.raises(TypeError, match=re.escape("one type or that type | None")):

        class Mixed(Record):
            kind: ClassVar[str] = "test-records.mixed"
            value: int | str


def test_scalar_fields_are_type_checked() -> None:
    with pytest.raises(TypeError, match=r"Sample\.count must be an int, not bool"):
        _sample(count=True)
    with pytest.raises(TypeError, match=r"Sample\.scale must be a float"):
        _sample(scale="0.5")
    with pytest.raises(TypeError, match=r"Sample\.label must not be None"):
        _sample(label=None)
    # numpy scalars are accepted and stored as Python scalars
    sample = _sample(count=np.int32(4), scale=np.float32(0.5), valid=np.bool_(False))
    assert (type(sample.count), type(sample.scale), type(sample.valid)) == (int, float, bool)


def test_object_arrays_are_refused() -> None:
    with pytest.raises(TypeError, match="object arrays"):
        _sample(values=np.array([1, "a"], dtype=object))


def test_decorating_a_record_with_dataclass_is_refused() -> None:
    # Record already applies dataclass(frozen=True, eq=False, repr=False); a second,
    # default-eq decorator would compare arrays with == and fail far from the cause.
    with pytest.raises(TypeError, match="Cannot overwrite attribute __setattr__"):

        @dataclass(frozen=True)
        class Frozen(Record):
            kind: ClassVar[str] = "test-records.decorated-frozen"
            values: np.ndarray

    @dataclass
    class Decorated(Record):
        kind: ClassVar[str] = "test-records.decorated"
        values: np.ndarray

    with pytest.raises(TypeError, match="do not decorate"):
        Decorated(np.zeros(2))


def test_validate_hook_runs_after_type_checks() -> None:
    class Pair(Record):
        kind: ClassVar[str] = "test-records.pair"
        left: np.ndarray
        right: np.ndarray

        def validate(self) -> None:
            if self.left.shape != self.right.shape:
                raise InputError("left and right differ in shape")

    Pair(np.zeros(3), np.ones(3))
    with pytest.raises(InputError, match="differ in shape"):
        Pair(np.zeros(3), np.ones(4))
    with pytest.raises(InputError, match="differ in shape"):
        Pair.from_arrays({"left": np.zeros(3), "right": np.ones(4)})
