"""The chain of stage plugins, pure: resolve it, key it, run it. No archive, no I/O.

:func:`resolve_chain` picks the stages from record types; :func:`run_chain` runs them on one
image in memory (``rasterserver reconstruct``, the tests); :func:`compute` runs the steps of a
plan, anywhere (a Dask worker); :func:`chain_keys` names every result. The archive-bound
service that stores results is :class:`rasterserver.pipeline.Pipeline`.

Reuse
-----
Every result has a *chain key*: SHA-256 over the frame's checksum and index and, for its stage
and each stage before it, the plugin name, algorithm version, parameters hash, and the
checksums of the calibration and raster definition for the stages that use them
(``requires``). The same key means the same computation, so the stored result is reused; the
longest stored prefix of a chain is loaded and only the rest is computed. A new calibration
therefore recomputes reconstruction onwards but reuses the image-processing stages, and a new
peak detector recomputes everything; old results stay beside the new ones.
"""

from __future__ import annotations

import hashlib
import socket
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from rasterserver.errors import InputError, RasterServerError
from rasterserver.frame_fit import check_frame_fits
from rasterserver.records import Image, Record
from rasterserver.registry import Registry, get_registry
from rasterserver.stage import (
    BUILTIN_STAGE_KINDS,
    Stage,
    StageContext,
    coerce_params,
    params_hash,
    run_stage,
)

if TYPE_CHECKING:
    from rasterserver.store.derived import StoredResult

__all__ = [
    "DEFAULT_TARGET",
    "DEFAULT_TARGETS",
    "CachedResult",
    "ChainStep",
    "Computation",
    "Plan",
    "chain_keys",
    "compute",
    "parse_stage_options",
    "resolve_chain",
    "run_chain",
]

DEFAULT_TARGET = "mesh"
#: What ``rasterserver process`` computes when told nothing: the mesh and the back-shape
#: analysis, both from the one surface.
DEFAULT_TARGETS: tuple[str, ...] = ("mesh", "analysis")
_KEY_TAG = "rasterserver.chain/1"


@dataclass(frozen=True)
class ChainStep:
    """One resolved stage of a chain: which plugin, with which validated parameters.

    Attributes
    ----------
    kind : str
        Stage kind (``"points"``).
    plugin : str
        Plugin name (``"points.ray-plane"``).
    version : str
        The plugin's algorithm version.
    params : dict
        Validated parameters, defaults included, JSON-ready.
    params_hash : str
        :func:`rasterserver.stage.params_hash` of them.
    requires : tuple of str
        What the plugin needs from the context.
    package : str
        ``"<distribution> <version>"`` that provides the plugin.
    """

    kind: str
    plugin: str
    version: str
    params: dict[str, Any]
    params_hash: str
    requires: tuple[str, ...]
    package: str = ""

    def describe(self) -> dict[str, Any]:
        """JSON-ready summary for the run's ``chain`` column."""
        return {
            "stage": self.kind,
            "plugin": self.plugin,
            "version": self.version,
            "params_hash": self.params_hash,
        }


def parse_stage_options(options: Sequence[str]) -> dict[str, str]:
    """Parse ``KIND=PLUGIN`` command-line options into a chain mapping.

    Parameters
    ----------
    options : sequence of str
        E.g. ``["peaks=peaks.first-moment", "surface=surface.linear-grid"]``.

    Returns
    -------
    dict of str to str

    Raises
    ------
    InputError
        An option without ``=`` or naming a kind twice.
    """
    chain: dict[str, str] = {}
    for option in options:
        kind, sep, plugin = option.partition("=")
        kind, plugin = kind.strip(), plugin.strip()
        if not sep or not kind or not plugin:
            raise InputError(
                f"--stage {option!r}: expected KIND=PLUGIN, e.g. points=points.ray-plane"
            )
        if kind in chain:
            raise InputError(f"--stage names stage {kind!r} twice")
        chain[kind] = plugin
    return chain


