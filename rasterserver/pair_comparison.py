"""Comparisons and asymmetry maps as records: what the two stages compute and store.

:func:`pack` turns two :class:`~rasterserver.comparison.Visit` into the comparison stage's
input (:class:`~rasterserver.records_comparison.VisitPair`), :func:`pack_visit` one visit into
the asymmetry stage's (:class:`~rasterserver.records_comparison.VisitGeometry`); :func:`unpack`
and :func:`unpack_visit` go back. :func:`compare_pair` (registration and distance map) and
:func:`visit_asymmetry` are the computations, a refusal included (its reason), so that a
refused one is stored and not recomputed either. :func:`distance_of`, :func:`asymmetry_of` and
:func:`registration_of` redraw the maps from a stored record and the visit's mesh.
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
    TrunkFrame,
    Visit,
    asymmetry_fit,
    distance_map,
    pair_frames,
    register,
    trunk_mask,
)
from rasterserver.errors import InputError
from rasterserver.records_comparison import (
    AsymmetryRecord,
    ComparisonRecord,
    VisitGeometry,
    VisitPair,
)
from rasterserver.records_surface import MeshRecord, Surface

__all__ = [
    "asymmetry_of",
    "compare_pair",
    "distance_of",
    "pack",
    "pack_visit",
    "registration_of",
    "unpack",
    "unpack_visit",
    "visit_asymmetry",
]


def _fields(visit: Visit, prefix: str) -> dict[str, object]:
    frame = BodyFrame.of(visit.shape)
    return {
        f"{prefix}vertices": np.asarray(visit.mesh.vertices, dtype=np.float64),
        f"{prefix}triangles": np.asarray(visit.mesh.triangles, dtype=np.int32),
        f"{prefix}normals": np.asarray(visit.mesh.normals, dtype=np.float64),
        f"{prefix}valid": np.asarray(visit.surface.valid, dtype=bool),
        f"{prefix}x0": float(visit.surface.x0),
        f"{prefix}y0": float(visit.surface.y0),
        f"{prefix}spacing": float(visit.surface.spacing),
        f"{prefix}landmarks": frame.landmarks,
        f"{prefix}frame_origin": frame.frame_origin,
        f"{prefix}frame_axes": frame.frame_axes,
        f"{prefix}reason": frame.reason,
        f"{prefix}reasons": frame.reasons,
        f"{prefix}label": visit.label,
        f"{prefix}gravity": frame.gravity,
    }


def pack(a: Visit, b: Visit) -> VisitPair:
    """The comparison stage's input from two visits (B is registered onto A)."""
    return VisitPair(**_fields(a, "a_"), **_fields(b, "b_"))  # type: ignore[arg-type]


def pack_visit(visit: Visit) -> VisitGeometry:
    """The asymmetry stage's input from one visit."""
    return VisitGeometry(**_fields(visit, ""))  # type: ignore[arg-type]


def _visit(record: VisitPair | VisitGeometry, prefix: str) -> Visit:
    def get(name: str) -> object:
        return getattr(record, f"{prefix}{name}")

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
        None if get("gravity") is None else np.asarray(get("gravity"), dtype=float),
    )
    return Visit(surface, mesh, frame, label=str(get("label")))


def unpack(pair: VisitPair) -> tuple[Visit, Visit]:
    """The two visits of a comparison's input, A first."""
    return _visit(pair, "a_"), _visit(pair, "b_")


def unpack_visit(record: VisitGeometry) -> Visit:
    """The visit of an asymmetry stage's input."""
    return _visit(record, "")


def _indices(
    visit: Visit, margin: float, window: float | None, frame: TrunkFrame | None = None
) -> np.ndarray:
    return np.flatnonzero(
        trunk_mask(visit, visit.mesh.vertices, margin=margin, window=window, frame=frame)
    ).astype(np.int64)


