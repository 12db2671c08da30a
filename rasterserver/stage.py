"""The stage plugin protocol: one processing step as a pure function of (record, params).

A stage never touches SQL, HDF5 or the network. The pipeline does I/O, caching and
provenance around it, so the same stage runs in a test on a numpy array, in a Dask worker or
behind an HTTP call. Every stage, built-in or third-party, is a :class:`Stage` subclass found
through the ``rasterserver.stages`` entry-point group (see :mod:`rasterserver.registry`)::

    class FirstMomentPeaks(Stage[Image, Peaks]):
        \"\"\"Peaks as the intensity-weighted centre of each bright run in a column.\"\"\"

        name = "peaks.first-moment"
        stage = "peaks"
        version = "1"
        input_type = Image
        output_type = Peaks

        class Params(StageParams):
            threshold: int = Field(20, ge=0, description="Least grey value of a peak.")

        def run(self, data: Image, params: Params, context: StageContext) -> Peaks:
            ...

Call a stage through :func:`run_stage`, which checks the input type, validates the
parameters and checks the output type.
"""

from __future__ import annotations

import inspect
import re
import reprlib
import weakref
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Generic, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from rasterserver.errors import InputError
from rasterserver.hashing import canonical_json_sha256
from rasterserver.records import Record

__all__ = [
    "BUILTIN_STAGE_KINDS",
    "Stage",
    "StageContext",
    "StageParams",
    "coerce_params",
    "params_hash",
    "run_stage",
    "stage_problems",
]

BUILTIN_STAGE_KINDS: tuple[str, ...] = (
    "peaks",
    "lines",
    "order",
    "numbers",
    "points",
    "surface",
    "mesh",
)
"""The stage kinds of the built-in reconstruction chain, in processing order.

The set of kinds is open: a plugin may implement any other kind; these only fix the order in
listings.
"""

InT = TypeVar("InT", bound=Record)
OutT = TypeVar("OutT", bound=Record)

_NAME_RE = re.compile(r"^[a-z0-9][a-z0-9_.-]*$")
_KIND_RE = re.compile(r"^[a-z][a-z0-9_-]*$")


