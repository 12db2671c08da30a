"""Run chains of stage plugins: in memory for one image, and for archived acquisitions.

Two entry points:

:func:`run_chain`
    Pure: an image (or any intermediate record) in, one record per stage out. No archive, no
    I/O; what ``rasterserver reconstruct`` and the tests use.
:class:`Pipeline`
    For an archived acquisition: read its raster frame (never modifying it), resolve its
    calibration, run the chain, store each stage's output in a derived HDF5 file
    (:mod:`rasterserver.store.derived`) and record a :class:`~rasterserver.catalog.models.
    StageResult` row with full provenance, inside a :class:`~rasterserver.catalog.models.
    PipelineRun` row.

Reuse
-----
Every result has a *chain key*: SHA-256 over the frame's checksum and index and, for its stage
and each stage before it, the plugin name, algorithm version, parameters hash, and the
checksums of the calibration and raster definition for the stages that use them
(``requires``). The same key means the same computation, so the stored result is reused; the
longest stored prefix of a chain is loaded and only the rest is computed. A new calibration
therefore recomputes reconstruction onwards but reuses the image-processing stages, and a new
peak detector recomputes everything; old results stay beside the new ones.

Work is split so that a Dask worker can do the computing: :meth:`Pipeline.plan` (catalogue and
files, in the driver), :func:`compute` (pure, anywhere) and :meth:`Pipeline.commit` (files and
rows, in the driver).

Interrupted runs
----------------
A run is committed ``running`` before anything is computed, naming its runner (the driver
process, :mod:`rasterserver.runner`). If that process is killed, nothing finishes the row, so
whenever runs are listed (:meth:`Pipeline.runs`), an acquisition is planned or the
unprocessed ones are selected, a ``running`` run of this host whose process is gone is stored
as ``failed`` with an error beginning :data:`INTERRUPTED`. Runs of other hosts cannot be
checked from here and are left; :meth:`Pipeline.reap` marks them when told their host has
stopped. Nothing else needs repairing: results are committed only with their files, and a
file written before the kill is adopted by the next run of the same computation.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import logging
import socket
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from sqlalchemy import exists, select, update
from sqlalchemy.exc import IntegrityError as SQLIntegrityError
from sqlalchemy.orm import Session

from rasterserver import __version__
from rasterserver.archive import Archive, Problem, VerifyReport, canonical_json_sha256
from rasterserver.catalog.models import (
    Acquisition,
    Calibration,
    Frame,
    PipelineRun,
    StageResult,
)
from rasterserver.catalog.models import Station as StationRow
from rasterserver.documents import calibration_from_document, raster_from_document
from rasterserver.errors import InputError, IntegrityError, NotFoundError, RasterServerError
from rasterserver.frame_fit import check_frame_fits
from rasterserver.optics import Station
from rasterserver.raster import Raster
from rasterserver.records import Image, Record
from rasterserver.registry import Registry, get_registry
from rasterserver.runner import (
    current_runner,
    describe_runner,
    local_host,
    runner_gone,
    runner_host,
)
from rasterserver.stage import (
    BUILTIN_STAGE_KINDS,
    Stage,
    StageContext,
    coerce_params,
    params_hash,
    run_stage,
)
from rasterserver.store.derived import DerivedStore

__all__ = [
    "DEFAULT_TARGETS",
    "INTERRUPTED",
    "ChainStep",
    "Computation",
    "Pipeline",
    "Plan",
    "ProcessResult",
    "ReapReport",
    "StepOutcome",
    "check_frame_fits",
    "compute",
    "parse_stage_options",
    "resolve_chain",
    "run_chain",
]

log = logging.getLogger(__name__)

DEFAULT_TARGET = "mesh"
#: What ``rasterserver process`` computes when told nothing: the mesh and the back-shape
#: analysis, both from the one surface.
DEFAULT_TARGETS: tuple[str, ...] = ("mesh", "analysis")
_KEY_TAG = "rasterserver.chain/1"

#: How the error of a run whose process was killed begins (its status is ``failed``).
INTERRUPTED = "interrupted: "


# --- chains ------------------------------------------------------------------------------------


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
        stage = registry.get(name)
        if stage.stage != kind:
            raise InputError(
                f"plugin {stage.name!r} implements stage {stage.stage!r}, not {kind!r}"
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


# --- archived acquisitions -----------------------------------------------------------------------


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

    Made by :meth:`Pipeline.plan` in the driver; :func:`compute` needs only ``steps[first:]``,
    ``input_record`` and ``context``.
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

    @property
    def to_compute(self) -> list[ChainStep]:
        """The steps that have no stored result yet."""
        return self.steps[self.first :]


@dataclass
class Computation:
    """What :func:`compute` returns: the new records, their timings and where it ran."""

    records: dict[str, Record]
    durations: dict[str, float]
    host: str


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


@dataclass(frozen=True)
class StepOutcome:
    """How one stage of a processed acquisition came about."""

    kind: str
    plugin: str
    result_id: int
    reused: bool
    duration_s: float
    reason: str
    store_path: str
    output_checksum: str


@dataclass
class ProcessResult:
    """The outcome of processing one acquisition.

    Attributes
    ----------
    uid : str
        The acquisition.
    run_id : int
        Its :class:`PipelineRun` row.
    steps : list of StepOutcome
        One per stage, in order.
    final : Record or None
        The last stage's record (loaded from its file when reused).
    records : dict of str to Record
        Records computed in this run (reused ones are not loaded).
    """

    uid: str
    run_id: int
    steps: list[StepOutcome]
    final: Record | None = None
    records: dict[str, Record] = field(default_factory=dict)

    @property
    def computed(self) -> int:
        """Number of stages computed in this run."""
        return sum(not s.reused for s in self.steps)

    @property
    def reused(self) -> int:
        """Number of stages whose stored result was reused."""
        return sum(s.reused for s in self.steps)

    @property
    def reason(self) -> str:
        """The last stage's reason (why it is empty, or a note)."""
        return self.steps[-1].reason if self.steps else ""


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