def _producer(
    wanted: type[Record],
    chain: Mapping[str, str],
    registry: Registry,
    seen: set[str],
) -> Stage[Any, Any] | None:
    """The stage that makes ``wanted`` records: the plugin named for a kind in ``chain``, else
    the default of the only kind whose default makes them; None when no kind does."""
    named = [
        registry.get(plugin)
        for kind, plugin in chain.items()
        if kind not in seen and registry.get(plugin).output_type is wanted
    ]
    if len(named) == 1:
        return named[0]
    candidates = {
        kind: stage
        for kind in registry.stage_kinds()
        if kind not in seen and (stage := registry.default_for(kind)).output_type is wanted
    }
    if len(candidates) == 1:
        return next(iter(candidates.values()))
    if not candidates:
        return None
    # Two kinds make the same records (a third-party alternative to a built-in stage kind):
    # the built-in one is the clinical default, another one is chosen only by name.
    builtin = [k for k in candidates if k in BUILTIN_STAGE_KINDS]
    if len(builtin) == 1:
        return candidates[builtin[0]]
    raise InputError(
        f"stage kinds {', '.join(sorted(candidates))} all make {wanted.kind!r} records: name "
        "the one to use with --stage KIND=PLUGIN"
    )


def resolve_chain(
    chain: Mapping[str, str] | None = None,
    *,
    params: Mapping[str, Mapping[str, Any]] | None = None,
    start: type[Record] = Image,
    until: str = DEFAULT_TARGET,
    registry: Registry | None = None,
) -> list[ChainStep]:
    """Pick the stages that turn ``start`` records into the records of stage kind ``until``.

    Stage kinds are not a fixed list: the chain is resolved by record types, backwards from
    the plugin of ``until``: each step's input type must be made by exactly one stage kind
    (the plugin named for it in ``chain``, else that kind's default), until a stage takes
    ``start``. A plugin package that adds a kind (an analysis taking a ``Surface``) is found,
    run, stored and reused like the built-in ones, with no change here.

    Parameters
    ----------
    chain : Mapping of str to str, optional
        Plugin name per stage kind; the registry's default for kinds not named.
    params : Mapping of str to Mapping, optional
        Parameters per stage kind (validated here).
    start : type of Record, optional
        Class of the chain's input; the chain begins at the stage that takes it.
    until : str, optional
        Last stage kind, ``"mesh"`` by default; any installed kind.
    registry : Registry, optional
        Where plugins are found; the process's shared registry by default.

    Returns
    -------
    list of ChainStep
        In processing order.

    Raises
    ------
    InputError
        Unknown stage kinds, a plugin of another kind, parameters for stages not in the
        chain, invalid parameters, or no way from ``start`` records to ``until``.
    NotFoundError
        A named plugin does not exist or no plugin implements a needed stage.
    """
    registry = registry or get_registry()
    chain = dict(chain or {})
    params = dict(params or {})
    kinds = registry.stage_kinds()
    for what, mapping in (("--stage", chain), ("parameters", params), ("until", {until: 0})):
        unknown = sorted(set(mapping) - set(kinds))
        if unknown:
            raise InputError(
                f"{what}: unknown stage kind(s) {', '.join(unknown)}; stages: {', '.join(kinds)}"
            )
    for kind, name in chain.items():
        named = registry.get(name)
        if named.stage != kind:
            raise InputError(
                f"plugin {named.name!r} implements stage {named.stage!r}, not {kind!r}"
            )
    for kind, given in params.items():
        # parameters of stages outside the chain are still checked: a misspelt one is a mistake
        coerce_params(
            registry.get(chain[kind]) if kind in chain else registry.default_for(kind), given
        )
    stage: Stage[Any, Any] | None = (
        registry.get(chain[until]) if until in chain else registry.default_for(until)
    )
    stages: list[Stage[Any, Any]] = []
    seen: set[str] = set()
    while True:
        assert stage is not None
        stages.insert(0, stage)
        seen.add(stage.stage)
        if stage.input_type is start:
            break
        stage = _producer(stage.input_type, chain, registry, seen)
        if stage is None:
            raise InputError(
                f"no stage up to {until!r} takes {start.kind!r} records "
                f"(nothing makes the {stages[0].input_type.kind!r} records "
                f"{stages[0].name} takes)"
            )
    ignored = (set(chain) | set(params)) - seen - _downstream(seen, registry)
    before = sorted(ignored & _upstream(start, chain, registry))
    if before:
        raise InputError(
            f"stage(s) {', '.join(before)} come before {stages[0].stage!r}, where this chain "
            f"starts ({start.kind} input)"
        )
    if ignored:
        raise InputError(
            f"stage(s) {', '.join(sorted(ignored))} are not on the way from {start.kind!r} "
            f"records to {until!r}"
        )
    steps = []
    for stage in stages:
        validated = coerce_params(stage, params.get(stage.stage))
        info = registry.info(stage.name)
        steps.append(
            ChainStep(
                kind=stage.stage,
                plugin=stage.name,
                version=stage.version,
                params=validated.model_dump(mode="json"),
                params_hash=params_hash(validated),
                requires=tuple(stage.requires),
                package=f"{info.package or '?'} {info.package_version or '?'}",
            )
        )
    return steps