class StageParams(BaseModel):
    """Base of a stage's parameters: frozen, no unknown keys, every field with a default.

    Frozen makes parameters hashable and safe to share between runs; ``extra="forbid"`` turns
    a misspelt parameter into an error instead of a silently ignored default.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    #: Options added to a released stage after its results were stored, left out of the
    #: digest (:func:`params_hash`) while at their default. An option added switched off
    #: leaves the stage's computation unchanged, so it must leave the digest that stored
    #: results are keyed by unchanged too; otherwise every stored result would count as
    #: another computation and be reprocessed to the same bytes.
    digest_omits_defaults: ClassVar[frozenset[str]] = frozenset()


class _FrozenMapping(Mapping[str, Any]):
    """A read-only mapping that, unlike ``MappingProxyType``, pickles (for Dask workers)."""

    __slots__ = ("_data",)

    def __init__(self, data: Mapping[str, Any]) -> None:
        self._data = dict(data)

    def __getitem__(self, key: str) -> Any:
        return self._data[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self._data!r})"

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self._data,))


@dataclass(frozen=True, eq=False)
class StageContext:
    """Station data a stage may need besides its input record; pure data, no I/O handles.

    The context is not part of :func:`params_hash`: the pipeline records which calibration
    and raster definition it passed in the provenance itself.

    Attributes
    ----------
    calibration : object or None
        The camera/projector calibration (needed for reconstruction).
    raster : object or None
        The raster definition, i.e. the light/heavy line code (needed for numbering).
    extras : Mapping of str to Any
        Anything else, read-only; keys are agreed between the pipeline and the plugins.
    """

    calibration: object | None = None
    raster: object | None = None
    extras: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "extras", _FrozenMapping(self.extras))

    def has(self, requirement: str) -> bool:
        """Tell whether ``requirement`` (``"calibration"``, ``"raster"`` or an extras key) is set.

        Parameters
        ----------
        requirement : str
            A name from a stage's ``requires``.

        Returns
        -------
        bool
            True when the attribute is not None or the extras hold the key.
        """
        if requirement in ("calibration", "raster"):
            return getattr(self, requirement) is not None
        return requirement in self.extras


class Stage(ABC, Generic[InT, OutT]):
    """Base of every stage plugin: a pure function of (input record, params, context).

    Subclasses set the class attributes below and implement :meth:`run`; the entry point in
    the ``rasterserver.stages`` group names the class (or an instance) and its name must equal
    :attr:`name`. Parametrise the base with the record types (``Stage[Image, Peaks]``) for
    type checkers; :attr:`input_type` and :attr:`output_type` are what is checked at run time.

    Attributes
    ----------
    name : str
        Unique plugin name, lowercase, conventionally ``"<stage>.<algorithm>"``
        (``"peaks.first-moment"``).
    stage : str
        The stage kind implemented, e.g. one of :data:`BUILTIN_STAGE_KINDS`.
    version : str
        Algorithm version; bump it whenever results change, since it is part of the
        provenance key that decides whether a stored result can be reused.
    input_type, output_type : type of Record
        The record classes taken and returned.
    Params : type of StageParams
        The parameter model: frozen, ``extra="forbid"``, every field with a default. Stages
        without parameters may keep the empty default.
    requires : tuple of str
        What the context must provide: ``"calibration"``, ``"raster"`` or extras keys.
    """

    name: ClassVar[str]
    stage: ClassVar[str]
    version: ClassVar[str]
    input_type: ClassVar[type[Record]]
    output_type: ClassVar[type[Record]]
    Params: ClassVar[type[BaseModel]] = StageParams
    requires: ClassVar[tuple[str, ...]] = ()

    @abstractmethod
    def run(self, data: InT, params: Any, context: StageContext) -> OutT:
        """Compute the output record; no I/O, no global state, same inputs → same output.

        Parameters
        ----------
        data : Record
            The input, an instance of :attr:`input_type`.
        params : Params
            Validated parameters, an instance of :attr:`Params`.
        context : StageContext
            Station data; holds everything named in :attr:`requires`.

        Returns
        -------
        Record
            An instance of :attr:`output_type`.
        """

    def __repr__(self) -> str:
        name = getattr(self, "name", "?")
        version = getattr(self, "version", "?")
        return f"<{type(self).__name__} {name} version {version}>"


def _params_problems(params_cls: object) -> list[str]:
    if not (isinstance(params_cls, type) and issubclass(params_cls, BaseModel)):
        return [f"Params must be a pydantic model class, not {params_cls!r}"]
    problems = []
    config = params_cls.model_config
    if config.get("frozen") is not True:
        problems.append("Params must be frozen (model_config frozen=True; subclass StageParams)")
    if config.get("extra") != "forbid":
        problems.append(
            "Params must forbid unknown keys (model_config extra='forbid'; subclass StageParams)"
        )
    required = [name for name, info in params_cls.model_fields.items() if info.is_required()]
    if required:
        problems.append(f"Params fields without a default: {', '.join(required)}")
    else:
        try:
            params_hash(params_cls())
        except (ValidationError, TypeError, ValueError) as exc:
            problems.append(f"Params() with the defaults fails: {exc}")
    return problems


def stage_problems(obj: object) -> list[str]:
    """List what keeps a class or instance from being a usable stage plugin.

    Parameters
    ----------
    obj : object
        A :class:`Stage` subclass or instance (or anything else, which is reported).

    Returns
    -------
    list of str
        One message per problem; empty when the stage declares everything correctly.
    """
    cls = obj if isinstance(obj, type) else type(obj)
    if not issubclass(cls, Stage):
        where = f"{cls.__module__}.{cls.__qualname__}"
        return [f"{where} is not a subclass of rasterserver.stage.Stage"]
    problems = []
    if inspect.isabstract(cls):
        missing = ", ".join(sorted(getattr(cls, "__abstractmethods__", ())))
        problems.append(f"abstract method(s) not implemented: {missing}")
    name = getattr(obj, "name", None)
    if not isinstance(name, str) or not _NAME_RE.match(name):
        problems.append(
            f"name must be a lowercase string of letters, digits, '.', '_', '-', not {name!r}"
        )
    kind = getattr(obj, "stage", None)
    if not isinstance(kind, str) or not _KIND_RE.match(kind):
        problems.append(f"stage must be a lowercase stage kind such as 'peaks', not {kind!r}")
    version = getattr(obj, "version", None)
    if not isinstance(version, str) or not version.strip():
        problems.append(f"version must be a non-empty string, not {version!r}")
    for attr in ("input_type", "output_type"):
        record_cls = getattr(obj, attr, None)
        if not (isinstance(record_cls, type) and issubclass(record_cls, Record)):
            problems.append(f"{attr} must be a Record subclass, not {record_cls!r}")
    problems.extend(_params_problems(getattr(obj, "Params", None)))
    requires = getattr(obj, "requires", ())
    if not (isinstance(requires, tuple) and all(isinstance(r, str) for r in requires)):
        problems.append(f"requires must be a tuple of strings, not {requires!r}")
    return problems


def params_hash(params: BaseModel) -> str:
    """Return the sha256 hex digest of the parameters' canonical JSON.

    Canonical means sorted keys, no whitespace and defaults included, so ``{"a": 1, "b": 2}``
    and ``{"b": 2, "a": 1}`` and an omitted default all give the same digest. Together with
    the plugin name and version it identifies a computation in the provenance. The fields
    a class names in ``digest_omits_defaults`` (options added switched off) are left out
    while at their default, so that adding one keeps the digest of the stored results.

    Parameters
    ----------
    params : pydantic.BaseModel
        A validated parameters instance (a stage's ``Params``).

    Returns
    -------
    str
        64 lowercase hex digits.
    """
    dump = params.model_dump(mode="json")
    omitted: frozenset[str] = getattr(type(params), "digest_omits_defaults", frozenset())
    fields = type(params).model_fields
    for name in omitted:
        if name in dump and getattr(params, name) == fields[name].default:
            del dump[name]
    # non-ASCII written as is, NaN allowed: as these digests were first stored
    return canonical_json_sha256(dump, ensure_ascii=False, allow_nan=True)


def _describe_validation_error(exc: ValidationError, params_cls: type[BaseModel]) -> str:
    known = ", ".join(params_cls.model_fields) or "none"
    parts = []
    for error in exc.errors():
        where = ".".join(str(p) for p in error["loc"]) or "parameters"
        if error["type"] == "extra_forbidden":
            parts.append(f"unknown parameter {where!r} (parameters: {known})")
        else:
            got = reprlib.repr(error.get("input"))
            parts.append(f"{where}: {error['msg']} (got {got})")
    return "; ".join(parts)


def coerce_params(
    stage: Stage[Any, Any], params: BaseModel | Mapping[str, Any] | None = None
) -> BaseModel:
    """Turn None, a mapping or a ``Params`` instance into validated ``stage.Params``.

    Parameters
    ----------
    stage : Stage
        The stage whose ``Params`` model applies.
    params : Params, Mapping or None
        None for the defaults, a mapping (e.g. parsed JSON from a request), or an instance of
        the stage's ``Params``.

    Returns
    -------
    pydantic.BaseModel
        An instance of ``stage.Params``.

    Raises
    ------
    InputError
        On unknown keys, wrong types or values, or a ``Params`` of another stage; the message
        names the plugin.
    """
    params_cls = stage.Params
    if params is None:
        params = {}
    if isinstance(params, params_cls):
        return params
    if isinstance(params, BaseModel):
        raise InputError(
            f"parameters for stage plugin {stage.name!r} must be its own Params "
            f"or a mapping, not {type(params).__qualname__}"
        )
    if not isinstance(params, Mapping):
        raise InputError(
            f"parameters for stage plugin {stage.name!r} must be a mapping, "
            f"not {type(params).__name__}"
        )
    try:
        return params_cls.model_validate(dict(params))
    except ValidationError as exc:
        detail = _describe_validation_error(exc, params_cls)
        raise InputError(f"invalid parameters for stage plugin {stage.name!r}: {detail}") from None


_declarations_ok: weakref.WeakSet[type] = weakref.WeakSet()


def _check_declarations(stage: object) -> None:
    # The registry checks what it loads, but run_stage is also called on classes straight from
    # tests and notebooks; check each class once, not on every call in a Dask worker loop.
    cls = type(stage)
    if cls in _declarations_ok:
        return
    problems = stage_problems(stage)
    if problems:
        name = getattr(stage, "name", cls.__qualname__)
        raise TypeError(f"{name!r} is not a valid stage plugin: {'; '.join(problems)}")
    _declarations_ok.add(cls)


def run_stage(
    stage: Stage[InT, OutT] | type[Stage[InT, OutT]],
    data: InT,
    params: BaseModel | Mapping[str, Any] | None = None,
    context: StageContext | None = None,
) -> OutT:
    """Run one stage with its inputs checked: the single way the pipeline calls a plugin.

    Parameters
    ----------
    stage : Stage or Stage subclass
        The plugin; a class is instantiated without arguments.
    data : Record
        The input record; must be an instance of ``stage.input_type``.
    params : Params, Mapping or None, optional
        Parameters as accepted by :func:`coerce_params`; None means the defaults.
    context : StageContext, optional
        Station data; an empty context when omitted.

    Returns
    -------
    Record
        The stage's output, an instance of ``stage.output_type``.

    Raises
    ------
    InputError
        When the input record has the wrong type, the parameters are invalid, or the context
        lacks something the stage requires.
    TypeError
        When the stage's declarations are invalid (see :func:`stage_problems`) or it returns
        something other than its ``output_type``: both are plugin bugs.
    """
    if isinstance(stage, type):
        stage = stage()
    _check_declarations(stage)
    input_type = stage.input_type
    if not isinstance(data, input_type):
        raise InputError(
            f"stage plugin {stage.name!r} takes {input_type.__name__} records "
            f"(kind {input_type.kind!r}), not {type(data).__name__}"
        )
    validated = coerce_params(stage, params)
    if context is None:
        context = StageContext()
    missing = [r for r in stage.requires if not context.has(r)]
    if missing:
        raise InputError(
            f"stage plugin {stage.name!r} needs {', '.join(missing)} in its context, none was given"
        )
    try:
        result = stage.run(data, validated, context)
    except Exception as exc:
        # Keep the plugin's own exception type (callers may handle InputError) but say which
        # plugin raised it: in a Dask worker traceback that is otherwise hard to tell.
        exc.add_note(f"raised by stage plugin {stage.name!r} version {stage.version}")
        raise
    output_type = stage.output_type
    if not isinstance(result, output_type):
        raise TypeError(
            f"stage plugin {stage.name!r} version {stage.version} returned "
            f"{type(result).__name__}, but declares output_type {output_type.__name__}"
        )
    return result
