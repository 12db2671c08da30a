"""One comparison of two visits as a record: what the comparison stage computes and stores.

:func:`pack` turns two :class:`~rasterserver.comparison.Visit` into the stage's input
(:class:`~rasterserver.records_comparison.VisitPair`), :func:`unpack` back; :func:`compare_pair`
is the computation (registration, distance map, both asymmetry maps) as a
:class:`~rasterserver.records_comparison.ComparisonRecord`, a refusal included (its reason),
so that a refused pair is stored and not recomputed either. :func:`distance_of`,
:func:`asymmetry_of` and :func:`registration_of` redraw the maps from a stored record and
visit A's (or B's) mesh.
"""

from __future__ import annotations

import json
from dataclasses import asdict

import numpy as np

from rasterserver.comparison import (
    EDGE_MARGIN,
    THRESHOLDS,
    BodyFrame,
    ComparisonRefusedError,
    DistanceMap,
    Registration,
    Thresholds,
    Visit,
    asymmetry_map,
    distance_map,
    register,
    trunk_mask,
)
from rasterserver.errors import InputError
from rasterserver.records_comparison import ComparisonRecord, VisitPair
from rasterserver.records_surface import MeshRecord, Surface

__all__ = [
    "asymmetry_of",
    "compare_pair",
    "distance_of",
    "pack",
    "registration_of",
    "unpack",
]


def pack(a: Visit, b: Visit) -> VisitPair:
    """The comparison stage's input from two visits (B is registered onto A)."""
    fields: dict[str, object] = {}
    for side, visit in (("a", a), ("b", b)):
        frame = BodyFrame.of(visit.shape)
        fields |= {
            f"{side}_vertices": np.asarray(visit.mesh.vertices, dtype=np.float64),
            f"{side}_triangles": np.asarray(visit.mesh.triangles, dtype=np.int32),
            f"{side}_normals": np.asarray(visit.mesh.normals, dtype=np.float64),
            f"{side}_valid": np.asarray(visit.surface.valid, dtype=bool),
            f"{side}_x0": float(visit.surface.x0),
            f"{side}_y0": float(visit.surface.y0),
            f"{side}_spacing": float(visit.surface.spacing),
            f"{side}_landmarks": frame.landmarks,
            f"{side}_frame_origin": frame.frame_origin,
            f"{side}_frame_axes": frame.frame_axes,
            f"{side}_reason": frame.reason,
            f"{side}_reasons": frame.reasons,
            f"{side}_label": visit.label,
        }
    return VisitPair(**fields)  # type: ignore[arg-type]


def _visit(pair: VisitPair, side: str) -> Visit:
    def get(name: str) -> object:
        return getattr(pair, f"{side}_{name}")

    valid = np.asarray(get("valid"), dtype=bool)
    surface = Surface(
        x0=float(get("x0")),  # type: ignore[arg-type]
        y0=float(get("y0")),  # type: ignore[arg-type]
        spacing=float(get("spacing")),  # type: ignore[arg-type]
        z=np.where(valid, 0.0, np.nan),  # only the outline matters here
    )
    mesh = MeshRecord(
        vertices=np.asarray(get("vertices")),
        triangles=np.asarray(get("triangles")),
        normals=np.asarray(get("normals")),
    )
    frame = BodyFrame(
        np.asarray(get("frame_origin")),
        np.asarray(get("frame_axes")),
        np.asarray(get("landmarks")),
        str(get("reason")),
        str(get("reasons")),
    )
    return Visit(surface, mesh, frame, label=str(get("label")))


def unpack(pair: VisitPair) -> tuple[Visit, Visit]:
    """The two visits of a stage input, A first."""
    return _visit(pair, "a"), _visit(pair, "b")


def _indices(visit: Visit, margin: float) -> np.ndarray:
    return np.flatnonzero(trunk_mask(visit, visit.mesh.vertices, margin=margin)).astype(np.int64)


