"""The back-shape analysis as users see it: the verbs the CLI and the HTTP API share.

The ``analysis`` stage (a plugin taking a :class:`~rasterserver.records_surface.Surface`,
giving a :class:`~rasterserver.records_analysis.BackShape`) does the work; this module runs it
and says what it found:

:func:`analyse_frames`
    One or several camera frames of one patient session, in memory, no archive
    (``rasterserver analyse``): one BackShape per frame, combined into mean and spread.
:func:`acquisition_analysis`
    The stored analysis of an archived acquisition, one per raster frame, processing the frames
    that have none when asked (``rasterserver show``, ``GET /acquisitions/{uid}/analysis``).
:meth:`Analysis.document`
    The JSON document of both: ``landmarks`` (``VP``, ``DL``, ``DR``, ``DM``, ``SP`` →
    ``[x, y, z]`` mm in the calibration's world frame, named in ``frame``), ``parameters``
    (name → ``{"value", "unit", "spread"}``), ``reasons`` (what could not be found, and why),
    the frames analysed and each one's provenance.

An analysis that found nothing at all (a calibration without gravity, no back in view) is not
a result to show: :meth:`Analysis.check` raises :class:`AnalysisRefusedError` (exit 2, HTTP 422)
with the analysis's own reason.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy.orm import selectinload

from rasterserver.catalog.models import Calibration, StageResult
from rasterserver.errors import InputError, NotFoundError
from rasterserver.records_analysis import SAGITTAL_POINTS, BackShape, combine
from rasterserver.records_surface import Surface

if TYPE_CHECKING:
    from rasterserver.optics import Station
    from rasterserver.pipeline import Pipeline
    from rasterserver.raster import Raster
    from rasterserver.registry import Registry

__all__ = [
    "ANALYSIS_STAGE",
    "DOCUMENT_FORMAT",
    "KEY_PARAMETERS",
    "WORLD_FRAME",
    "Analysis",
    "AnalysisRefusedError",
    "FrameAnalysis",
    "acquisition_analysis",
    "analyse_frames",
    "ordered_parameters",
    "parameter_columns",
    "parameter_label",
]

#: The stage kind whose records are :class:`BackShape`.
ANALYSIS_STAGE = "analysis"
#: The ``format`` of the JSON document.
DOCUMENT_FORMAT = "rasterserver.back-shape/1"

#: The coordinate frame every position of the document is in.
WORLD_FRAME: dict[str, str] = {
    "name": "calibration world",
    "unit": "mm",
    "axes": (
        "the frame of the station's calibration, in which the reconstructed points are: "
        "X to the patient's right, Y down, Z away from the camera (anterior); gravity as given"
    ),
}

#: The parameters a short summary shows (the demo's table), in this order.
KEY_PARAMETERS: tuple[str, ...] = (
    "trunk_length",
    "surface_rotation_rms_deg",
    "surface_rotation_max_deg",
    "lateral_deviation_max_mm",
    "scoliosis_angle_deg",
    "pelvic_tilt_mm",
    "kyphotic_angle_deg",
    "lordotic_angle_deg",
)

# Clinical order and names (DIERS formetric's, Degenhardt et al. 2017); a parameter of a
# plugin not listed here is shown after these under its own name.
_LABELS: dict[str, str] = {
    "trunk_length": "Trunk length VP-DM",
    "trunk_inclination_mm": "Trunk inclination",
    "trunk_inclination_deg": "Trunk inclination",
    "trunk_imbalance_mm": "Trunk imbalance",
    "trunk_imbalance_deg": "Trunk imbalance",
    "pelvic_tilt_mm": "Pelvic tilt",
    "pelvic_tilt_deg": "Pelvic tilt",
    "pelvic_torsion_deg": "Pelvic torsion",
    "pelvic_rotation_deg": "Pelvic rotation",
    "kyphotic_angle_deg": "Kyphotic angle ICT-ITL",
    "lordotic_angle_deg": "Lordotic angle ITL-ILS",
    "fleche_cervicale_mm": "Flèche cervicale",
    "fleche_lombaire_mm": "Flèche lombaire",
    "surface_rotation_rms_deg": "Surface rotation (rms)",
    "surface_rotation_max_deg": "Surface rotation (max)",
    "surface_rotation_pos_max_deg": "Surface rotation (+max)",
    "surface_rotation_neg_max_deg": "Surface rotation (-max)",
    "lateral_deviation_rms_mm": "Lateral deviation (rms)",
    "lateral_deviation_max_mm": "Lateral deviation (max)",
    "lateral_deviation_pos_max_mm": "Lateral deviation (+max)",
    "lateral_deviation_neg_max_mm": "Lateral deviation (-max)",
    "scoliosis_angle_deg": "Scoliosis angle",
    "asymmetry_rms_mm": "Asymmetry (rms)",
}


def parameter_label(name: str) -> str:
    """The clinical name of parameter ``name`` (``"Trunk length VP-DM"``), else ``name``."""
    return _LABELS.get(name, name)


def ordered_parameters(names: Sequence[str] | Mapping[str, Any]) -> list[str]:
    """``names`` in clinical order: the known parameters first, then the others sorted."""
    known = [n for n in _LABELS if n in names]
    return known + sorted(set(names) - set(known))


def parameter_columns(
    columns: Sequence[tuple[str, Mapping[str, Mapping[str, Any]] | None]],
    *,
    names: Sequence[str] = KEY_PARAMETERS,
) -> list[str]:
    """A compact text table of parameters: one row per parameter, one column per analysis.

    Parameters
    ----------
    columns : sequence of (str, mapping or None)
        Heading and ``parameters`` of a document (:meth:`Analysis.document`), or None for an
        analysis that could not be made (its column shows ``-``).
    names : sequence of str, optional
        The rows, :data:`KEY_PARAMETERS` by default; a parameter no column has is left out.

    Returns
    -------
    list of str
        The lines, heading first.
    """
    rows = [n for n in names if any(p and n in p for _h, p in columns)]
    units = {n: next(p[n]["unit"] for _h, p in columns if p and n in p) for n in rows}
    first = max([len(parameter_label(n)) for n in rows] + [9])
    width = max([len(h) for h, _p in columns] + [8]) + 2

    def cell(parameters: Mapping[str, Mapping[str, Any]] | None, name: str) -> str:
        entry = parameters.get(name) if parameters else None
        value = _number(entry.get("value")) if entry else None
        return f"{'-':>{width}}" if value is None else f"{round(value, 1) + 0.0:>{width}.1f}"

    lines = [f"{'parameter':{first}}" + "".join(f"{h:>{width}}" for h, _p in columns) + "  unit"]
    lines += [
        f"{parameter_label(n):{first}}" + "".join(cell(p, n) for _h, p in columns) + f"  {units[n]}"
        for n in rows
    ]
    return lines


class AnalysisRefusedError(InputError):
    """The analysis found nothing to report; the message is its reason (exit 2, HTTP 422)."""


@dataclass(frozen=True)
class FrameAnalysis:
    """The analysis of one camera frame.

    Attributes
    ----------
    name : str
        The frame: its file name, or ``"frame N"`` of an acquisition.
    shape : BackShape
        What the analysis made of it (empty, with ``reason``, when it refused).
    surface : Surface or None
        The smoothed surface it was computed from (for the report), when loaded.
    index : int or None
        Frame index in its acquisition.
    result : StageResult or None
        The stored analysis result (provenance) of an archived frame.
    """

    name: str
    shape: BackShape
    surface: Surface | None = None
    index: int | None = None
    result: StageResult | None = None

    @property
    def analysed(self) -> bool:
        """Whether the analysis found anything in this frame."""
        return not self.shape.reason


@dataclass(frozen=True)
class Analysis:
    """The back-shape analysis of one patient session: its frames, and their combination.

    Attributes
    ----------
    frames : tuple of FrameAnalysis
        One per camera frame, in order.
    combined : BackShape
        The frames' analyses combined (:func:`rasterserver.records_analysis.combine`):
        parameters with their mean and spread; the single frame's analysis when there is one.
    calibration : str
        Which calibration: ``"STATION:VERSION"`` (archive) or the calibration's name.
    gravity : list of float or None
        Direction of gravity in the world frame, as the calibration gives it.
    plugin : dict
        The analysis plugin: ``plugin``, ``version``, ``package``.
    uid : str or None
        The acquisition, for an archived one.
    """

    frames: tuple[FrameAnalysis, ...]
    combined: BackShape
    calibration: str = ""
    gravity: list[float] | None = None
    plugin: dict[str, str] = field(default_factory=dict)
    uid: str | None = None

    @property
    def refused(self) -> bool:
        """Whether nothing was found in any frame."""
        return bool(self.combined.reason) or not any(f.analysed for f in self.frames)

    def check(self) -> Analysis:
        """Return self, or raise :class:`AnalysisRefusedError` when nothing was found.

        Raises
        ------
        AnalysisRefusedError
            With the analysis's reason (each frame's when they differ) and what it could not
            find.
        """
        if not self.refused:
            return self
        why = list(dict.fromkeys(f.shape.reason or "nothing found" for f in self.frames))
        if len(self.frames) > 1 and len(why) > 1:
            why = [f"{f.name}: {f.shape.reason or 'nothing found'}" for f in self.frames]
        subject = f"acquisition {self.uid}" if self.uid else ", ".join(f.name for f in self.frames)
        message = f"no back-shape analysis of {subject}: {'; '.join(why)}"
        details = self.frames[0].shape.reason_table() if len(self.frames) == 1 else {}
        if details:
            message += " (" + "; ".join(f"{k}: {v}" for k, v in details.items()) + ")"
        raise AnalysisRefusedError(message)

    def shown_frame(self) -> FrameAnalysis:
        """The frame whose maps and lines a report shows: the one :func:`combine` took them
        from (the representative frame), else the first one analysed."""
        combined = self.combined
        for frame in self.frames:
            shape = frame.shape
            if (
                frame.analysed
                and np.array_equal(shape.mean_curvature, combined.mean_curvature, equal_nan=True)
                and np.array_equal(shape.symmetry_line, combined.symmetry_line, equal_nan=True)
            ):
                return frame
        return next((f for f in self.frames if f.analysed), self.frames[0])

    def document(
        self, *, shift_time: Callable[[dt.datetime], dt.datetime] | None = None
    ) -> dict[str, Any]:
        """The JSON-ready document (``rasterserver.back-shape/1``).

        Parameters
        ----------
        shift_time : callable, optional
            Applied to every time of the provenance (the researchers' date shift).

        Returns
        -------
        dict
            ``format``, ``uid`` (archived), ``frame`` (the coordinate frame: name, unit, axes,
            gravity, calibration), ``landmarks``, ``landmark_confidence``, ``sagittal_points``
            (ICT, KA, ITL, LA, ILS of the sagittal profile, or None), ``body_frame``,
            ``parameters``, ``reasons`` (a list of ``{"what", "why"}``), ``frames`` (name,
            index, analysed, reason and, archived, ``provenance``) and ``plugin``.
        """
        shape = self.combined
        summary = shape.summary()
        parameters = shape.parameter_table()
        document: dict[str, Any] = {"format": DOCUMENT_FORMAT}
        if self.uid is not None:
            document["uid"] = self.uid
        document |= {
            "frame": {**WORLD_FRAME, "gravity": self.gravity, "calibration": self.calibration},
            "landmarks": summary["landmarks"],
            "landmark_confidence": summary["landmark_confidence"],
            "sagittal_points": {
                name: None if (p := shape.sagittal_point(name)) is None else [float(v) for v in p]
                for name in SAGITTAL_POINTS
            },
            "body_frame": _body_frame(shape),
            "parameters": {
                name: _parameter(parameters[name]) for name in ordered_parameters(parameters)
            },
            "reasons": _reasons(self),
            "frames": [_frame_entry(f, shift_time) for f in self.frames],
            "plugin": dict(self.plugin),
        }
        return document


def _number(value: Any) -> float | None:
    """A finite float, or None (JSON has no NaN)."""
    if value is None:
        return None
    number = float(value)
    return number if math.isfinite(number) else None


def _parameter(entry: Mapping[str, Any]) -> dict[str, Any]:
    return {
        "value": _number(entry.get("value")),
        "unit": str(entry.get("unit", "")),
        "spread": _number(entry.get("spread")),
    }


def _body_frame(shape: BackShape) -> dict[str, Any] | None:
    if not (np.all(np.isfinite(shape.frame_origin)) and np.all(np.isfinite(shape.frame_axes))):
        return None
    names = ("transverse", "vertical", "sagittal")
    return {
        "origin": [float(v) for v in shape.frame_origin],
        "axes": {
            n: [float(v) for v in row] for n, row in zip(names, shape.frame_axes, strict=True)
        },
    }


def _reasons(analysis: Analysis) -> list[dict[str, str]]:
    reasons = [{"what": what, "why": why} for what, why in analysis.combined.reason_table().items()]
    if len(analysis.frames) > 1:
        reasons += [
            {"what": f.name, "why": f.shape.reason} for f in analysis.frames if not f.analysed
        ]
    return reasons


def _frame_entry(
    frame: FrameAnalysis, shift_time: Callable[[dt.datetime], dt.datetime] | None
) -> dict[str, Any]:
    entry: dict[str, Any] = {
        "name": frame.name,
        "index": frame.index,
        "analysed": frame.analysed,
        "reason": frame.shape.reason,
    }
    row = frame.result
    if row is not None:
        created = row.created_at if row.created_at.tzinfo else row.created_at.replace(tzinfo=dt.UTC)
        if shift_time is not None:
            created = shift_time(created)
        entry["provenance"] = {
            "result_id": row.id,
            "stage": row.stage,
            "plugin": row.plugin,
            "plugin_version": row.plugin_version,
            "plugin_package": row.plugin_package,
            "params": row.params,
            "params_hash": row.params_hash,
            "chain_key": row.chain_key,
            "input_checksum": row.input_checksum,
            "output_checksum": row.output_checksum,
            "calibration_id": row.calibration_id,
            "package_version": row.package_version,
            "duration_s": row.duration_s,
            "created_at": created.isoformat().replace("+00:00", "Z"),
        }
    return entry


# --- the verbs ------------------------------------------------------------------------------


def _gravity(station: Station | None) -> list[float] | None:
    gravity = getattr(station, "gravity", None)
    return None if gravity is None else [float(v) for v in np.asarray(gravity).reshape(3)]


def analyse_frames(
    frames: Sequence[tuple[str, np.ndarray]],
    *,
    calibration: Station,
    raster: Raster,
    chain: Mapping[str, str] | None = None,
    params: Mapping[str, Mapping[str, Any]] | None = None,
    registry: Registry | None = None,
) -> Analysis:
    """Analyse camera frames of one patient session in memory, without an archive.

    Each frame runs through the whole chain (peaks → … → surface → analysis); the analyses
    are then combined (:func:`rasterserver.records_analysis.combine`).

    Parameters
    ----------
    frames : sequence of (str, numpy.ndarray)
        Name (for messages) and 2-D ``uint8``/``uint16`` pixels of each frame.
    calibration : Station
        The station's calibration (its world frame is the document's).
    raster : Raster
        The raster definition.
    chain, params, registry
        As for :func:`rasterserver.pipeline.run_chain`.

    Returns
    -------
    Analysis
        Check it with :meth:`Analysis.check` before showing it.

    Raises
    ------
    InputError
        No frame, a frame that does not fit the calibration, a bad chain.
    """
    from rasterserver.pipeline import resolve_chain, run_chain
    from rasterserver.stage import StageContext

    if not frames:
        raise InputError("no frame to analyse")
    context = StageContext(calibration=calibration, raster=raster)
    step = resolve_chain(chain, params=params, until=ANALYSIS_STAGE, registry=registry)[-1]
    analysed = []
    for name, pixels in frames:
        try:
            records = run_chain(
                pixels,
                chain=chain,
                params=params,
                context=context,
                until=ANALYSIS_STAGE,
                registry=registry,
            )
        except InputError as exc:
            raise type(exc)(f"{name}: {exc}") from None
        shape, surface = records[ANALYSIS_STAGE], records.get("surface")
        assert isinstance(shape, BackShape)
        analysed.append(
            FrameAnalysis(name, shape, surface if isinstance(surface, Surface) else None)
        )
    return Analysis(
        frames=tuple(analysed),
        combined=combine([f.shape for f in analysed]),
        calibration=calibration.name,
        gravity=_gravity(calibration),
        plugin={"plugin": step.plugin, "version": step.version, "package": step.package},
    )


def acquisition_analysis(
    pipeline: Pipeline, uid: str, *, process: bool = False, surfaces: bool = False
) -> Analysis:
    """The back-shape analysis of an archived acquisition: its stored results.

    Each raster frame's newest stored ``analysis`` result is read (verified against its
    checksum); with several raster frames they are combined
    (:func:`rasterserver.records_analysis.combine`).

    Parameters
    ----------
    pipeline : Pipeline
        The archive's pipeline.
    uid : str
        Acquisition uid.
    process : bool, optional
        Process the raster frames that have no stored analysis first (with the acquisition's
        calibration; stored results of earlier stages are reused).
    surfaces : bool, optional
        Also load each analysis's surface (what a report draws).

    Returns
    -------
    Analysis
        Check it with :meth:`Analysis.check` before showing it.

    Raises
    ------
    NotFoundError
        Unknown acquisition; no stored analysis and ``process`` false (the message says how
        to process it); no calibration when processing.
    InputError
        No raster frame; processing refused (see :meth:`Pipeline.plan`).
    """
    acquisition = pipeline.archive.acquisition(uid)
    indices = sorted(f.index for f in acquisition.frames if f.role == "raster")
    if not indices:
        roles = ", ".join(sorted({f.role for f in acquisition.frames})) or "none"
        raise InputError(f"acquisition {uid} has no raster frame to analyse (roles: {roles})")
    rows = _newest_analyses(pipeline, uid)
    missing = [i for i in indices if i not in rows]
    if missing and process:
        for index in missing:
            pipeline.process(uid, until=ANALYSIS_STAGE, frame_index=index)
        rows = _newest_analyses(pipeline, uid)
    rows = {i: rows[i] for i in indices if i in rows}
    if not rows:
        raise NotFoundError(
            f"acquisition {uid} has no stored analysis yet: process it first "
            f"(`rasterserver process {uid}`, `rasterserver show {uid} --process`, or over "
            'HTTP a job: POST /jobs with "until": "analysis")'
        )
    frames = []
    for index, row in rows.items():
        shape = pipeline.derived.read(row.store_path, expected_checksum=row.output_checksum)
        if not isinstance(shape, BackShape):
            raise InputError(
                f"the analysis result {row.id} of {uid} holds {row.record_kind!r} records, "
                "not a back-shape analysis"
            )
        surface = _parent_surface(pipeline, row) if surfaces else None
        frames.append(FrameAnalysis(f"frame {index}", shape, surface, index, row))
    newest = max(rows.values(), key=lambda r: r.id)
    calibration, gravity = _calibration(pipeline, newest.calibration_id)
    return Analysis(
        frames=tuple(frames),
        combined=combine([f.shape for f in frames]),
        calibration=calibration,
        gravity=gravity,
        plugin={
            "plugin": newest.plugin,
            "version": newest.plugin_version,
            "package": newest.plugin_package,
        },
        uid=uid,
    )


def _newest_analyses(pipeline: Pipeline, uid: str) -> dict[int, StageResult]:
    """The newest stored analysis result of each frame of ``uid``."""
    newest: dict[int, StageResult] = {}
    for row in pipeline.results(uid):  # oldest first
        if row.stage == ANALYSIS_STAGE:
            newest[row.frame_index] = row
    return newest


def _parent_surface(pipeline: Pipeline, row: StageResult) -> Surface | None:
    """The stored surface the analysis ``row`` was computed from (its parent result)."""
    if row.parent_id is None:
        return None
    with pipeline.archive.session() as s:
        parent = s.get(StageResult, row.parent_id)
    if parent is None:
        return None
    record = pipeline.derived.read(parent.store_path, expected_checksum=parent.output_checksum)
    return record if isinstance(record, Surface) else None


def _calibration(pipeline: Pipeline, calibration_id: int | None) -> tuple[str, list[float] | None]:
    """``"STATION:VERSION"`` and the gravity of calibration row ``calibration_id``."""
    from rasterserver.documents import stored_calibration

    if calibration_id is None:
        return "", None
    with pipeline.archive.session() as s:
        row = s.get(Calibration, calibration_id, options=[selectinload(Calibration.station)])
        if row is None:
            return "", None
        label, parameters = f"{row.station.name}:{row.version}", row.parameters
    return label, _gravity(stored_calibration(parameters, label=label))
