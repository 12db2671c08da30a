"""Typed records: the immutable containers of numpy arrays that pass between pipeline stages.

A record is a frozen dataclass whose fields are numpy arrays or scalars (``bool``, ``int``,
``float``, ``str``, each optionally ``| None``). Subclassing :class:`Record` is all it takes to
get a dataclass with validation, a generic round trip through a flat ``{name: array}``
mapping (which is what an HDF5 group or an ``.npz`` file holds) and a content hash::

    class Peaks(Record):
        \"\"\"Sub-pixel peak rows per image column.\"\"\"

        kind: ClassVar[str] = "peaks"
        rows: np.ndarray
        strength: np.ndarray
        image_shape: np.ndarray

        def validate(self) -> None:
            if self.rows.shape != self.strength.shape:
                raise InputError("rows and strength differ in shape")

Do not decorate subclasses with ``@dataclass``: :class:`Record` applies
``dataclass(frozen=True, eq=False, repr=False)`` itself, because the dataclass defaults for
``__eq__`` (truth value of an array) and ``__repr__`` (megabytes of pixels) are wrong for
arrays. Every concrete subclass declares a unique ``kind``; :func:`record_type` finds the
class again from that string, e.g. when the pipeline reads a stored result.
"""

from __future__ import annotations

import dataclasses
import hashlib
import reprlib
import types
import typing
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar, Literal, Self, cast, dataclass_transform

import numpy as np

from rasterserver.errors import InputError
from rasterserver.hashing import canonical_array

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

__all__ = ["Image", "Record", "record_type", "record_types"]

_FieldKind = Literal["array", "bool", "int", "float", "str"]

# Scalars are stored as 0-d arrays of these dtypes; strings as 0-d UTF-8 ``bytes`` arrays
# (numpy "S"), because h5py cannot store numpy's fixed-width unicode ("U") dtype.
_SCALAR_DTYPES: dict[str, type[np.generic]] = {
    "bool": np.bool_,
    "int": np.int64,
    "float": np.float64,
}

_ARTICLE = {"bool": "a", "int": "an", "float": "a"}

_RECORD_TYPES: dict[str, type[Record]] = {}


@dataclasses.dataclass(frozen=True)
class _FieldSpec:
    name: str
    kind: _FieldKind
    optional: bool
    has_default: bool


def _classify(owner: type, name: str, hint: Any) -> tuple[_FieldKind, bool]:
    """Map a field annotation to its storage kind and whether it may be None."""
    optional = False
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        rest = [a for a in args if a is not type(None)]
        if len(rest) != 1 or len(args) != 2:
            raise TypeError(
                f"{owner.__name__}.{name}: a record field is one type or that type | None, "
                f"not {hint!r}"
            )
        hint, optional = rest[0], True
    if hint is np.ndarray or typing.get_origin(hint) is np.ndarray:
        return "array", optional
    scalars: tuple[tuple[_FieldKind, type], ...] = (
        ("bool", bool),
        ("int", int),
        ("float", float),
        ("str", str),
    )
    for kind, py_type in scalars:
        if hint is py_type:
            return kind, optional
    raise TypeError(
        f"{owner.__name__}.{name}: record fields must be numpy arrays, bool, int, float or str "
        f"(optionally | None), not {hint!r}"
    )