def _upstream(start: type[Record], chain: Mapping[str, str], registry: Registry) -> set[str]:
    """Stage kinds that make ``start`` records, directly or not (empty if undecidable)."""
    found: set[str] = set()
    wanted = start
    while wanted is not Image:
        try:
            stage = _producer(wanted, chain, registry, found)
        except InputError:
            break
        if stage is None:
            break
        found.add(stage.stage)
        wanted = stage.input_type
    return found


def _downstream(kinds: set[str], registry: Registry) -> set[str]:
    """Stage kinds fed, directly or not, by the records of ``kinds``: choices for them are
    not run by this chain, but they are not misplaced either (``process --stage mesh=...
    --until surface``)."""
    made = {registry.default_for(k).output_type for k in kinds}
    found: set[str] = set()
    grew = True
    while grew:
        grew = False
        for kind in registry.stage_kinds():
            stage = registry.default_for(kind)
            if kind not in found and kind not in kinds and stage.input_type in made:
                found.add(kind)
                made.add(stage.output_type)
                grew = True
    return found


def _as_record(data: np.ndarray | Record) -> Record:
    if isinstance(data, Record):
        return data
    if isinstance(data, np.ndarray):
        return Image(data)
    raise InputError(f"a chain takes an image array or a record, not {type(data).__name__}")


def _run_steps(
    record: Record,
    steps: Sequence[ChainStep],
    context: StageContext,
    registry: Registry,
) -> tuple[dict[str, Record], dict[str, float]]:
    results: dict[str, Record] = {}
    durations: dict[str, float] = {}
    for step in steps:
        stage = registry.get(step.plugin)
        if stage.version != step.version:
            raise RasterServerError(
                f"plugin {step.plugin} is version {stage.version} here but the chain was "
                f"planned with version {step.version}: install the same version everywhere"
            )
        t0 = time.perf_counter()
        record = run_stage(stage, record, step.params, context)
        durations[step.kind] = time.perf_counter() - t0
        results[step.kind] = record
    return results, durations


