"""The midline's parameters of a visit without its own VP, from VP carried from another visit.

Where the analysis of an acquisition refused VP (hair, a shadow or a collar over the nape),
the parameters a scoliosis follow-up compares (lateral deviation, surface rotation, the
scoliosis angle: all measured along the symmetry line from VP to DM) are missing, and the
trend has a gap at that visit. The comparison of visits registers it onto its neighbours;
when one of them found VP, :func:`rasterserver.comparison.carry_vp` carries that VP across
and the acquisition's own analysis plugin is run again on its stored surface with it
(``vp_carried``), in memory: nothing is stored, the acquisition's own analysis stays as it
is. The values so obtained fill only the parameters the visit's own analysis lacked, and
each says which visit its VP came from (``vp_carried_from``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from rasterserver.catalog.models import Calibration, StageResult
from rasterserver.comparison import carry_vp
from rasterserver.errors import InputError
from rasterserver.records_analysis import BackShape
from rasterserver.stage import StageContext, run_stage

if TYPE_CHECKING:
    from rasterserver.pipeline import Pipeline
    from rasterserver.visit_comparison import ArchivedVisit

__all__ = ["NO_PARTNER", "carried_parameters", "has_vp", "with_carried"]

#: Why :func:`carried_parameters` carries nothing to a visit none of whose registered
#: partners found VP.
NO_PARTNER = "no registered visit found its VP"


def has_vp(visit: ArchivedVisit) -> bool:
    """Whether the visit's analysis found VP."""
    return visit.visit is not None and visit.visit.shape.landmark("VP") is not None


def _reanalysed(pipeline: Pipeline, visit: ArchivedVisit, point: Any) -> dict[str, Any]:
    """The shown frame's stored analysis run again with VP at ``point``: its parameters.

    Raises
    ------
    InputError
        Why it cannot be: the plugin takes no carried VP, is another version now, or found
        nothing.
    """
    from rasterserver.documents import stored_calibration

    assert visit.visit is not None
    ids = [i for role, i, _ in visit.inputs if role == "analysis"]
    with pipeline.archive.session() as s:
        rows = [s.get(StageResult, i) for i in ids]
        row = next((r for r in rows if r is not None and r.frame_index == visit.frame_index), None)
        if row is None:
            raise InputError("its stored analysis is gone")
        plugin, version, params = row.plugin, row.plugin_version, dict(row.params or {})
        calibration = s.get(Calibration, row.calibration_id) if row.calibration_id else None
        if calibration is None:
            raise InputError("its analysis has no calibration")
        label = f"{calibration.station.name}:{calibration.version}"
        document = calibration.parameters
    stage = pipeline.registry.get(plugin)
    if stage.version != version:
        raise InputError(
            f"its analysis was made by {plugin} version {version}, version {stage.version} is "
            "installed now: process it again first"
        )
    if "vp_carried" not in stage.Params.model_fields:
        raise InputError(f"the analysis plugin {plugin} takes no carried VP")
    station = stored_calibration(document, label=label)
    shape = run_stage(
        stage,
        visit.visit.surface,
        {**params, "vp_carried": [float(c) for c in point]},
        StageContext(calibration=station),
    )
    assert isinstance(shape, BackShape)
    if shape.reason:
        raise InputError(f"its analysis with the carried VP found nothing: {shape.reason}")
    return shape.parameter_table()


def with_carried(
    own: Mapping[str, Any] | None, carried: Mapping[str, Any], source: str
) -> dict[str, Any]:
    """A visit's own parameters, and those only the carried VP gave, marked with the visit it
    came from (``vp_carried_from``): a value of the visit's own is never replaced."""
    merged = dict(own or {})
    for name, value in carried.items():
        if name not in merged:
            merged[name] = {**value, "vp_carried_from": source}
    return merged


def carried_parameters(
    pipeline: Pipeline, visits: Sequence[ArchivedVisit], pairs: Sequence[Mapping[str, Any]]
) -> dict[str, dict[str, Any]]:
    """VP carried to every visit without its own, and the parameters it gives.

    Parameters
    ----------
    pipeline : Pipeline
        The archive's pipeline (stored analyses, calibrations, the plugins).
    visits : sequence of ArchivedVisit
        The compared visits.
    pairs : sequence of mapping
        The pair entries of :func:`rasterserver.visit_comparison.compare_visits` (``a``,
        ``b`` and, when registered, ``_stored``: the stored comparison, its registration
        and distance map). VP is carried only through these registrations, from the nearest
        visit in time that found it.

    Returns
    -------
    dict
        Per uid of an analysed visit without VP: ``from`` (the uid VP came from), ``vp``
        (world mm), ``surface_distance_mm`` and ``parameters`` (its own, plus those the
        carried VP gave, each marked ``vp_carried_from``); or ``refused`` (why not).
    """
    by_uid = {v.uid: v for v in visits}
    out: dict[str, dict[str, Any]] = {}
    for target in visits:
        if target.visit is None or has_vp(target):
            continue
        candidates = []
        for entry in pairs:
            if entry.get("_stored") is None or target.uid not in (entry["a"], entry["b"]):
                continue
            source = by_uid[entry["b"] if entry["a"] == target.uid else entry["a"]]
            if has_vp(source):
                gap = abs(source.acquired_at - target.acquired_at)
                candidates.append((gap, source.acquired_at, source, entry))
        if not candidates:
            out[target.uid] = {"refused": NO_PARTNER}
            continue
        reasons = []
        for _, _, source, entry in sorted(candidates, key=lambda c: (c[0], c[1])):
            assert source.visit is not None
            carried = carry_vp(
                source.visit,
                target.visit,
                entry["_stored"][1],
                source_is_a=entry["a"] == source.uid,
            )
            if carried.point is None:
                reasons.append(carried.reason)
                continue
            try:
                values = _reanalysed(pipeline, target, carried.point)
            except InputError as exc:
                reasons.append(f"VP of visit {source.uid}: {exc}")
                continue
            merged = with_carried(target.parameters, values, source.uid)
            out[target.uid] = {
                "from": source.uid,
                "vp": [float(c) for c in carried.point],
                "surface_distance_mm": carried.surface_distance,
                "parameters": merged,
            }
            break
        else:
            out[target.uid] = {"refused": "; ".join(reasons)}
    return out