@dataclass_transform(
    frozen_default=True, eq_default=False, field_specifiers=(dataclasses.field, dataclasses.Field)
)
class Record:
    """Base of every record: a frozen dataclass of numpy arrays and scalars.

    Subclasses declare ``kind`` (a unique, stable string that names the record type in the
    archive) and their fields as class annotations; they may override :meth:`validate`.
    Array fields are stored as read-only views, so a stage cannot modify its input in place
    and corrupt a cached result.

    Attributes
    ----------
    kind : str
        Name of the record type, unique among all records (``"image"``, ``"peaks"``, ...).
    """

    kind: ClassVar[str]
    _fields: ClassVar[tuple[_FieldSpec, ...]] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        dataclasses.dataclass(frozen=True, eq=False, repr=False)(cls)
        if "kind" not in cls.__dict__ or not isinstance(cls.__dict__["kind"], str):
            raise TypeError(f"record class {cls.__qualname__} must declare kind: ClassVar[str]")
        if not cls.kind:
            raise TypeError(f"record class {cls.__qualname__} has an empty kind")
        hints = typing.get_type_hints(cls)
        specs = []
        # The dataclass() call above made cls a dataclass; its static type cannot say so.
        for f in dataclasses.fields(cast("type[DataclassInstance]", cls)):
            kind, optional = _classify(cls, f.name, hints[f.name])
            has_default = (
                f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
            )
            specs.append(_FieldSpec(f.name, kind, optional, has_default))
        cls._fields = tuple(specs)
        previous = _RECORD_TYPES.get(cls.kind)
        # Re-importing the same module (tests, reloads) redefines the class; a different class
        # claiming the kind would make stored results ambiguous.
        if previous is not None and (previous.__module__, previous.__qualname__) != (
            cls.__module__,
            cls.__qualname__,
        ):
            raise TypeError(
                f"record kind {cls.kind!r} of {cls.__module__}.{cls.__qualname__} is already "
                f"used by {previous.__module__}.{previous.__qualname__}"
            )
        _RECORD_TYPES[cls.kind] = cls

    def __post_init__(self) -> None:
        if type(self).__dataclass_params__.eq:  # type: ignore[attr-defined]
            raise TypeError(
                f"{type(self).__qualname__}: do not decorate Record subclasses with @dataclass"
            )
        for spec in self._fields:
            value = getattr(self, spec.name)
            object.__setattr__(self, spec.name, self._check_field(spec, value))
        self.validate()

    def _check_field(self, spec: _FieldSpec, value: Any) -> Any:
        where = f"{type(self).__name__}.{spec.name}"
        if value is None:
            if spec.optional:
                return None
            raise TypeError(f"{where} must not be None")
        if spec.kind == "array":
            if not isinstance(value, np.ndarray):
                raise TypeError(f"{where} must be a numpy array, not {type(value).__name__}")
            if value.dtype.hasobject:
                raise TypeError(f"{where}: object arrays cannot be hashed or stored")
            view = value.view()
            view.flags.writeable = False
            return view
        if spec.kind == "str":
            if not isinstance(value, str):
                raise TypeError(f"{where} must be a str, not {type(value).__name__}")
            return value
        if spec.kind == "bool":
            if not isinstance(value, bool | np.bool_):
                raise TypeError(f"{where} must be a bool, not {type(value).__name__}")
            return bool(value)
        # bool is an int subclass: refuse it where a number is meant, it is always a mix-up.
        if isinstance(value, bool | np.bool_):
            raise TypeError(f"{where} must be {_ARTICLE[spec.kind]} {spec.kind}, not bool")
        if spec.kind == "int":
            if not isinstance(value, int | np.integer):
                raise TypeError(f"{where} must be an int, not {type(value).__name__}")
            return int(value)
        if not isinstance(value, int | float | np.integer | np.floating):
            raise TypeError(f"{where} must be a float, not {type(value).__name__}")
        return float(value)

    def validate(self) -> None:
        """Check the values beyond their types; raise :class:`InputError` when unusable.

        Called after construction. The base implementation accepts everything; subclasses
        override it to check shapes, dtypes and value ranges.
        """

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Return the fields as a flat mapping of numpy arrays, ready for HDF5 or ``.npz``.

        Returns
        -------
        dict of str to numpy.ndarray
            Array fields as they are (read-only), scalars as 0-d arrays (``bool``, ``int64``,
            ``float64``), strings as 0-d UTF-8 ``bytes`` arrays. Fields that are None are left
            out.
        """
        arrays: dict[str, np.ndarray] = {}
        for spec in self._fields:
            value = getattr(self, spec.name)
            if value is None:
                continue
            if spec.kind == "array":
                arrays[spec.name] = value
            elif spec.kind == "str":
                arrays[spec.name] = np.array(value.encode("utf-8"))
            else:
                arrays[spec.name] = np.array(value, dtype=_SCALAR_DTYPES[spec.kind])
        return arrays

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, Any]) -> Self:
        """Build a record from the mapping :meth:`to_arrays` produced.

        Parameters
        ----------
        arrays : Mapping of str to array-like
            One entry per field; an h5py group works as well as a dict. Optional fields and
            fields with defaults may be missing.

        Returns
        -------
        Record
            A new record of this class.

        Raises
        ------
        InputError
            When a field is missing, an entry names no field, or a scalar is not 0-d.
        """
        names = {spec.name for spec in cls._fields}
        unknown = sorted(set(arrays) - names)
        if unknown:
            raise InputError(
                f"{cls.__name__} has no field(s) {', '.join(unknown)} "
                f"(fields: {', '.join(sorted(names))})"
            )
        values: dict[str, Any] = {}
        missing = []
        for spec in cls._fields:
            if spec.name not in arrays:
                if spec.has_default:
                    continue
                if spec.optional:
                    values[spec.name] = None
                else:
                    missing.append(spec.name)
                continue
            values[spec.name] = _from_array(cls, spec, np.asarray(arrays[spec.name]))
        if missing:
            raise InputError(f"{cls.__name__} is missing field(s) {', '.join(missing)}")
        return cls(**values)

    def content_hash(self) -> str:
        """Return a sha256 hex digest of the record's kind and contents.

        The digest covers the kind and, for each field in name order, its name, dtype, shape
        and bytes (C order, little-endian), so it is the same after a round trip through
        :meth:`to_arrays`/:meth:`from_arrays` or HDF5, and on any machine. It serves as the
        input checksum in provenance.

        Returns
        -------
        str
            64 lowercase hex digits.
        """
        digest = hashlib.sha256(f"rasterserver.record\0{self.kind}\0".encode())
        arrays = self.to_arrays()
        for name in sorted(arrays):
            array = canonical_array(arrays[name])
            digest.update(f"{name}\0{array.dtype.str}\0{array.shape}\0".encode())
            # the bytes tobytes() gives, read in place: a copy of every megabyte costs as
            # much as a fifth of hashing it
            flat = array.reshape(-1)
            digest.update(array.tobytes() if array.dtype.hasobject else flat.view(np.uint8).data)
        return digest.hexdigest()

    def __eq__(self, other: object) -> bool:
        # Exact equality of dtypes, shapes and bytes, as content_hash sees them: what "same
        # data" means for caching (so NaN equals the same NaN, and 0.0 differs from -0.0).
        if type(other) is not type(self):
            return NotImplemented
        assert isinstance(other, Record)
        mine, theirs = self.to_arrays(), other.to_arrays()
        if mine.keys() != theirs.keys():
            return False
        for key, a in mine.items():
            a, b = canonical_array(a), canonical_array(theirs[key])
            if a.dtype != b.dtype or a.shape != b.shape or a.tobytes() != b.tobytes():
                return False
        return True

    __hash__ = None  # type: ignore[assignment]  # arrays are mutable through their base

    def __repr__(self) -> str:
        parts = []
        for spec in self._fields:
            value = getattr(self, spec.name)
            if isinstance(value, np.ndarray):
                shape = "x".join(str(n) for n in value.shape) or "scalar"
                parts.append(f"{spec.name}=<{value.dtype} {shape}>")
            else:
                parts.append(f"{spec.name}={reprlib.repr(value)}")
        return f"{type(self).__name__}({', '.join(parts)})"


def _from_array(cls: type, spec: _FieldSpec, array: np.ndarray) -> Any:
    if spec.kind == "array":
        return array
    where = f"{cls.__name__}.{spec.name}"
    if array.ndim != 0:
        raise InputError(f"{where} must be a 0-d array (a scalar), got shape {array.shape}")
    item = array.item()
    if spec.kind == "str":
        if isinstance(item, bytes):
            return item.decode("utf-8")
        if isinstance(item, str):
            return item
        raise InputError(f"{where} must hold a string, got {array.dtype}")
    expected = {"bool": "b", "int": "iu", "float": "iuf"}[spec.kind]
    if array.dtype.kind not in expected:
        raise InputError(f"{where} must hold {_ARTICLE[spec.kind]} {spec.kind}, got {array.dtype}")
    return {"bool": bool, "int": int, "float": float}[spec.kind](item)


def record_type(kind: str) -> type[Record]:
    """Return the record class declared with ``kind``.

    Parameters
    ----------
    kind : str
        The record kind, e.g. ``"image"``.

    Returns
    -------
    type of Record
        The class; only classes whose module has been imported are known.

    Raises
    ------
    NotFoundError
        When no imported record class has that kind.
    """
    from rasterserver.errors import NotFoundError

    try:
        return _RECORD_TYPES[kind]
    except KeyError:
        known = ", ".join(sorted(_RECORD_TYPES)) or "none"
        raise NotFoundError(f"no record kind {kind!r} (known: {known})") from None


def record_types() -> dict[str, type[Record]]:
    """Return every known record class by kind (a copy)."""
    return dict(_RECORD_TYPES)


class Image(Record):
    """One camera frame: a 2-D grey-value image.

    Attributes
    ----------
    pixels : numpy.ndarray
        2-D ``uint8`` or ``uint16`` array, rows first (height x width).
    role : str
        What the frame shows, e.g. ``"raster"`` (the projected line raster, the default),
        ``"texture"`` or ``"dark"``.
    """

    kind: ClassVar[str] = "image"
    pixels: np.ndarray
    role: str = "raster"

    def validate(self) -> None:
        """Refuse anything but a non-empty 2-D uint8/uint16 image with a role."""
        pixels = self.pixels
        if pixels.ndim != 2:
            raise InputError(f"an image must be 2-D, got {pixels.ndim}-D {pixels.shape}")
        # By kind and size, so big-endian uint16 (as some cameras write it) is accepted too.
        if pixels.dtype.kind != "u" or pixels.dtype.itemsize not in (1, 2):
            raise InputError(f"image pixels must be uint8 or uint16, got {pixels.dtype}")
        if pixels.size == 0:
            raise InputError(f"an image must not be empty, got shape {pixels.shape}")
        if not self.role:
            raise InputError("an image needs a role (e.g. 'raster')")