@dataclass
class ReapReport:
    """What :meth:`Pipeline.reap` found among the ``running`` runs.

    Attributes
    ----------
    marked : int
        Runs marked interrupted (with ``dry_run``: that would have been).
    alive : int
        Runs of live processes on this host, left running.
    unchecked : dict of str to int
        Per host, runs left running that cannot be checked from here: those of other hosts
        not named in ``hosts``, and those recorded before runs named their process.
    """

    marked: int = 0
    alive: int = 0
    unchecked: dict[str, int] = field(default_factory=dict)


def _interruption(host: str, runner: str, declared: frozenset[str]) -> str | None:
    """The error to store for a ``running`` run, or None to leave it running."""
    if runner_gone(runner):
        return f"{INTERRUPTED}the process running it ({describe_runner(runner)}) is gone"
    where = runner_host(runner) or host
    if where not in declared:
        return None
    if where == local_host() and runner_host(runner):
        return None  # its process is here and alive: naming the host does not stop it
    return (
        f"{INTERRUPTED}host {where} was reported to run it no longer "
        f"(`rasterserver runs reap --host {where}`); it ran as {describe_runner(runner)}"
    )


class Pipeline:
    """Processing of archived acquisitions with stored results, provenance and reuse.

    Parameters
    ----------
    archive : Archive
        The archive (catalogue and raw store).
    registry : Registry, optional
        Where plugins are found.
    """

    def __init__(self, archive: Archive, *, registry: Registry | None = None) -> None:
        self.archive = archive
        self.registry = registry or get_registry()
        self.derived = DerivedStore(archive.settings.archive, resolve=self.registry.record_type)

    # --- the three phases ------------------------------------------------------------------

    def plan(
        self,
        uid: str,
        *,
        chain: Mapping[str, str] | None = None,
        params: Mapping[str, Mapping[str, Any]] | None = None,
        calibration: tuple[str, int | None] | None = None,
        until: str = DEFAULT_TARGET,
        frame_index: int | None = None,
    ) -> Plan:
        """Resolve the chain, the frame and the calibration; find stored results; open a run.

        A :class:`PipelineRun` row is committed with status ``running``, naming this process
        as its runner; if anything after that fails, the run is marked ``failed`` with the
        message and the error re-raised. Earlier runs of the acquisition left ``running`` by a
        killed process of this host are marked interrupted in the same transaction.

        Parameters
        ----------
        uid : str
            Acquisition uid.
        chain, params, until
            As for :func:`run_chain`.
        calibration : (str, int or None), optional
            Station name and calibration version (None: newest) to use instead of the one
            attached at ingest. It must belong to the acquisition's station.
        frame_index : int, optional
            Frame to process; the first ``raster`` frame by default.

        Returns
        -------
        Plan

        Raises
        ------
        NotFoundError
            Unknown acquisition, station or calibration; no calibration attached or given.
        InputError
            Bad chain or parameters, no raster frame, a calibration of another station, an
            invalid calibration document, or a frame of another size than the camera's.
        IntegrityError
            A stored result to be reused is missing or altered.
        """
        steps = resolve_chain(chain, params=params, until=until, registry=self.registry)
        acquisition = self.archive.acquisition(uid)
        with self.archive.session() as s:
            # a run its killed process left "running" must not look like work in progress
            # beside the new one
            self._reap(s, ReapReport(), acquisition_id=acquisition.id, local_only=True)
            run = PipelineRun(
                acquisition_id=acquisition.id,
                chain=[step.describe() for step in steps],
                status="running",
                started_at=_now(),
                host=socket.gethostname(),
                runner=current_runner(),
                package_version=__version__,
            )
            s.add(run)
        try:
            return self._plan(acquisition, run, steps, calibration, frame_index)
        except BaseException as exc:
            self.fail(run.id, exc)
            raise

    def _plan(
        self,
        acquisition: Acquisition,
        run: PipelineRun,
        steps: list[ChainStep],
        calibration: tuple[str, int | None] | None,
        frame_index: int | None,
    ) -> Plan:
        uid = acquisition.uid
        frame = self._frame(acquisition, frame_index)
        cal_row, station, raster = self._calibration(acquisition, calibration)
        with self.archive.session() as s:
            s.get(PipelineRun, run.id).calibration_id = cal_row.id  # type: ignore[union-attr]
        check_frame_fits((frame.height, frame.width), station)
        raster_sha = canonical_json_sha256(raster.to_dict())
        keys = chain_keys(
            frame.sha256, frame.index, steps, calibration_sha=cal_row.sha256, raster_sha=raster_sha
        )
        with self.archive.session() as s:
            rows = {
                row.chain_key: row
                for row in s.scalars(
                    select(StageResult).where(
                        StageResult.acquisition_id == acquisition.id,
                        StageResult.chain_key.in_(keys),
                    )
                )
            }
        cached: list[CachedResult | None] = []
        for key in keys:
            row = rows.get(key)
            if row is None or (cached and cached[-1] is None):
                cached.append(None)
                continue
            cached.append(CachedResult(row.id, row.store_path, row.output_checksum, row.reason))
        first = next((i for i, c in enumerate(cached) if c is None), len(steps))
        context = StageContext(calibration=station, raster=raster)
        input_record: Record | None = None
        input_checksum = ""
        if first < len(steps):
            if first == 0:
                # read-only, SHA-256 verified against the file: the raw frame is never touched
                pixels = self.archive.read_frame(uid, frame.index)
                input_record = Image(pixels, role=frame.role)
            else:
                previous = cached[first - 1]
                assert previous is not None
                input_record = self._load(previous)
            input_checksum = input_record.content_hash()
        return Plan(
            uid=uid,
            acquisition_id=acquisition.id,
            run_id=run.id,
            frame_index=frame.index,
            calibration_id=cal_row.id,
            steps=steps,
            keys=keys,
            cached=cached,
            first=first,
            input_record=input_record,
            input_checksum=input_checksum,
            context=context,
        )

    def compute(self, plan: Plan) -> Computation:
        """Compute the steps of ``plan`` without stored results, in this process."""
        if plan.input_record is None:
            return Computation({}, {}, socket.gethostname())
        try:
            return compute(plan.input_record, plan.to_compute, plan.context, registry=self.registry)
        except BaseException as exc:
            self.fail(plan.run_id, exc)
            raise

    def commit(self, plan: Plan, computation: Computation) -> ProcessResult:
        """Store the computed records and their provenance; finish the run.

        Files are written (durably) before their rows; a crash in between leaves files that
        the next run adopts, because their names follow from their chain keys.
        """
        try:
            return self._commit(plan, computation)
        except BaseException as exc:
            self.fail(plan.run_id, exc)
            raise

    def _commit(self, plan: Plan, computation: Computation) -> ProcessResult:
        outcomes: list[StepOutcome] = []
        for step, cached in zip(plan.steps[: plan.first], plan.cached[: plan.first], strict=True):
            assert cached is not None
            outcomes.append(
                StepOutcome(
                    step.kind,
                    step.plugin,
                    cached.result_id,
                    True,
                    0.0,
                    cached.reason,
                    cached.store_path,
                    cached.output_checksum,
                )
            )
        stored = []
        input_checksum = plan.input_checksum
        for step, key in zip(plan.to_compute, plan.keys[plan.first :], strict=True):
            record = computation.records[step.kind]
            result = self.derived.write(
                plan.uid,
                record,
                stage=step.kind,
                plugin=step.plugin,
                plugin_version=step.version,
                params=step.params,
                params_hash=step.params_hash,
                chain_key=key,
                input_checksum=input_checksum,
            )
            stored.append((step, key, record, result, input_checksum))
            input_checksum = result.output_checksum
        parent_id = outcomes[-1].result_id if outcomes else None
        with self.archive.session() as s:
            for step, key, record, result, in_sum in stored:
                row = StageResult(
                    acquisition_id=plan.acquisition_id,
                    run_id=plan.run_id,
                    parent_id=parent_id,
                    calibration_id=(
                        plan.calibration_id
                        if {"calibration", "raster"} & set(step.requires)
                        else None
                    ),
                    frame_index=plan.frame_index,
                    stage=step.kind,
                    plugin=step.plugin,
                    plugin_version=step.version,
                    plugin_package=step.package,
                    params=step.params,
                    params_hash=step.params_hash,
                    chain_key=key,
                    input_checksum=in_sum,
                    output_checksum=result.output_checksum,
                    record_kind=record.kind,
                    store_path=result.path,
                    reason=getattr(record, "reason", "") or "",
                    package_version=__version__,
                    host=computation.host,
                    duration_s=float(computation.durations.get(step.kind, 0.0)),
                    created_at=_now(),
                )
                reused = False
                try:
                    with s.begin_nested():
                        s.add(row)
                except SQLIntegrityError:
                    # another process stored the same computation meanwhile: use its row
                    existing = s.scalar(
                        select(StageResult).where(
                            StageResult.acquisition_id == plan.acquisition_id,
                            StageResult.chain_key == key,
                        )
                    )
                    if existing is None:
                        raise
                    row, reused = existing, True
                parent_id = row.id
                outcomes.append(
                    StepOutcome(
                        step.kind,
                        step.plugin,
                        row.id,
                        reused,
                        row.duration_s,
                        row.reason,
                        row.store_path,
                        row.output_checksum,
                    )
                )
            run = s.get(PipelineRun, plan.run_id)
            assert run is not None
            run.status = "done"
            run.finished_at = _now()
            run.computed = sum(not o.reused for o in outcomes)
            run.reused = sum(o.reused for o in outcomes)
        final: Record | None = None
        if computation.records and plan.steps:
            final = computation.records.get(plan.steps[-1].kind)
        if final is None and outcomes:
            last = outcomes[-1]
            final = self.derived.read(last.store_path, expected_checksum=last.output_checksum)
        log.info(
            "processed acquisition %s: %d stage(s) computed, %d reused",
            plan.uid,
            sum(not o.reused for o in outcomes),
            sum(o.reused for o in outcomes),
        )
        return ProcessResult(plan.uid, plan.run_id, outcomes, final, dict(computation.records))

    def process(
        self,
        uid: str,
        *,
        chain: Mapping[str, str] | None = None,
        params: Mapping[str, Mapping[str, Any]] | None = None,
        calibration: tuple[str, int | None] | None = None,
        until: str = DEFAULT_TARGET,
        frame_index: int | None = None,
    ) -> ProcessResult:
        """Process one acquisition in this process: plan, compute, commit.

        See :meth:`plan` for the parameters and errors.

        Returns
        -------
        ProcessResult
        """
        plan = self.plan(
            uid,
            chain=chain,
            params=params,
            calibration=calibration,
            until=until,
            frame_index=frame_index,
        )
        return self.commit(plan, self.compute(plan))

    # --- queries ---------------------------------------------------------------------------

    def result(
        self, uid: str, stage: str, *, plugin: str | None = None
    ) -> tuple[StageResult, Record]:
        """The newest stored result of ``stage`` for acquisition ``uid``, with its record.

        Raises
        ------
        NotFoundError
            Unknown acquisition, or nothing of that stage stored (the message says how to
            process it).
        """
        acquisition = self.archive.acquisition(uid)
        query = select(StageResult).where(
            StageResult.acquisition_id == acquisition.id, StageResult.stage == stage
        )
        if plugin is not None:
            query = query.where(StageResult.plugin == plugin)
        with self.archive.session() as s:
            row = s.scalar(query.order_by(StageResult.created_at.desc(), StageResult.id.desc()))
        if row is None:
            which = f" by {plugin}" if plugin else ""
            raise NotFoundError(
                f"acquisition {uid} has no stored {stage} result{which}: "
                f"run `rasterserver process {uid}` first"
            )
        return row, self.derived.read(row.store_path, expected_checksum=row.output_checksum)

    def results(self, uid: str) -> list[StageResult]:
        """Every stored result of ``uid``, oldest first."""
        acquisition = self.archive.acquisition(uid)
        with self.archive.session() as s:
            return list(
                s.scalars(
                    select(StageResult)
                    .where(StageResult.acquisition_id == acquisition.id)
                    .order_by(StageResult.id)
                )
            )

    def runs(self, uid: str) -> list[PipelineRun]:
        """Every pipeline run of ``uid``, oldest first.

        A ``running`` run of this host whose process is gone is marked interrupted first
        (``failed``, error beginning :data:`INTERRUPTED`), so it is never listed as running.
        """
        acquisition = self.archive.acquisition(uid)
        query = (
            select(PipelineRun)
            .where(PipelineRun.acquisition_id == acquisition.id)
            .order_by(PipelineRun.id)
        )
        with self.archive.session() as s:
            rows = list(s.scalars(query))
            # one query when nothing is running, the usual case
            if any(row.status == "running" for row in rows):
                report = self._reap(s, ReapReport(), acquisition_id=acquisition.id, local_only=True)
                if report.marked:
                    rows = list(s.scalars(query.execution_options(populate_existing=True)))
            return rows

    def reap(self, *, hosts: Sequence[str] = (), dry_run: bool = False) -> ReapReport:
        """Mark every run left ``running`` by a process that is gone as interrupted.

        Runs of this host are checked (see :func:`rasterserver.runner.runner_gone`); those of
        a live process are left alone. Runs of another host cannot be checked from here:
        they are marked only if that host is named in ``hosts``, by someone who knows that
        nothing processes there any more. Marked runs get status ``failed`` and an error
        beginning :data:`INTERRUPTED` that says which process ran them.

        Parameters
        ----------
        hosts : sequence of str, optional
            Hosts whose ``running`` runs are to be taken as stopped. Naming this host marks
            its runs recorded without a runner (before revision 0008), never a live one.
        dry_run : bool, optional
            Count, change nothing.

        Returns
        -------
        ReapReport
        """
        report = ReapReport()
        with self.archive.session() as s:
            self._reap(s, report, declared=frozenset(hosts), dry_run=dry_run)
        return report

    def _reap(
        self,
        s: Session,
        report: ReapReport,
        *,
        acquisition_id: int | None = None,
        local_only: bool = False,
        declared: frozenset[str] = frozenset(),
        dry_run: bool = False,
    ) -> ReapReport:
        query = select(PipelineRun.id, PipelineRun.host, PipelineRun.runner).where(
            PipelineRun.status == "running"
        )
        if acquisition_id is not None:
            query = query.where(PipelineRun.acquisition_id == acquisition_id)
        here = local_host()
        if local_only:  # the automatic path: other hosts' runs cannot be checked anyway
            query = query.where(PipelineRun.host == here)
        for run_id, host, runner in s.execute(query).all():
            error = _interruption(host, runner, declared)
            if error is None:
                where = runner_host(runner) or host
                if where == here and runner:
                    report.alive += 1
                else:
                    report.unchecked[where] = report.unchecked.get(where, 0) + 1
                continue
            if dry_run:
                report.marked += 1
                continue
            # only if still running: its process may have finished it since it was read
            done = s.execute(
                update(PipelineRun)
                .where(PipelineRun.id == run_id, PipelineRun.status == "running")
                .values(status="failed", finished_at=_now(), error=error)
                .execution_options(synchronize_session=False)
            )
            if done.rowcount:
                report.marked += 1
                log.warning("pipeline run %d marked failed: %s", run_id, error)
        return report

    def unprocessed(self, *, patient: str | None = None, limit: int = 100_000) -> list[str]:
        """Uids of acquisitions with a raster frame and no successful run, oldest first.

        Runs that killed processes of this host left ``running`` are marked interrupted
        first, so that a reprocessing job does not find them still "in progress".
        """
        done = exists().where(
            PipelineRun.acquisition_id == Acquisition.id, PipelineRun.status == "done"
        )
        has_raster = exists().where(Frame.acquisition_id == Acquisition.id, Frame.role == "raster")
        query = select(Acquisition.uid).where(~done, has_raster)
        with self.archive.session() as s:
            self._reap(s, ReapReport(), local_only=True)
            if patient is not None:
                query = query.where(Acquisition.patient_id == self.archive.patient(patient, s).id)
            query = query.order_by(Acquisition.acquired_at, Acquisition.id).limit(limit)
            return list(s.scalars(query))

    def verify(self, *, progress: Callable[[int, int], None] | None = None) -> VerifyReport:
        """Check stored results against their rows: every row's file exists and matches.

        Reported problems (:class:`rasterserver.archive.Problem`): ``missing`` (a row without
        its file), ``corrupt`` (a file whose contents differ from the row's checksum or that
        cannot be read), ``orphaned`` (a complete file without a row: processing stopped
        between writing it and committing its row; the next run of the same computation
        adopts it), ``temporary`` (a partial write) and ``stray`` (not made by rasterserver).

        Returns
        -------
        rasterserver.archive.VerifyReport
            ``frames_checked`` counts the results checked.
        """
        report = VerifyReport()
        with self.archive.session() as s:
            rows = list(
                s.execute(
                    select(Acquisition.uid, StageResult.store_path, StageResult.output_checksum)
                    .join(Acquisition, Acquisition.id == StageResult.acquisition_id)
                    .order_by(StageResult.id)
                )
            )
        known = {path for _uid, path, _sum in rows}
        for done, (uid, path, checksum) in enumerate(rows, start=1):
            where = self.archive.settings.archive / path
            try:
                self.derived.read(path, expected_checksum=checksum)
            except NotFoundError:
                report.problems.append(
                    Problem("missing", uid, where, "stored result row without its file")
                )
            except IntegrityError as exc:
                report.problems.append(Problem("corrupt", uid, where, str(exc)))
            report.frames_checked += 1
            if progress:
                progress(done, len(rows))
        for entry in self.derived.scan():
            relative = entry.path.relative_to(self.archive.settings.archive).as_posix()
            if entry.kind == "final" and relative not in known:
                report.problems.append(
                    Problem(
                        "orphaned",
                        entry.uid,
                        entry.path,
                        "result file without a catalogue row: processing stopped between "
                        "writing it and recording it; the same computation will adopt it",
                    )
                )
            elif entry.kind == "temp":
                report.problems.append(
                    Problem(
                        "temporary",
                        entry.uid,
                        entry.path,
                        "partial write of an interrupted run; safe to delete",
                    )
                )
            elif entry.kind == "stray":
                report.problems.append(
                    Problem("stray", None, entry.path, "file not made by rasterserver")
                )
        report.acquisitions_checked = len({uid for uid, _p, _s in rows})
        return report

    # --- helpers ---------------------------------------------------------------------------

    def _frame(self, acquisition: Acquisition, index: int | None) -> Frame:
        frames = sorted(acquisition.frames, key=lambda f: f.index)
        if index is not None:
            for frame in frames:
                if frame.index == index:
                    return frame
            raise NotFoundError(f"acquisition {acquisition.uid} has no frame {index}")
        for frame in frames:
            if frame.role == "raster":
                return frame
        roles = ", ".join(sorted({f.role for f in frames})) or "none"
        raise InputError(
            f"acquisition {acquisition.uid} has no raster frame (frame roles: {roles}); "
            "give the frame index to process another one"
        )

    def _calibration(
        self, acquisition: Acquisition, wanted: tuple[str, int | None] | None
    ) -> tuple[Calibration, Station, Raster]:
        with self.archive.session() as s:
            if wanted is not None:
                station_name, version = wanted
                row = self.archive.calibration(station_name, version, s)
                if acquisition.station_id is not None and row.station_id != acquisition.station_id:
                    own_row = s.get(StationRow, acquisition.station_id)
                    own = own_row.name if own_row is not None else "?"
                    raise InputError(
                        f"calibration {station_name}:{row.version} belongs to station "
                        f"{station_name!r} but acquisition {acquisition.uid} was recorded at "
                        f"station {own!r}"
                    )
            elif acquisition.calibration_id is not None:
                row = s.get(Calibration, acquisition.calibration_id)
                assert row is not None
            else:
                raise NotFoundError(
                    f"acquisition {acquisition.uid} has no calibration: give one with "
                    "--calibration STATION:VERSION (or ingest with --station after storing a "
                    "calibration of that station)"
                )
            raster_definition = row.raster.definition if row.raster is not None else None
            station_name = row.station.name
        label = f"calibration {station_name}:{row.version}"
        station = calibration_from_document(row.parameters, source=label)
        if raster_definition is not None:
            raster = raster_from_document(raster_definition, source=f"the raster of {label}")
        else:
            try:
                raster = station.raster_definition
            except KeyError as exc:
                raise InputError(f"the raster of {label} is unusable: {exc}") from None
        return row, station, raster

    def _load(self, cached: CachedResult) -> Record:
        try:
            return self.derived.read(cached.store_path, expected_checksum=cached.output_checksum)
        except NotFoundError:
            raise IntegrityError(
                f"stored result {cached.store_path} is missing; run `rasterserver verify`"
            ) from None

    def fail(self, run_id: int, exc: BaseException) -> None:
        """Mark run ``run_id`` failed with the message of ``exc`` (if it is still running)."""
        message = str(exc) if isinstance(exc, RasterServerError) else f"{type(exc).__name__}: {exc}"
        try:
            with self.archive.session() as s:
                run = s.get(PipelineRun, run_id)
                if run is not None and run.status == "running":
                    run.status = "failed"
                    run.finished_at = _now()
                    run.error = message[:10_000]
        except Exception:  # the original error matters more than failing to record it
            log.exception("could not mark pipeline run %s as failed", run_id)