def compare_pair(
    pair: VisitPair, *, thresholds: Thresholds = THRESHOLDS, margin: float = EDGE_MARGIN
) -> ComparisonRecord:
    """Register B onto A, measure the distance map and each visit's asymmetry map.

    Parameters
    ----------
    pair : VisitPair
        The two visits.
    thresholds : Thresholds, optional
        When a registration (and a mirror fit) is accepted.
    margin : float, optional
        Outline erosion of the trunk, mm.

    Returns
    -------
    ComparisonRecord
        With ``reason`` set (and empty maps) when the registration was refused; an asymmetry
        map that was refused has its own reason.
    """
    a, b = unpack(pair)
    parameters = json.dumps({"margin_mm": margin, "thresholds": asdict(thresholds)})
    empty_i, empty_f = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.float64)
    asym: dict[str, tuple[np.ndarray, np.ndarray, str]] = {}
    for side, visit in (("a", a), ("b", b)):
        try:
            amap = asymmetry_map(visit, thresholds=thresholds, margin=margin)
            asym[side] = (_indices(visit, margin), amap.distance, "")
        except ComparisonRefusedError as exc:
            asym[side] = (empty_i, empty_f, str(exc))
    try:
        reg = register(a, b, thresholds=thresholds, margin=margin)
    except ComparisonRefusedError as exc:
        nan = np.full((4, 4), np.nan)
        reg, dmap, reason = Registration(nan, nan, 0.0, 0.0, 0), None, str(exc)
    else:
        dmap, reason = distance_map(a, b, reg, margin=margin), ""
    return ComparisonRecord(
        reason=reason,
        transform=np.asarray(reg.transform, dtype=np.float64),
        start=np.asarray(reg.start, dtype=np.float64),
        fitness=float(reg.fitness),
        rmse=float(reg.rmse),
        points=int(reg.points),
        trunk=_indices(a, margin) if dmap is not None else empty_i,
        distance=np.asarray(dmap.distance, dtype=np.float64) if dmap is not None else empty_f,
        a_asymmetry_trunk=asym["a"][0],
        a_asymmetry=np.asarray(asym["a"][1], dtype=np.float64),
        a_asymmetry_reason=asym["a"][2],
        b_asymmetry_trunk=asym["b"][0],
        b_asymmetry=np.asarray(asym["b"][1], dtype=np.float64),
        b_asymmetry_reason=asym["b"][2],
        parameters=parameters,
    )


def registration_of(record: ComparisonRecord) -> Registration:
    """The registration of a stored comparison.

    Raises
    ------
    ComparisonRefusedError
        The comparison was refused (its reason).
    """
    if record.refused:
        raise ComparisonRefusedError(record.reason)
    return Registration(
        np.array(record.transform),
        np.array(record.start),
        record.fitness,
        record.rmse,
        record.points,
    )


def _map(mesh: MeshRecord, index: np.ndarray, values: np.ndarray, what: str) -> DistanceMap:
    from rasterserver.comparison import _submesh

    if len(index) and int(index.max()) >= len(mesh.vertices):
        raise InputError("the stored map does not belong to this mesh (vertex index too large)")
    keep = np.zeros(len(mesh.vertices), dtype=bool)
    keep[index] = True
    trunk = _submesh(mesh, keep)
    return DistanceMap(trunk.vertices, trunk.triangles, trunk.normals, np.array(values), what=what)


def distance_of(record: ComparisonRecord, mesh_a: MeshRecord) -> DistanceMap:
    """The distance map of a stored comparison, on visit A's mesh.

    Raises
    ------
    ComparisonRefusedError
        The comparison was refused (its reason).
    """
    if record.refused:
        raise ComparisonRefusedError(record.reason)
    return _map(mesh_a, record.trunk, record.distance, "signed distance (mm)")


def asymmetry_of(record: ComparisonRecord, side: str, mesh: MeshRecord) -> DistanceMap | None:
    """Visit ``side``'s (``"a"`` or ``"b"``) asymmetry map on its mesh; None when refused
    (:attr:`~rasterserver.records_comparison.ComparisonRecord.a_asymmetry_reason`)."""
    if side not in ("a", "b"):
        raise InputError(f"side must be 'a' or 'b', not {side!r}")
    if getattr(record, f"{side}_asymmetry_reason"):
        return None
    index = getattr(record, f"{side}_asymmetry_trunk")
    return _map(mesh, index, getattr(record, f"{side}_asymmetry"), "asymmetry (mm)")