def compare_pair(
    pair: VisitPair, *, thresholds: Thresholds = THRESHOLDS, margin: float = EDGE_MARGIN
) -> ComparisonRecord:
    """Register B onto A and measure the distance map.

    Parameters
    ----------
    pair : VisitPair
        The two visits.
    thresholds : Thresholds, optional
        When a registration is accepted.
    margin : float, optional
        Outline erosion of the trunk, mm.

    Returns
    -------
    ComparisonRecord
        With ``reason`` set (and an empty map) when the registration was refused.
    """
    a, b = unpack(pair)
    parameters = json.dumps({"margin_mm": margin, "thresholds": asdict(thresholds)})
    try:
        reg = register(a, b, thresholds=thresholds, margin=margin)
    except ComparisonRefusedError as exc:
        nan = np.full((4, 4), np.nan)
        return ComparisonRecord(
            reason=str(exc),
            transform=nan,
            start=nan,
            fitness=0.0,
            rmse=0.0,
            points=0,
            trunk=np.zeros(0, dtype=np.int64),
            distance=np.zeros(0, dtype=np.float64),
            parameters=parameters,
        )
    dmap = distance_map(a, b, reg, margin=margin, thresholds=thresholds)
    return ComparisonRecord(
        reason="",
        transform=np.asarray(reg.transform, dtype=np.float64),
        start=np.asarray(reg.start, dtype=np.float64),
        fitness=float(reg.fitness),
        rmse=float(reg.rmse),
        points=int(reg.points),
        trunk=_indices(
            a,
            margin,
            thresholds.axis_window,
            pair_frames(
                a, b, partial=thresholds.partial_frame, neither=thresholds.frame_without_vp
            )[0],
        ),
        distance=np.asarray(dmap.distance, dtype=np.float64),
        parameters=parameters,
        displaced=dmap.displaced,
        start_from=reg.start_from,
    )


def visit_asymmetry(
    record: VisitGeometry, *, thresholds: Thresholds = THRESHOLDS, margin: float = EDGE_MARGIN
) -> AsymmetryRecord:
    """One visit's asymmetry map (:func:`~rasterserver.comparison.asymmetry_fit`) as a record;
    a refusal is a record with its reason."""
    visit = unpack_visit(record)
    parameters = json.dumps({"margin_mm": margin, "thresholds": asdict(thresholds)})
    try:
        amap, transform, fitness, rmse = asymmetry_fit(visit, thresholds=thresholds, margin=margin)
    except ComparisonRefusedError as exc:
        return AsymmetryRecord(
            reason=str(exc),
            trunk=np.zeros(0, dtype=np.int64),
            asymmetry=np.zeros(0, dtype=np.float64),
            transform=np.full((4, 4), np.nan),
            fitness=0.0,
            rmse=0.0,
            parameters=parameters,
        )
    return AsymmetryRecord(
        reason="",
        trunk=_indices(visit, margin, thresholds.axis_window),
        asymmetry=np.asarray(amap.distance, dtype=np.float64),
        transform=np.asarray(transform, dtype=np.float64),
        fitness=float(fitness),
        rmse=float(rmse),
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
        record.start_from,
    )


def _map(
    mesh: MeshRecord,
    index: np.ndarray,
    values: np.ndarray,
    what: str,
    displaced: np.ndarray | None = None,
) -> DistanceMap:
    from rasterserver.comparison import submesh

    if len(index) and int(index.max()) >= len(mesh.vertices):
        raise InputError("the stored map does not belong to this mesh (vertex index too large)")
    keep = np.zeros(len(mesh.vertices), dtype=bool)
    keep[index] = True
    trunk = submesh(mesh, keep)
    return DistanceMap(
        trunk.vertices,
        trunk.triangles,
        trunk.normals,
        np.array(values),
        what=what,
        displaced=None if displaced is None else np.array(displaced),
    )


def distance_of(record: ComparisonRecord, mesh_a: MeshRecord) -> DistanceMap:
    """The distance map of a stored comparison, on visit A's mesh.

    Raises
    ------
    ComparisonRefusedError
        The comparison was refused (its reason).
    """
    if record.refused:
        raise ComparisonRefusedError(record.reason)
    return _map(mesh_a, record.trunk, record.distance, "signed distance (mm)", record.displaced)


def asymmetry_of(record: AsymmetryRecord, mesh: MeshRecord) -> DistanceMap | None:
    """A stored asymmetry map on its visit's mesh; None when it was refused
    (:attr:`~rasterserver.records_comparison.AsymmetryRecord.reason`)."""
    if record.refused:
        return None
    return _map(mesh, record.trunk, record.asymmetry, "asymmetry (mm)")