def run_chain(
    image: np.ndarray | Record,
    *,
    chain: Mapping[str, str] | None = None,
    params: Mapping[str, Mapping[str, Any]] | None = None,
    context: StageContext | None = None,
    until: str = DEFAULT_TARGET,
    registry: Registry | None = None,
    durations: dict[str, float] | None = None,
) -> dict[str, Record]:
    """Run the stages on one image in memory; no archive, no files.

    Parameters
    ----------
    image : numpy.ndarray or Record
        A 2-D ``uint8``/``uint16`` frame, an :class:`~rasterserver.records.Image`, or an
        intermediate record (e.g. ``NumberedLines``): the chain then starts at the stage that
        takes it.
    chain : Mapping of str to str, optional
        Plugin per stage kind (defaults from the registry).
    params : Mapping of str to Mapping, optional
        Parameters per stage kind.
    context : StageContext, optional
        Calibration (:class:`~rasterserver.optics.Station`) and raster
        (:class:`~rasterserver.raster.Raster`) for the stages that need them.
    until : str, optional
        Last stage kind (``"mesh"``).
    registry : Registry, optional
        Where plugins are found.
    durations : dict, optional
        Filled with seconds per stage kind.

    Returns
    -------
    dict of str to Record
        One record per stage kind run, in processing order.

    Raises
    ------
    InputError
        Bad chain, parameters or input, a frame of another size than the calibrated camera,
        or a stage's requirement missing from ``context``.
    """
    registry = registry or get_registry()
    record = _as_record(image)
    context = context or StageContext()
    steps = resolve_chain(chain, params=params, start=type(record), until=until, registry=registry)
    if isinstance(record, Image):
        check_frame_fits(record.pixels.shape, context.calibration)
    results, spent = _run_steps(record, steps, context, registry)
    if durations is not None:
        durations.update(spent)
    return results


def _key(previous: str, step: ChainStep, calibration_sha: str, raster_sha: str) -> str:
    parts = [
        previous,
        step.plugin,
        step.version,
        step.params_hash,
        calibration_sha if "calibration" in step.requires else "",
        raster_sha if "raster" in step.requires else "",
    ]
    return hashlib.sha256("\0".join(parts).encode()).hexdigest()


def chain_keys(
    frame_sha256: str,
    frame_index: int,
    steps: Sequence[ChainStep],
    *,
    calibration_sha: str,
    raster_sha: str,
) -> list[str]:
    """The chain key of every step (see the module docstring).

    Returns
    -------
    list of str
        64 hex digits each, one per step.
    """
    key = hashlib.sha256(f"{_KEY_TAG}\0{frame_sha256}\0{frame_index}".encode()).hexdigest()
    keys = []
    for step in steps:
        key = _key(key, step, calibration_sha, raster_sha)
        keys.append(key)
    return keys


@dataclass(frozen=True)
class CachedResult:
    """A stored result found for a step of a plan."""

    result_id: int
    store_path: str
    output_checksum: str
    reason: str


@dataclass
class Plan:
    """Everything needed to compute and store one acquisition's chain (picklable).

    Made by :meth:`rasterserver.pipeline.Pipeline.plan` in the driver; :func:`compute` needs
    only ``steps[first:]``, ``input_record`` and ``context``.
    """

    uid: str
    acquisition_id: int
    run_id: int
    frame_index: int
    calibration_id: int
    steps: list[ChainStep]
    keys: list[str]
    cached: list[CachedResult | None]
    first: int
    input_record: Record | None
    input_checksum: str
    context: StageContext
    frame_role: str = "raster"

    @property
    def needs_computing(self) -> bool:
        """Whether some step has no stored result yet."""
        return self.first < len(self.steps)

    @property
    def to_compute(self) -> list[ChainStep]:
        """The steps that have no stored result yet."""
        return self.steps[self.first :]


@dataclass
class Computation:
    """What :func:`compute` returns: the new records, their timings and where it ran.

    :func:`rasterserver.worker.work` also fills ``stored``: per stage kind, the
    :class:`~rasterserver.store.derived.StoredResult` written and the input checksum it was
    computed from; ``records`` then holds only what was asked to come back.
    """

    records: dict[str, Record]
    durations: dict[str, float]
    host: str
    stored: dict[str, tuple[StoredResult, str]] = field(default_factory=dict)


def compute(
    input_record: Record,
    steps: Sequence[ChainStep],
    context: StageContext,
    *,
    registry: Registry | None = None,
) -> Computation:
    """Run ``steps`` on ``input_record``: the pure part of processing, fit for a Dask worker.

    Plugins are looked up by name in ``registry``, by default the process's own (a worker's);
    a worker with another version of a plugin than the driver planned with refuses to compute.
    """
    records, durations = _run_steps(input_record, steps, context, registry or get_registry())
    return Computation(records, durations, socket.gethostname())
