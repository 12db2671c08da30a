"""Comparisons of two visits as stored stage results: computed once, reused after.

The comparison stage (kind ``comparison``, default ``comparison.landmark-icp``) takes its
input from two acquisitions. Its result is stored like every stage result (a derived file
under visit A's acquisition and a ``stage_result`` row), with provenance keyed by what it was
computed from: the plugin, its version and parameters, and the ids and checksums of the four
input results (each visit's mesh and analysis; the surface is the analysis's parent). The
inputs are also rows of ``stage_result_input``, so an input cannot be deleted from under a
comparison. Asking again for the same comparison of the same results finds the row; a new
analysis of either visit, another plugin version or other parameters computes a new one
beside the old. The asymmetry map (kind ``asymmetry``, default ``asymmetry.mirror-icp``) is
stored the same way with one visit's inputs, so it is computed once per visit.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from sqlalchemy import select

from rasterserver.catalog.models import StageResult, StageResultInput
from rasterserver.errors import InputError
from rasterserver.pair_comparison import pack, pack_visit
from rasterserver.records import Record
from rasterserver.result_rows import add_or_adopt, result_row
from rasterserver.stage import coerce_params, params_hash, run_stage

if TYPE_CHECKING:
    from rasterserver.pipeline import Pipeline
    from rasterserver.visit_comparison import ArchivedVisit

__all__ = [
    "ASYMMETRY_STAGE",
    "COMPARISON_STAGE",
    "StoredComparison",
    "comparison_key",
    "stored_asymmetry",
    "stored_comparison",
]

#: The stage kind of comparisons.
COMPARISON_STAGE = "comparison"
#: The stage kind of a visit's asymmetry map.
ASYMMETRY_STAGE = "asymmetry"
_KEY_TAG = "rasterserver.comparison-key/1"


@dataclass(frozen=True)
class StoredComparison:
    """A comparison of two visits (or one visit's asymmetry map) as stored.

    Attributes
    ----------
    result_id : int
        Its ``stage_result`` row.
    record : Record
        A :class:`~rasterserver.records_comparison.ComparisonRecord` or
        :class:`~rasterserver.records_comparison.AsymmetryRecord` (``reason`` set when
        refused).
    reused : bool
        True when it was found stored, False when computed now.
    plugin, version : str
        The comparison plugin and its algorithm version.
    """

    result_id: int
    record: Any
    reused: bool
    plugin: str
    version: str

    def provenance(self) -> dict[str, Any]:
        """JSON-ready: the result id, plugin, version and whether it was reused."""
        return {
            "result_id": self.result_id,
            "plugin": self.plugin,
            "version": self.version,
            "reused": self.reused,
        }


def comparison_key(
    plugin: str, version: str, params_digest: str, inputs: list[tuple[str, int, str]]
) -> str:
    """The provenance key of a comparison: SHA-256 over the plugin, its version, the
    parameters' hash and each input's role, result id and checksum (in order)."""
    text = json.dumps(
        [_KEY_TAG, plugin, version, params_digest, [list(i) for i in inputs]],
        separators=(",", ":"),
    )
    return hashlib.sha256(text.encode()).hexdigest()


def _inputs(visits: Sequence[tuple[str, ArchivedVisit]]) -> list[tuple[str, int, str, int]]:
    """``(role, result id, checksum, acquisition id)`` of every input, in order."""
    out = []
    for prefix, visit in visits:
        if visit.visit is None:
            raise InputError(f"acquisition {visit.uid} cannot be compared: {visit.reason}")
        if not visit.inputs:
            raise InputError(f"acquisition {visit.uid}: no stored results to compare")
        out += [
            (f"{prefix}{role}", rid, checksum, visit.acquisition_id)
            for role, rid, checksum in visit.inputs
        ]
    return out


def _stored(
    pipeline: Pipeline,
    kind: str,
    visits: Sequence[tuple[str, ArchivedVisit]],
    make_input: Callable[[], Record],
    plugin: str | None,
    params: Mapping[str, Any] | None,
) -> StoredComparison:
    """The stored result of stage ``kind`` over ``visits`` (stored under the first one's
    acquisition), or computed now and stored."""
    registry = pipeline.registry
    stage = registry.get(plugin) if plugin else registry.default_for(kind)
    if stage.stage != kind:
        raise InputError(f"plugin {stage.name!r} implements {stage.stage!r}, not {kind!r}")
    validated = coerce_params(stage, params)
    digest = params_hash(validated)
    inputs = _inputs(visits)
    owner = visits[0][1]
    key = comparison_key(stage.name, stage.version, digest, [i[:3] for i in inputs])
    with pipeline.archive.session() as s:
        row = s.scalar(
            select(StageResult).where(
                StageResult.acquisition_id == owner.acquisition_id, StageResult.chain_key == key
            )
        )
    if row is not None:
        record = pipeline.derived.read(row.store_path, expected_checksum=row.output_checksum)
        if not isinstance(record, stage.output_type):
            raise InputError(f"result {row.id} holds {row.record_kind!r}, not {kind!r}")
        return StoredComparison(row.id, record, True, stage.name, stage.version)
    began = time.perf_counter()
    record = run_stage(stage, make_input(), validated)
    duration = time.perf_counter() - began
    input_checksum = hashlib.sha256("".join(i[2] for i in inputs).encode()).hexdigest()
    stored = pipeline.derived.write(
        owner.uid,
        record,
        stage=kind,
        plugin=stage.name,
        plugin_version=stage.version,
        params=validated.model_dump(mode="json"),
        params_hash=digest,
        chain_key=key,
        input_checksum=input_checksum,
    )
    # Answer from the stored bytes, as every later ask will: the plugin's arrays may come
    # in another memory order (open3d's transforms are Fortran-ordered), and a product
    # taken in another order differs in the last bit, so that a parameter carried through
    # this comparison would change between the first ask and the second.
    record = pipeline.derived.read(stored.path, expected_checksum=stored.output_checksum)
    package = registry.info(stage.name).package or ""
    new = result_row(
        record_kind=stored.record_kind,
        reason=stored.reason,
        acquisition_id=owner.acquisition_id,
        frame_index=owner.frame_index,
        stage=kind,
        plugin=stage.name,
        plugin_version=stage.version,
        plugin_package=package,
        params=validated.model_dump(mode="json"),
        params_hash=digest,
        chain_key=key,
        input_checksum=input_checksum,
        output_checksum=stored.output_checksum,
        store_path=stored.path,
        duration_s=duration,
    )

    def add_inputs(row: StageResult) -> None:
        for position, (role, rid, _sum, acquisition_id) in enumerate(inputs):
            s.add(
                StageResultInput(
                    result_id=row.id,
                    position=position,
                    role=role,
                    input_id=rid,
                    acquisition_id=acquisition_id,
                )
            )

    with pipeline.archive.session() as s:
        row, adopted = add_or_adopt(s, new, then=add_inputs)
        result_id = row.id
    return StoredComparison(result_id, record, adopted, stage.name, stage.version)


def stored_comparison(
    pipeline: Pipeline,
    a: ArchivedVisit,
    b: ArchivedVisit,
    *,
    plugin: str | None = None,
    params: Mapping[str, Any] | None = None,
) -> StoredComparison:
    """The comparison of visits A and B (B registered onto A): the stored one, or computed
    now and stored.

    Parameters
    ----------
    pipeline : Pipeline
        The archive's pipeline.
    a, b : ArchivedVisit
        Two analysed visits of one patient with geometry (``visit`` not None).
    plugin : str, optional
        The comparison plugin; the registry's default for ``comparison`` when omitted.
    params : Mapping, optional
        Its parameters (validated).

    Returns
    -------
    StoredComparison
        Its ``record`` a :class:`~rasterserver.records_comparison.ComparisonRecord`.

    Raises
    ------
    InputError
        A visit without geometry, a plugin of another kind, invalid parameters.
    """

    def make() -> Record:
        assert a.visit is not None and b.visit is not None
        return pack(a.visit, b.visit)

    return _stored(pipeline, COMPARISON_STAGE, [("a.", a), ("b.", b)], make, plugin, params)


def stored_asymmetry(
    pipeline: Pipeline,
    visit: ArchivedVisit,
    *,
    plugin: str | None = None,
    params: Mapping[str, Any] | None = None,
) -> StoredComparison:
    """The asymmetry map of one visit: the stored one, or computed now and stored.

    Parameters and errors as :func:`stored_comparison`; the ``record`` is an
    :class:`~rasterserver.records_comparison.AsymmetryRecord`.
    """

    def make() -> Record:
        assert visit.visit is not None
        return pack_visit(visit.visit)

    return _stored(pipeline, ASYMMETRY_STAGE, [("", visit)], make, plugin, params)
