"""Comparing archived visits: the service behind ``rasterserver compare``.

Reads each acquisition's stored analysis, surface and mesh (processing them when asked),
compares consecutive visits and the first with the last (:mod:`rasterserver.comparison`),
computes the parameter trends (:mod:`rasterserver.trends`) and writes everything into one
folder: built in a temporary folder beside it and renamed into place at the end, so the
folder is whole or absent.

Files (``A-B`` are the two acquisitions' uids):

* ``distance_A-B.ply`` / ``.png``: the distance map of B registered onto A;
* ``asymmetry_UID.png``: each visit's asymmetry map;
* ``comparison.json`` (``rasterserver.comparison/1``): per pair the registration
  (transform, fitness, rmse) and the distance-map and asymmetry-change statistics, or the
  reason it was refused; per visit the asymmetry statistics; per visit without its own VP
  the visit VP was carried from (``carried_vp``: :mod:`rasterserver.carried_analysis`), or
  why it was not;
* ``trends.csv``, ``trends.json``, ``trends.png``;
* ``report.html``: timeline of the visits, parameter trends, the maps.
The report and the trends plot are written by :mod:`rasterserver.comparison_report`.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import secrets
import shutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rasterserver.analysis import acquisition_analysis
from rasterserver.carried_analysis import NO_PARTNER, carried_parameters, has_vp
from rasterserver.comparison import (
    ComparisonRefusedError,
    DistanceMap,
    Registration,
    Visit,
    asymmetry_change,
)
from rasterserver.comparison_report import write_report, write_trends_plot
from rasterserver.errors import InputError, NotFoundError
from rasterserver.pair_comparison import asymmetry_of, distance_of, registration_of
from rasterserver.records_surface import MeshRecord
from rasterserver.stored_comparison import StoredComparison, stored_asymmetry, stored_comparison
from rasterserver.trends import TrendVisit, trends, write_trends

if TYPE_CHECKING:
    from rasterserver.pipeline import Pipeline

__all__ = [
    "ArchivedVisit",
    "TwoVisits",
    "carry_from_nearest",
    "compare_two",
    "compare_visits",
    "load_visit",
    "patient_visits",
    "trend_visits",
]

#: How many of the nearest visits with VP a patient's trends try to carry it from, in turn
#: (each try registers two visits: a comparison computed and stored when new).
CARRY_FROM = 3

#: ``format`` of ``comparison.json``.
COMPARISON_FORMAT = "rasterserver.comparison/1"


@dataclass(frozen=True)
class ArchivedVisit:
    """One archived acquisition ready to compare.

    Attributes
    ----------
    uid : str
        The acquisition.
    acquired_at : datetime
        When it was acquired.
    visit : Visit or None
        Its geometry and analysis; None when the analysis found nothing (``reason``).
    parameters : dict or None
        The analysis's parameters.
    reason : str
        Why there is no visit geometry.
    acquisition_id : int
        Its catalogue row.
    frame_index : int
        The raster frame whose surface and mesh are compared.
    inputs : tuple
        ``(role, result id, checksum)`` of the stored results the geometry comes from
        (``analysis`` rows of every frame, then the ``mesh``): a comparison's provenance.
    """

    uid: str
    acquired_at: dt.datetime
    visit: Visit | None
    parameters: dict[str, Any] | None
    reason: str = ""
    acquisition_id: int = 0
    frame_index: int = 0
    inputs: tuple[tuple[str, int, str], ...] = ()


def load_visit(pipeline: Pipeline, uid: str, *, process: bool = False) -> ArchivedVisit:
    """Read the stored analysis, surface and mesh of acquisition ``uid``.

    An analysis that found nothing gives a visit without geometry (``visit`` None) and its
    reason: the trends show it as a gap, comparisons with it are refused.

    Raises
    ------
    NotFoundError
        Unknown acquisition, or not processed (and ``process`` false).
    """
    from rasterserver.analysis import AnalysisRefusedError

    info = pipeline.archive.info(uid)
    acquisition_id = pipeline.archive.acquisition(uid).id
    analysis = acquisition_analysis(pipeline, uid, process=process, surfaces=True)
    try:
        analysis.check()
    except AnalysisRefusedError as exc:
        return ArchivedVisit(uid, info.acquired_at, None, None, str(exc), acquisition_id)
    frame = analysis.shown_frame()
    index = frame.index or 0
    mesh_row = _mesh_row(pipeline, acquisition_id, frame.result)
    if mesh_row is None and process:
        pipeline.process(uid, until="mesh", frame_index=index)
        mesh_row = _mesh_row(pipeline, acquisition_id, frame.result)
    if frame.surface is None or mesh_row is None:
        return ArchivedVisit(
            uid, info.acquired_at, None, None, "no stored surface or mesh", acquisition_id, index
        )
    mesh = pipeline.derived.read(mesh_row.store_path, expected_checksum=mesh_row.output_checksum)
    if not isinstance(mesh, MeshRecord):
        raise InputError(
            f"result {mesh_row.id} of {uid} holds {mesh_row.record_kind!r}, not a mesh"
        )
    analyses = [f.result for f in analysis.frames if f.result is not None]
    inputs = (
        *(("analysis", r.id, r.output_checksum) for r in analyses),
        ("mesh", mesh_row.id, mesh_row.output_checksum),
    )
    visit = Visit(frame.surface, mesh, analysis.combined, label=uid)
    return ArchivedVisit(
        uid,
        info.acquired_at,
        visit,
        analysis.document()["parameters"],
        "",
        acquisition_id,
        index,
        inputs,
    )


def _mesh_row(pipeline: Pipeline, acquisition_id: int, analysis_row: Any) -> Any:
    """The newest stored mesh made from the surface the analysis ``analysis_row`` was computed
    from (the same frame, the same smoothing), None when there is none."""
    from sqlalchemy import select

    from rasterserver.catalog.models import StageResult

    if analysis_row is None or analysis_row.parent_id is None:
        return None
    with pipeline.archive.session() as s:
        return s.scalar(
            select(StageResult)
            .where(
                StageResult.acquisition_id == acquisition_id,
                StageResult.stage == "mesh",
                StageResult.parent_id == analysis_row.parent_id,
            )
            .order_by(StageResult.id.desc())
        )


def patient_visits(pipeline: Pipeline, patient: str) -> list[str]:
    """The uids of ``patient``'s acquisitions, oldest first.

    Raises
    ------
    NotFoundError
        Unknown patient.
    InputError
        Fewer than two acquisitions.
    """
    pipeline.archive.patient(patient)
    found = sorted(pipeline.archive.find(patient=patient), key=lambda i: i.acquired_at)
    if len(found) < 2:
        raise InputError(
            f"the patient has {len(found)} acquisition(s): a comparison needs at least two"
        )
    return [i.uid for i in found]


def _distance_title(when_a: dt.datetime, when_b: dt.datetime) -> str:
    return f"{when_a:%Y-%m-%d} → {when_b:%Y-%m-%d}: B − A (mm)"


def _landmarks(visit: Visit) -> dict[str, Any]:
    return {n: visit.shape.landmark(n) for n in ("VP", "DL", "DR", "DM")}


def stored_pair(
    pipeline: Pipeline, a: ArchivedVisit, b: ArchivedVisit, plugins: Mapping[str, str]
) -> tuple[StoredComparison, Registration, DistanceMap]:
    """The stored comparison of B onto A (computed and stored when new), its registration and
    distance map; ComparisonRefusedError with why not."""
    if a.visit is None or b.visit is None:
        bad = a if a.visit is None else b
        raise ComparisonRefusedError(f"acquisition {bad.uid}: {bad.reason}")
    stored = stored_comparison(pipeline, a, b, plugin=plugins.get("comparison"))
    reg = registration_of(stored.record)
    return stored, reg, distance_of(stored.record, a.visit.mesh)


def _asymmetry(
    pipeline: Pipeline, v: ArchivedVisit, plugins: Mapping[str, str]
) -> tuple[DistanceMap | None, dict[str, Any]]:
    """A visit's asymmetry map (stored, or computed and stored now) and its entry
    (statistics and provenance, or the reason it was refused)."""
    if v.visit is None:
        return None, {"refused": v.reason}
    stored = stored_asymmetry(pipeline, v, plugin=plugins.get("asymmetry"))
    amap = asymmetry_of(stored.record, v.visit.mesh)
    if amap is None:
        return None, {"refused": stored.record.reason, "provenance": stored.provenance()}
    return amap, {"statistics": amap.statistics(), "provenance": stored.provenance()}


def _pair(
    pipeline: Pipeline,
    a: ArchivedVisit,
    b: ArchivedVisit,
    folder: Path,
    plugins: Mapping[str, str],
) -> dict[str, Any]:
    from rasterserver.comparison_files import write_distance_ply, write_distance_png

    entry: dict[str, Any] = {"a": a.uid, "b": b.uid}
    try:
        stored, reg, dmap = stored_pair(pipeline, a, b, plugins)
    except ComparisonRefusedError as exc:
        return entry | {"refused": str(exc)}
    assert a.visit is not None
    stem = f"distance_{a.uid}-{b.uid}"
    comments = [f"visit A {a.uid} ({a.acquired_at:%Y-%m-%d}), visit B {b.uid} registered onto A"]
    write_distance_ply(dmap, folder / f"{stem}.ply", comments=comments)
    write_distance_png(
        dmap,
        folder / f"{stem}.png",
        title=_distance_title(a.acquired_at, b.acquired_at),
        landmarks=_landmarks(a.visit),
    )
    entry |= {
        "registration": reg.summary(),
        "distance": dmap.statistics(),
        "provenance": stored.provenance(),
        "files": [f"{stem}.ply", f"{stem}.png"],
    }
    entry["_stored"] = (stored, reg, dmap)
    return entry


def _asymmetry_change(
    map_a: DistanceMap, map_b: DistanceMap, reg: Registration, dmap: DistanceMap
) -> DistanceMap:
    """B's asymmetry minus A's, not compared where the distance map was not (arms, hands or
    clothing placed otherwise) when both maps lie on the same trunk (the same margin)."""
    same = dmap.displaced is not None and np.array_equal(dmap.vertices, map_a.vertices)
    return asymmetry_change(map_a, map_b, reg, displaced=dmap.displaced if same else None)


@dataclass(frozen=True)
class TwoVisits:
    """The comparison of two acquisitions in memory (what the HTTP API answers).

    Attributes
    ----------
    a, b : ArchivedVisit
        The earlier and the later visit (B is registered onto A).
    document : dict
        ``a``, ``b``, ``registration``, ``distance`` (statistics), ``asymmetry`` (per uid:
        statistics or the reason) and ``asymmetry_change`` (statistics, or null when a
        visit's asymmetry map was refused); no file names and no times.
    distance : DistanceMap
        B − A along A's normals.
    """

    a: ArchivedVisit
    b: ArchivedVisit
    document: dict[str, Any]
    distance: DistanceMap

    def distance_png(
        self, when_a: dt.datetime | None = None, when_b: dt.datetime | None = None
    ) -> bytes:
        """The colour-mapped distance map (PNG), titled with the visits' dates (or the ones
        given: shifted dates for pseudonymised readers)."""
        from rasterserver.comparison_files import distance_png

        assert self.a.visit is not None
        title = _distance_title(when_a or self.a.acquired_at, when_b or self.b.acquired_at)
        return distance_png(self.distance, title=title, landmarks=_landmarks(self.a.visit))


def compare_two(pipeline: Pipeline, uid_a: str, uid_b: str) -> TwoVisits:
    """Compare two stored acquisitions of one patient (nothing processed; no files written):
    the earlier is A, the later B. The comparison and the asymmetry maps are stored stage
    results, computed and stored on the first request and reused after.

    Raises
    ------
    InputError
        The same acquisition twice, or acquisitions of different patients.
    ComparisonRefusedError
        The visits cannot be compared (the reason).
    NotFoundError
        Unknown or unprocessed acquisitions.
    """
    if uid_a == uid_b:
        raise InputError("a comparison needs two different acquisitions")
    infos = sorted(
        (pipeline.archive.info(uid_a), pipeline.archive.info(uid_b)), key=lambda i: i.acquired_at
    )
    if infos[0].patient_id is None or infos[0].patient_id != infos[1].patient_id:
        raise InputError("the acquisitions belong to different patients")
    a, b = (load_visit(pipeline, i.uid) for i in infos)
    stored, reg, dmap = stored_pair(pipeline, a, b, {})
    (map_a, entry_a), (map_b, entry_b) = _asymmetry(pipeline, a, {}), _asymmetry(pipeline, b, {})
    change = None
    if map_a is not None and map_b is not None:
        change = _asymmetry_change(map_a, map_b, reg, dmap).statistics()
    document = {
        "format": COMPARISON_FORMAT,
        "frame": "world frame of visit A's calibration (mm)",
        "a": a.uid,
        "b": b.uid,
        "registration": reg.summary(),
        "distance": dmap.statistics(),
        "asymmetry": {a.uid: entry_a, b.uid: entry_b},
        "asymmetry_change": change,
        "provenance": stored.provenance(),
    }
    return TwoVisits(a, b, document, dmap)


def trend_visits(pipeline: Pipeline, patient: str) -> list[tuple[str, dt.datetime, Any]]:
    """Each stored acquisition of ``patient``, oldest first, with its analysis parameters
    (None when the analysis found nothing, when the acquisition is not analysed yet, or has no
    raster frame: a gap in the trends, not a reason to show none): ``(uid, acquired_at,
    parameters)``, what :class:`~rasterserver.trends.TrendVisit` takes. Nothing is processed;
    an acquisition whose analysis refused VP gets the parameters measured along the symmetry
    line with VP carried from the nearest visit that found it
    (:func:`~rasterserver.carried_analysis.carried_parameters`: their comparison is
    computed and stored when new, as :func:`compare_two` does).

    Raises
    ------
    NotFoundError
        Unknown patient, or none of the patient's acquisitions has a stored analysis.
    """
    from rasterserver.analysis import AnalysisRefusedError

    pipeline.archive.patient(patient)
    found = sorted(pipeline.archive.find(patient=patient), key=lambda i: i.acquired_at)
    out: list[tuple[str, dt.datetime, Any]] = []
    with_vp: set[str] = set()
    analysed = 0
    for info in found:
        try:
            analysis = acquisition_analysis(pipeline, info.uid)
        except (NotFoundError, InputError):
            out.append((info.uid, info.acquired_at, None))  # not processed, or no raster frame
            continue
        analysed += 1
        try:
            document = analysis.check().document()
        except AnalysisRefusedError:
            out.append((info.uid, info.acquired_at, None))
            continue
        out.append((info.uid, info.acquired_at, document["parameters"]))
        if document["landmarks"].get("VP") is not None:
            with_vp.add(info.uid)
    if found and not analysed:
        raise NotFoundError(
            "none of the patient's acquisitions has a stored analysis yet: process them first "
            "(`rasterserver process --patient ID`, or over HTTP a job)"
        )
    return _carried_trends(pipeline, out, with_vp)


def carry_from_nearest(
    pipeline: Pipeline,
    target: ArchivedVisit,
    sources: Sequence[ArchivedVisit],
    plugins: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """VP carried to ``target`` (a visit without its own) from the nearest of ``sources``.

    The :data:`CARRY_FROM` visits of ``sources`` nearest in time that found VP are tried in
    turn: the two registered (their comparison computed and stored when new, reused after),
    then :func:`~rasterserver.carried_analysis.carried_parameters`.

    Returns
    -------
    dict
        ``carried_parameters``'s entry for ``target``: ``from``, ``vp``,
        ``surface_distance_mm`` and ``parameters``; or ``refused`` (every reason).
    """
    found = [s for s in sources if has_vp(s)]
    if not found:
        return {"refused": "no other visit found its VP"}
    when = target.acquired_at
    reasons = []
    for source in sorted(found, key=lambda s: (abs(s.acquired_at - when), s.acquired_at))[
        :CARRY_FROM
    ]:
        a, b = (source, target) if source.acquired_at <= when else (target, source)
        try:
            stored = stored_pair(pipeline, a, b, dict(plugins or {}))
        except ComparisonRefusedError as exc:
            reasons.append(str(exc))
            continue
        entry = {"a": a.uid, "b": b.uid, "_stored": stored}
        got = carried_parameters(pipeline, [a, b], [entry]).get(target.uid, {})
        if "parameters" in got:
            return got
        reasons.append(got.get("refused", "not carried"))
    return {"refused": "; ".join(reasons)}


def _carried_trends(
    pipeline: Pipeline,
    visits: Sequence[tuple[str, dt.datetime, Any]],
    with_vp: set[str],
) -> list[tuple[str, dt.datetime, Any]]:
    """A patient's trend rows (uid, acquired_at, parameters), a visit without VP given its
    parameters with VP carried (:func:`carry_from_nearest`) from the visits that found it."""
    targets = {uid for uid, _, p in visits if p is not None and uid not in with_vp}
    if not targets or not with_vp:  # nothing to carry: no visit read from the store
        return list(visits)
    loaded: dict[str, ArchivedVisit] = {}

    def visit(uid: str) -> ArchivedVisit:
        if uid not in loaded:
            loaded[uid] = load_visit(pipeline, uid)
        return loaded[uid]

    sources = [(uid, at) for uid, at, _ in visits if uid in with_vp]
    out = []
    for uid, at, parameters in visits:
        if uid in targets:
            nearest = sorted(sources, key=lambda s: (abs(s[1] - at), s[1]))[:CARRY_FROM]
            got = carry_from_nearest(pipeline, visit(uid), [visit(u) for u, _ in nearest])
            parameters = got.get("parameters", parameters)
        out.append((uid, at, parameters))
    return out


def compare_visits(
    pipeline: Pipeline,
    uids: Sequence[str],
    out: Path,
    *,
    process: bool = False,
    plugins: Mapping[str, str] | None = None,
    log: Callable[[str], None] = lambda _line: None,
) -> dict[str, Any]:
    """Compare archived acquisitions of one patient and write the files into ``out``.

    Parameters
    ----------
    pipeline : Pipeline
        The archive's pipeline.
    uids : sequence of str
        Two or more acquisitions (put in time order here).
    out : Path
        The folder to create (it must not exist, or be empty).
    process : bool, optional
        Process acquisitions that have no stored analysis first.
    plugins : Mapping of str to str, optional
        The plugin for the ``comparison`` and ``asymmetry`` stage kinds (their defaults when
        not named).
    log : callable, optional
        Progress lines (no patient data).

    Returns
    -------
    dict
        The ``comparison.json`` document.

    Raises
    ------
    InputError
        Fewer than two acquisitions, acquisitions of different patients, an unusable output
        folder, or the only pair refused (the reason).
    NotFoundError
        Unknown or unprocessed acquisitions.
    """
    from rasterserver.comparison_files import write_distance_png
    from rasterserver.output_files import check_output_folder
    from rasterserver.store.durable import fsync_dir, fsync_file

    if len(set(uids)) < 2:
        raise InputError("a comparison needs two different acquisitions")
    plugins = dict(plugins or {})
    unknown = sorted(set(plugins) - {"comparison", "asymmetry"})
    if unknown:
        raise InputError(
            f"--stage: {', '.join(unknown)} is not a stage of a comparison (comparison, asymmetry)"
        )
    for kind, name in plugins.items():
        stage = pipeline.registry.get(name)
        if stage.stage != kind:
            raise InputError(f"plugin {name!r} implements stage {stage.stage!r}, not {kind!r}")
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"output folder {out}: exists and is not an empty folder")
    check_output_folder(out, what="output folder")
    infos = [pipeline.archive.info(uid) for uid in uids]
    if len({i.patient_id for i in infos}) > 1:
        raise InputError("the acquisitions belong to different patients")
    order = sorted(range(len(uids)), key=lambda k: infos[k].acquired_at)
    visits = []
    for k in order:
        visits.append(load_visit(pipeline, uids[k], process=process))
        log(f"read acquisition {uids[k]}")
    out.parent.mkdir(parents=True, exist_ok=True)
    temp = out.with_name(f".{out.name}.partial-{secrets.token_hex(4)}")
    temp.mkdir()
    try:
        pairs = [(visits[k], visits[k + 1]) for k in range(len(visits) - 1)]
        if len(visits) > 2:
            pairs.append((visits[0], visits[-1]))
        entries = []
        for k, (a, b) in enumerate(pairs, 1):
            entries.append(_pair(pipeline, a, b, temp, plugins))
            log(f"compared pair {k} of {len(pairs)}")
        if len(entries) == 1 and "refused" in entries[0]:
            raise ComparisonRefusedError(entries[0]["refused"])
        asymmetry: dict[str, Any] = {}
        maps: dict[str, DistanceMap] = {}
        for v in visits:
            amap, asymmetry[v.uid] = _asymmetry(pipeline, v, plugins)
            if amap is None:
                continue
            maps[v.uid] = amap
            name = f"asymmetry_{v.uid}.png"
            write_distance_png(amap, temp / name, title=f"asymmetry {v.acquired_at:%Y-%m-%d}")
            asymmetry[v.uid]["file"] = name
        carried = carried_parameters(pipeline, visits, entries)
        for v in visits:  # none of its registered partners found VP: the nearest that did
            if carried.get(v.uid, {}).get("refused") == NO_PARTNER:
                carried[v.uid] = carry_from_nearest(pipeline, v, visits, plugins)
        if carried:
            log(
                f"VP carried to {sum('from' in c for c in carried.values())} of {len(carried)} "
                "visits without their own"
            )
        for entry in entries:
            kept = entry.pop("_stored", None)
            if kept is not None and entry["a"] in maps and entry["b"] in maps:
                change = _asymmetry_change(maps[entry["a"]], maps[entry["b"]], kept[1], kept[2])
                entry["asymmetry_change"] = change.statistics()
        table = trends(
            [
                TrendVisit(
                    v.uid,
                    v.acquired_at,
                    carried.get(v.uid, {}).get("parameters") or v.parameters,
                )
                for v in visits
            ]
        )
        write_trends(table, temp)
        write_trends_plot(table, temp / "trends.png")
        document = {
            "format": COMPARISON_FORMAT,
            "frame": "world frame of each pair's first visit's calibration (mm)",
            "visits": [
                {"uid": v.uid, "acquired_at": v.acquired_at.isoformat(), "reason": v.reason}
                for v in visits
            ],
            "pairs": entries,
            "asymmetry": asymmetry,
            "carried_vp": {
                uid: {k: v for k, v in c.items() if k != "parameters"} for uid, c in carried.items()
            },
        }
        (temp / "comparison.json").write_text(
            json.dumps(document, indent=2, allow_nan=False) + "\n", encoding="utf-8"
        )
        write_report(temp, visits, entries, table, asymmetry, carried)
        for path in temp.iterdir():
            fsync_file(path)
        if out.exists():
            out.rmdir()  # empty, checked above
        os.replace(temp, out)
        fsync_dir(out.parent)
    except OSError as exc:
        raise InputError(f"cannot write {out}: {exc.strerror or exc}") from None
    finally:
        if temp.exists():
            shutil.rmtree(temp, ignore_errors=True)
    return document
